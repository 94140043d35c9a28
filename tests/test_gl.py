"""The one GL stack: renderers of every kind (render-and-compare, the evaluator's depth windows,
pictures, the generator's lit scenes) live side by side in one process, each closed in any order
without breaking the others; the evaluator's window pass samples the same pixels as the crops'."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cosy_lite.render.renderer import GlRenderer

BOX, SPHERE = 1, 2
K = np.array([[220.0, 0.0, 81.3], [0.0, 215.0, 58.9], [0.0, 0.0, 1.0]])
RES = (120, 160)  # (H, W)


def _T(t, rotvec=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    if any(rotvec):
        T[:3, :3] = trimesh.transformations.rotation_matrix(np.linalg.norm(rotvec), rotvec)[:3, :3]
    T[:3, 3] = t
    return T


def _meshes() -> dict[int, trimesh.Trimesh]:
    box = trimesh.creation.box(extents=(0.10, 0.08, 0.06))
    box.visual.vertex_colors = np.tile((200, 30, 60, 255), (len(box.vertices), 1))
    return {BOX: box, SPHERE: trimesh.creation.icosphere(subdivisions=2, radius=0.05)}


POSES = np.stack([_T((0.01, -0.02, 0.5), (0.3, 0.5, 0.1)), _T((-0.03, 0.01, 0.6), (1.0, -0.2, 0.7))])


class Kinds:
    """One renderer of each kind, and what each renders (a function of the renderer)."""

    def __init__(self, order: list[str]):
        from cosy_lite.render.pyrender_scene import OffscreenSceneRenderer

        meshes = _meshes()
        make = {
            "render_and_compare": lambda: GlRenderer(meshes, shading="headlight"),
            "pictures": lambda: GlRenderer(meshes),
            "lit_scenes": lambda: OffscreenSceneRenderer(RES[1], RES[0]),
        }
        self.renderers = {}
        for kind in order:  # each renders once on creation: its context exists before the next one's
            self.renderers[kind] = make[kind]()
            self.render(kind)

    def render(self, kind: str) -> list[np.ndarray]:
        r = self.renderers[kind]
        if kind == "render_and_compare":
            out = r.render([BOX, SPHERE], POSES, K, RES)
            return [out.rgb, out.depth]
        if kind == "pictures":
            return [r.render([SPHERE, BOX], POSES, K, RES, depth_only=True).depth]
        return list(r.render(_lit_scene(), flags=0))

    def close_all(self) -> None:
        for r in self.renderers.values():
            r.close()


def _lit_scene():
    """A lit box, as the generator's scenes: pyrender materials, a point light."""
    from cosy_lite.geometry.transforms import look_at
    from cosy_lite.render.pyrender_scene import camera_node_pose, intrinsics_camera, pyrender_module

    pyrender = pyrender_module()
    scene = pyrender.Scene(bg_color=[0, 0, 0, 0], ambient_light=[0.3, 0.3, 0.3])
    scene.add(pyrender.Mesh.from_trimesh(_meshes()[BOX]), pose=np.eye(4))
    scene.add(pyrender.PointLight(color=np.ones(3), intensity=5.0), pose=_T((0.2, -0.3, 0.8)))
    scene.add(intrinsics_camera(K), pose=camera_node_pose(look_at([0.3, -0.3, 0.4], [0.0, 0.0, 0.0])))
    return scene


ORDER = ["render_and_compare", "pictures", "lit_scenes"]


@pytest.fixture(scope="module", autouse=True)
def egl_available():
    from cosy_lite.render.gl import EglContext

    try:
        EglContext().destroy()
    except Exception as e:  # no EGL / OpenGL on this machine
        pytest.skip(f"offscreen rendering unavailable: {e}")


@pytest.mark.parametrize("created", ["forward", "reversed"])
@pytest.mark.parametrize("closed", ORDER)
def test_closing_one_renderer_leaves_the_others_rendering_the_same(closed: str, created: str):
    kinds = Kinds(ORDER if created == "forward" else ORDER[::-1])
    try:
        before = {kind: kinds.render(kind) for kind in ORDER}
        assert all(np.count_nonzero(a) > 100 for arrays in before.values() for a in arrays)
        kinds.renderers[closed].close()
        for kind in ORDER:
            if kind != closed:
                for a, b in zip(kinds.render(kind), before[kind]):
                    np.testing.assert_array_equal(a, b, err_msg=f"{kind} after closing {closed}")
        if closed != "lit_scenes":  # a closed GlRenderer makes a new context on its next render
            for a, b in zip(kinds.render(closed), before[closed]):
                np.testing.assert_array_equal(a, b)
    finally:
        kinds.close_all()
