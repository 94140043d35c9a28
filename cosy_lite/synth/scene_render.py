"""Render one synthetic scene (a settled layout) from many cameras with pyrender.

Per view: the lit RGB image and depth of the whole scene (objects, distractors, textured room),
then the depth of every annotated instance alone (for its full mask and visibility).
World frame: z up, floor at z = 0, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from cosy_lite.render.pyrender_scene import OffscreenSceneRenderer, camera_node_pose, intrinsics_camera, pyrender_module
from cosy_lite.synth.textures import random_texture


@dataclass
class LightingConfig:
    """Random lights and materials (ranges sampled uniformly per scene)."""

    ambient: tuple[float, float] = (0.15, 0.5)
    point_intensity: tuple[float, float] = (4.0, 25.0)  # pyrender point-light intensity
    point_height: tuple[float, float] = (0.8, 2.0)  # metres above the floor
    point_radius: float = 1.2  # horizontal offset of the light from the centre, metres
    light_saturation: float = 0.3  # 0 = white light, 1 = fully saturated colours
    roughness: tuple[float, float] = (0.3, 1.0)
    metallic: tuple[float, float] = (0.0, 0.4)
    room_half_size: float = 1.6  # metres
    room_height: float = 1.6
    texture_repeats: tuple[float, float] = (1.0, 6.0)


@dataclass
class PlacedMesh:
    """A mesh instance in the scene (``mesh`` in metres, its frame = object frame)."""

    key: str
    mesh: trimesh.Trimesh
    T_WO: np.ndarray  # [4,4]
    annotated: bool  # False for distractors


def _quad(width: float, height: float, repeats: float, texture: np.ndarray) -> trimesh.Trimesh:
    """A textured rectangle in the XY plane centred at the origin, normal +z."""
    w, h = width / 2, height / 2
    v = np.array([[-w, -h, 0], [w, -h, 0], [w, h, 0], [-w, h, 0]], dtype=np.float64)
    uv = np.array([[0, 0], [repeats, 0], [repeats, repeats * height / width], [0, repeats * height / width]])
    from PIL import Image

    visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(texture))
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], visual=visual, process=False)


def _random_colour(rng: np.random.Generator, saturation: float) -> np.ndarray:
    c = 1.0 - saturation * rng.random(3)
    return c / c.max()


class SceneRenderer:
    """Offscreen renderer reused across scenes (one GL context of the project's stack; object meshes
    uploaded once)."""

    def __init__(self, width: int, height: int):
        self.width, self.height = width, height
        self._renderer = OffscreenSceneRenderer(width, height)
        self._meshes: dict[str, object] = {}

    def _pyrender_mesh(self, key: str, mesh: trimesh.Trimesh):
        if key not in self._meshes:
            self._meshes[key] = pyrender_module().Mesh.from_trimesh(mesh, smooth=True)
        return self._meshes[key]

    def render_views(
        self,
        placed: list[PlacedMesh],
        T_CWs: list[np.ndarray],
        K: np.ndarray,
        rng: np.random.Generator,
        light: LightingConfig,
    ) -> list[tuple[np.ndarray, np.ndarray, list[np.ndarray]]]:
        """Render every camera view of one layout.

        Returns per view: rgb [H,W,3] uint8, depth [H,W] float32 metres, and the depth of each
        annotated instance alone (in the order of ``placed`` filtered by ``annotated``).
        """
        pyrender = pyrender_module()
        scene = pyrender.Scene(
            bg_color=[0, 0, 0, 0],
            ambient_light=np.full(3, rng.uniform(*light.ambient)) * _random_colour(rng, light.light_saturation),
        )
        for p in placed:
            m = self._pyrender_mesh(p.key, p.mesh)
            for prim in m.primitives:
                prim.material.roughnessFactor = float(rng.uniform(*light.roughness))
                prim.material.metallicFactor = float(rng.uniform(*light.metallic))
            scene.add(m, pose=p.T_WO)
        self._add_room(scene, rng, light)
        angle = rng.uniform(0, 2 * np.pi)
        lpos = [light.point_radius * rng.random() * np.cos(angle), light.point_radius * rng.random() * np.sin(angle),
                rng.uniform(*light.point_height)]
        L = np.eye(4)
        L[:3, 3] = lpos
        scene.add(pyrender.PointLight(color=_random_colour(rng, light.light_saturation),
                                      intensity=rng.uniform(*light.point_intensity)), pose=L)
        cam_node = scene.add(intrinsics_camera(K), pose=np.eye(4))

        solo = pyrender.Scene(bg_color=[0, 0, 0, 0])
        solo_cam = solo.add(intrinsics_camera(K), pose=np.eye(4))
        annotated = [p for p in placed if p.annotated]

        out = []
        for T_CW in T_CWs:
            pose = camera_node_pose(T_CW)
            scene.set_pose(cam_node, pose)
            rgb, depth = self._renderer.render(scene)
            solo.set_pose(solo_cam, pose)
            depths = []
            for p in annotated:
                node = solo.add(self._pyrender_mesh(p.key, p.mesh), pose=p.T_WO)
                depths.append(self._renderer.render(solo, flags=pyrender.RenderFlags.DEPTH_ONLY).copy())
                solo.remove_node(node)
            out.append((rgb.copy(), depth.copy(), depths))
        return out

    def _add_room(self, scene, rng: np.random.Generator, light: LightingConfig) -> None:
        pyrender = pyrender_module()
        s, hgt = light.room_half_size, light.room_height
        floor = _quad(2 * s, 2 * s, rng.uniform(*light.texture_repeats), random_texture(rng))
        scene.add(pyrender.Mesh.from_trimesh(floor), pose=np.eye(4))
        wall_tex = random_texture(rng)
        reps = rng.uniform(*light.texture_repeats)
        for k in range(4):
            wall = _quad(2 * s, hgt, reps, wall_tex)
            yaw = k * np.pi / 2
            # Rotate the quad upright (normal pointing to the room centre) and push it to the wall.
            R_up = trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0])
            R_yaw = trimesh.transformations.rotation_matrix(yaw, [0, 0, 1])
            T = R_yaw @ trimesh.transformations.translation_matrix([0, -s, hgt / 2]) @ R_up
            scene.add(pyrender.Mesh.from_trimesh(wall), pose=T)

    def delete(self) -> None:
        self._renderer.close()
