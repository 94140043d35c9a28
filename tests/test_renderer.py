"""Batched renderer: geometry against projection, analytic depth, textures, batching, errors."""

from __future__ import annotations

import multiprocessing as mp
import pickle

import cv2
import numpy as np
import pytest
import trimesh
from PIL import Image

from cosy_lite.render.renderer import GlRenderer, RenderOutput, check_render_inputs

SPHERE, BOX, QUAD, YCB = 1, 2, 3, 4
BOX_EXTENTS = (0.10, 0.08, 0.06)
QUAD_HALF = 0.05  # m
BOX_RGBA = (200, 30, 60, 255)
RES = (240, 320)
K = np.array([[410.0, 0.0, 166.3], [0.0, 395.0, 118.9], [0.0, 0.0, 1.0]])  # crop-like, fx != fy, off-centre


def _rot(axis: str, deg: float) -> np.ndarray:
    return cv2.Rodrigues(np.radians(deg) * np.eye(3)["xyz".index(axis)])[0]


def _T(R: np.ndarray = np.eye(3), t=(0.0, 0.0, 0.5)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _quad_texture() -> Image.Image:
    """64x64 RGB, 4x4 blocks of 16 px, each its own colour."""
    blocks = np.array([[(40 * i + 20, 60 * j + 10, 255 - 50 * i - 10 * j) for j in range(4)] for i in range(4)])
    blocks = blocks.astype(np.uint8)
    return Image.fromarray(np.kron(blocks, np.ones((16, 16, 1), np.uint8)))


def _meshes() -> dict[int, trimesh.Trimesh]:
    from cosy_lite.synth.objects import load_ycb_mesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.06)
    rgb = (sphere.vertices / 0.12 + 0.5) * 255
    sphere.visual.vertex_colors = np.column_stack([rgb, np.full(len(rgb), 255)]).astype(np.uint8)
    box = trimesh.creation.box(extents=BOX_EXTENTS)
    box.visual.vertex_colors = np.tile(BOX_RGBA, (len(box.vertices), 1))
    a = QUAD_HALF
    quad = trimesh.Trimesh(
        [[-a, -a, 0], [a, -a, 0], [a, a, 0], [-a, a, 0]], [[0, 1, 2], [0, 2, 3]], process=False,
        visual=trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1], [0, 1]], image=_quad_texture()),
    )
    return {SPHERE: sphere, BOX: box, QUAD: quad, YCB: load_ycb_mesh(2)}  # YCB: the textured cracker box


@pytest.fixture(scope="module")
def meshes() -> dict[int, trimesh.Trimesh]:
    return _meshes()


@pytest.fixture(scope="module")
def renderer(meshes):
    with GlRenderer(meshes) as r:
        yield r


def _filled_mask(mesh: trimesh.Trimesh, T: np.ndarray, K: np.ndarray, resolution) -> np.ndarray:
    """Every face projected and filled with cv2 (pixel (r, c) has its centre at (c + 0.5, r + 0.5))."""
    pts = mesh.vertices @ T[:3, :3].T + T[:3, 3]
    uv = pts @ K.T
    uv = uv[:, :2] / uv[:, 2:]
    fixed = np.round((uv - 0.5) * 16).astype(np.int32)  # shift=4: 1/16 px
    mask = np.zeros(resolution, np.uint8)
    for f in mesh.faces:
        cv2.fillConvexPoly(mask, fixed[f], 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


def _centroid(mask: np.ndarray) -> np.ndarray:
    r, c = np.nonzero(mask)
    return np.array([c.mean() + 0.5, r.mean() + 0.5])


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return (a & b).sum() / (a | b).sum()


@pytest.mark.parametrize("obj_id", [SPHERE, YCB])
def test_mask_is_where_the_projected_mesh_is(renderer, meshes, obj_id):
    T = _T(_rot("x", 35) @ _rot("z", 20), (0.012, -0.008, 0.45))
    out = renderer.render([obj_id], T[None], K, RES)
    mask = out.mask[0]
    filled = _filled_mask(meshes[obj_id], T, K, RES)
    assert mask.sum() > 5000
    assert _iou(mask, filled) >= 0.97
    assert np.abs(_centroid(mask) - _centroid(filled)).max() < 0.5
    if obj_id == SPHERE:  # the origin projects onto the centre of the disc
        origin = K @ T[:3, 3]
        assert np.abs(_centroid(mask) - origin[:2] / origin[2]).max() < 1.0
    # the mask's box is the projected vertices' box, to a pixel
    uv = (meshes[obj_id].vertices @ T[:3, :3].T + T[:3, 3]) @ K.T
    uv = uv[:, :2] / uv[:, 2:]
    rows, cols = np.nonzero(mask)
    box = [cols.min(), rows.min(), cols.max() + 1, rows.max() + 1]
    np.testing.assert_allclose(box, [*uv.min(0), *uv.max(0)], atol=1.0)


@pytest.mark.parametrize("cull", [None, True, False])
def test_depth_of_a_box_is_its_front_face(meshes, cull):
    """Head-on, only the front face is seen: depth = t_z - extent_z / 2 everywhere on the mask
    (with forced culling this also checks the front-face winding convention)."""
    T = _T(t=(0.0, 0.0, 0.7))
    with GlRenderer({BOX: meshes[BOX]}, cull_back_faces=cull) as r:
        out = r.render([BOX], T[None], K, RES)
    depth, mask = out.depth[0], out.mask[0]
    assert 0.9 * 410 * 0.10 / 0.67 * 395 * 0.08 / 0.67 < mask.sum()
    np.testing.assert_allclose(depth[mask], 0.7 - BOX_EXTENTS[2] / 2, atol=1e-5)
    assert np.all(depth[~mask] == 0)
    np.testing.assert_array_equal(out.rgb[0][mask], np.tile(BOX_RGBA[:3], (mask.sum(), 1)))
    assert np.all(out.rgb[0][~mask] == 0)


def test_culling_is_not_used_where_it_would_show(meshes):
    """An inward-wound sphere: forced culling shows its far side; the default (per-mesh check)
    draws it two-sided, like cull_back_faces=False."""
    inverted = meshes[SPHERE].copy()
    inverted.invert()
    T = _T(t=(0.0, 0.0, 0.5))[None]
    depth = {}
    for cull in (None, False, True):
        with GlRenderer({SPHERE: inverted}, cull_back_faces=cull) as r:
            depth[cull] = r.render([SPHERE], T, K, RES).depth[0]
    np.testing.assert_array_equal(depth[None], depth[False])
    centre = depth[False][int(K[1, 2]), int(K[0, 2])]
    assert centre == pytest.approx(0.5 - 0.06, abs=1e-3)
    assert depth[True][int(K[1, 2]), int(K[0, 2])] == pytest.approx(0.5 + 0.06, abs=1e-3)


def test_depth_of_a_tilted_plane_is_the_ray_intersection(renderer):
    R = _rot("x", 40) @ _rot("y", -25)
    T = _T(R, (0.01, -0.01, 0.6))
    out = renderer.render([QUAD], T[None], K, RES)
    mask = out.mask[0]
    rows, cols = np.nonzero(mask)
    rays = np.column_stack([cols + 0.5, rows + 0.5, np.ones(len(rows))]) @ np.linalg.inv(K).T  # z = 1
    n = R[:, 2]
    z = (n @ T[:3, 3]) / (rays @ n)
    assert len(z) > 3000
    np.testing.assert_allclose(out.depth[0][mask], z, atol=1e-4)  # 0.1 mm


def test_texture_colours_are_trimesh_texture(renderer, meshes):
    """Fronto-parallel textured quad: each block centre has the texture's colour at its UV."""
    z = 0.5
    out = renderer.render([QUAD], _T(t=(0.0, 0.0, z))[None], K, RES)
    rgb = out.rgb[0]
    image = meshes[QUAD].visual.material.image
    checked = 0
    for bu in range(4):
        for bv in range(4):
            uv = np.array([(bu + 0.5) / 4, (bv + 0.5) / 4])
            xy = (uv * 2 - 1) * QUAD_HALF  # object x, y = camera x, y (identity rotation)
            c, r = (K[:2, :2] @ xy / z + K[:2, 2]).astype(int)
            expected = trimesh.visual.color.uv_to_color(uv[None], image)[0, :3]
            np.testing.assert_array_equal(rgb[r, c], expected)
            checked += 1
    assert checked == 16
    # the 16 block colours fill the quad but for the bilinear blends along block borders
    colours, counts = np.unique(rgb[out.mask[0]], axis=0, return_counts=True)
    top = colours[np.argsort(counts)[-16:]]
    texture_colours = np.unique(np.asarray(image).reshape(-1, 3), axis=0)
    np.testing.assert_array_equal(np.unique(top, axis=0), texture_colours)
    assert np.sort(counts)[-16:].sum() > 0.8 * out.mask[0].sum()


def test_face_colours_and_a_material_colour():
    box = trimesh.creation.box(extents=BOX_EXTENTS)
    facing = box.face_normals[:, 2] < -0.9  # the two triangles seen by a camera looking along +z
    box.visual.face_colors = np.where(facing[:, None], [[0, 255, 0, 255]], [[255, 0, 0, 255]])
    plain = trimesh.creation.box(extents=BOX_EXTENTS)
    material = trimesh.visual.material.SimpleMaterial(diffuse=[10, 200, 30, 255])
    plain.visual = trimesh.visual.TextureVisuals(material=material)
    with GlRenderer({1: box, 2: plain}) as r:
        out = r.render([1, 2], np.stack([_T(t=(0.0, 0.0, 0.7))] * 2), K, RES)
    for i, rgb in enumerate([(0, 255, 0), (10, 200, 30)]):
        assert out.mask[i].sum() > 1000
        np.testing.assert_array_equal(np.unique(out.rgb[i][out.mask[i]], axis=0), [rgb])


def test_textured_ycb_model_is_not_one_colour(renderer):
    out = renderer.render([YCB], _T(_rot("x", 100), (0.0, 0.0, 0.4))[None], K, RES)
    pixels = out.rgb[0][out.mask[0]].astype(float)
    assert len(np.unique(pixels, axis=0)) > 500
    assert pixels.std(axis=0).min() > 20  # the red, white and yellow print
    assert pixels.mean() > 60  # texture colours as they are (not darkened by a lighting factor)


def _batch():
    ids = [YCB, SPHERE, QUAD, BOX, YCB, SPHERE, BOX]
    rng = np.random.default_rng(3)
    T = np.stack([
        _T(cv2.Rodrigues(rng.normal(size=3))[0], (*rng.uniform(-0.03, 0.03, 2), rng.uniform(0.35, 0.7))) for _ in ids
    ])
    T[5, 2, 3] = -0.5  # behind the camera
    Ks = np.stack([K * [[s], [s], [1]] for s in rng.uniform(0.8, 1.2, len(ids))])
    return ids, T, Ks


def test_batch_equals_items_one_by_one(renderer):
    ids, T, Ks = _batch()
    batch = renderer.render(ids, T, Ks, RES)
    for i in range(len(ids)):
        one = renderer.render([ids[i]], T[i : i + 1], Ks[i], RES)
        np.testing.assert_array_equal(batch.rgb[i], one.rgb[0])
        np.testing.assert_array_equal(batch.depth[i], one.depth[0])
    only = renderer.render(ids, T, Ks, RES, depth_only=True)
    assert only.rgb is None
    np.testing.assert_array_equal(only.depth, batch.depth)
    np.testing.assert_array_equal(batch.mask, batch.depth > 0)
    # more crops than framebuffers in flight: drawn in groups, same pixels
    r = GlRenderer(renderer.meshes, max_in_flight=3)
    np.testing.assert_array_equal(r.render(ids, T, Ks, RES).rgb, batch.rgb)
    r.close()


def test_object_behind_the_camera_renders_empty(renderer):
    T = np.stack([_T(t=(0.0, 0.0, -0.5)), _T(t=(0.0, 0.0, 0.0)), _T(t=(0.0, 0.0, 0.5))])
    out = renderer.render([SPHERE] * 3, T, K, RES)
    assert out.mask[:2].sum() == 0 and np.all(out.depth[:2] == 0) and np.all(out.rgb[:2] == 0)
    assert out.mask[2].sum() > 1000


def test_render_tensors(renderer):
    import torch

    ids, T, Ks = _batch()
    rgb, depth = renderer.render_tensors(ids, torch.from_numpy(T).float(), torch.from_numpy(Ks), RES, device="cpu")
    out = renderer.render(ids, T.astype(np.float32), Ks, RES)
    assert rgb.shape == (7, 3, *RES) and rgb.dtype == torch.float32 and depth.shape == (7, 1, *RES)
    np.testing.assert_allclose(rgb.permute(0, 2, 3, 1).numpy() * 255, out.rgb, atol=1e-3)
    np.testing.assert_array_equal(depth[:, 0].numpy(), out.depth)
    rgb, depth = renderer.render_tensors(ids, T, Ks, RES, depth_only=True)
    assert rgb is None and depth.shape == (7, 1, *RES)


def test_errors_name_the_problem(renderer):
    T = _T()[None]
    with pytest.raises(KeyError, match=r"unknown obj_id 99; known: \[1, 2, 3, 4\]"):
        renderer.render([99], T, K, RES)
    bad = np.stack([_T(), _T()])
    bad[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match=r"NaN/inf at batch index \[1\]"):
        renderer.render([SPHERE, SPHERE], bad, K, RES)
    with pytest.raises(ValueError, match=r"K must be \[3,3\] or \[B,3,3\].*\(2, 3\)"):
        renderer.render([SPHERE], T, K[:2], RES)
    with pytest.raises(ValueError, match=r"K must be .*\(3, 3, 3\)"):
        renderer.render([SPHERE], T, np.stack([K] * 3), RES)
    with pytest.raises(ValueError, match=r"TCO must be \[B,4,4\] with B = len\(obj_ids\) = 2"):
        renderer.render([SPHERE, BOX], T, K, RES)
    with pytest.raises(ValueError, match="resolution"):
        check_render_inputs([SPHERE], T, K, (0, 320))
    with pytest.raises(ValueError, match="needs meshes or a models_dir"):
        GlRenderer()
    out = renderer.render([], np.zeros((0, 4, 4)), K, RES)
    assert isinstance(out, RenderOutput) and out.rgb.shape == (0, *RES, 3)


def test_from_dataset_reads_bop_models(tmp_path):
    from bop_fixtures import BOX_MM, write_tiny_bop

    from cosy_lite.bop.dataset import BopDataset

    r = GlRenderer.from_dataset(BopDataset(write_tiny_bop(tmp_path)), eval_models=True)
    out = r.render([1, 2], np.stack([_T(t=(0, 0, 0.8))] * 2), K, RES)
    for i, obj_id in enumerate((1, 2)):  # box models in mm, read in metres: front face at 0.8 - z/2
        np.testing.assert_allclose(out.depth[i][out.mask[i]], 0.8 - BOX_MM[obj_id][2] / 2000, atol=1e-5)
    with pytest.raises(KeyError, match=r"unknown obj_id 7 \(no .*obj_000007.ply\); known: \[1, 2\]"):
        r.render([7], _T()[None], K, RES)
    r.close()


def test_pickled_renderer_renders_the_same(renderer):
    ids, T, Ks = _batch()
    before = renderer.render(ids, T, Ks, RES)
    copy = pickle.loads(pickle.dumps(renderer))  # as a DataLoader worker receives it: no GL state
    assert copy._gl is None
    np.testing.assert_array_equal(copy.render(ids, T, Ks, RES).rgb, before.rgb)
    copy.close()


def _render_in_child(renderer, queue) -> None:
    try:
        renderer.render([SPHERE], _T()[None], K, RES)
        queue.put("rendered")
    except RuntimeError as e:
        queue.put(str(e))


def test_forked_child_of_a_rendering_process_raises_instead_of_hanging(renderer):
    """Mesa's EGL hangs in a child forked after the parent made a context: the renderer (whose
    inherited GL state must not even be freed there) raises and names the remedy."""
    renderer.render([SPHERE], _T()[None], K, RES)  # this process has an EGL context
    ctx = mp.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_render_in_child, args=(renderer, queue))
    child.start()
    try:
        message = queue.get(timeout=60)
    finally:
        child.join(timeout=10)
        child.kill()
    assert "forked from process" in message and "spawn" in message


def test_closing_a_renderer_leaves_other_contexts_alive(renderer, meshes):
    """close() and garbage collection destroy only the renderer's own context (no eglTerminate)."""
    import gc

    other = GlRenderer({BOX: meshes[BOX]})
    T = _T(t=(0.0, 0.0, 0.6))[None]
    before = other.render([BOX], T, K, RES, depth_only=True).depth
    try:
        for close in (True, False):
            r = GlRenderer({BOX: meshes[BOX]})
            r.render([BOX], T, K, RES)
            if close:
                r.close()
            del r
            gc.collect()
            after = other.render([BOX], T, K, RES, depth_only=True).depth  # fails if the display was terminated
            np.testing.assert_array_equal(after, before)
    finally:
        other.close()


def _pyrender_offscreen_depth(mesh: trimesh.Trimesh, TCO: np.ndarray, K: np.ndarray, resolution) -> np.ndarray:
    """Depth [H,W] of ``mesh`` at ``TCO`` rendered by pyrender's own ``OffscreenRenderer`` (what a user's
    code may do in the same process), whose ``delete()`` terminates the EGL display."""
    from cosy_lite.render.gl import CV_TO_GL
    from cosy_lite.render.pyrender_scene import intrinsics_camera, pyrender_module

    pyrender = pyrender_module()
    scene = pyrender.Scene(bg_color=[0, 0, 0, 0], ambient_light=[1.0, 1.0, 1.0])
    scene.add(pyrender.Mesh.from_trimesh(mesh), pose=CV_TO_GL @ TCO)
    scene.add(intrinsics_camera(K), pose=np.eye(4))
    offscreen = pyrender.OffscreenRenderer(resolution[1], resolution[0])
    try:
        return offscreen.render(scene, flags=pyrender.RenderFlags.DEPTH_ONLY).copy()
    finally:
        offscreen.delete()  # eglTerminate


def test_survives_pyrender_terminating_the_display(renderer, meshes):
    """pyrender's OffscreenRenderer.delete() calls eglTerminate: the renderer starts a new context."""
    T = _T(_rot("y", 30), (0.0, 0.0, 0.5))[None]
    before = renderer.render([BOX], T, K, RES)
    depth = _pyrender_offscreen_depth(meshes[BOX], T[0], K, RES)[None]
    after = renderer.render([BOX], T, K, RES)
    np.testing.assert_array_equal(after.depth, before.depth)
    both = before.mask[0] & (depth[0] > 0)  # and pyrender agrees (it samples 4x MSAA, so edges differ)
    assert _iou(before.mask[0], depth[0] > 0) > 0.97
    np.testing.assert_allclose(before.depth[0][both], depth[0][both], atol=1e-3)  # MSAA: depth off-centre


def test_headlight_shading_follows_the_face_orientation(meshes):
    """A box face seen head-on keeps its colour; turned by 60 deg about y it gets
    ambient + (1 - ambient) cos(angle) of it (the light sits at the camera); depth is the flat render's."""
    from cosy_lite.render.renderer import AMBIENT

    head_on, turned = _T(t=(0.0, 0.0, 0.7)), _T(_rot("y", 60.0), t=(0.0, 0.0, 0.7))
    with GlRenderer({BOX: meshes[BOX]}) as flat, GlRenderer({BOX: meshes[BOX]}, shading="headlight") as lit:
        poses = np.stack([head_on, turned])
        a, b = flat.render([BOX, BOX], poses, K, RES), lit.render([BOX, BOX], poses, K, RES)
    np.testing.assert_array_equal(a.depth, b.depth)
    m = b.mask[0]
    np.testing.assert_allclose(b.rgb[0][m].mean(0), BOX_RGBA[:3], atol=1.5)  # normal . view ~ 1 at the centre
    # turned: two faces visible, at 60 and 30 deg to the viewing rays (rays off-axis by a few degrees)
    levels = np.unique(np.round(b.rgb[1][b.mask[1]][:, 0] / BOX_RGBA[0], 1))
    for cos in (np.cos(np.radians(60)), np.cos(np.radians(30))):
        assert np.any(np.abs(levels - (AMBIENT + (1 - AMBIENT) * cos)) <= 0.1), (levels, cos)
    assert np.all(b.rgb[1][b.mask[1]] <= np.array(BOX_RGBA[:3]) + 1)
    with pytest.raises(ValueError, match="shading must be one of"):
        GlRenderer({BOX: meshes[BOX]}, shading="phong")
