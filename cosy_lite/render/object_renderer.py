"""Render object models at given poses: RGB, depth and mask per item (OpenCV camera, metres)."""

from __future__ import annotations

import numpy as np
import trimesh

from cosy_lite.render.gl import CV_TO_GL, intrinsics_camera, pyrender_module


class ObjectRenderer:
    """Renders single objects on black, flat-shaded (texture / vertex colours as they are).

    Args:
        meshes: obj_id -> trimesh.Trimesh in metres (uploaded to GL lazily, once).
    """

    def __init__(self, meshes: dict[int, trimesh.Trimesh]):
        self.meshes = meshes
        self._pr_meshes: dict[int, object] = {}
        self._renderers: dict[tuple[int, int], object] = {}

    def _mesh(self, obj_id: int):
        if obj_id not in self._pr_meshes:
            if obj_id not in self.meshes:
                raise KeyError(f"no mesh for obj_id {obj_id}; known: {sorted(self.meshes)}")
            self._pr_meshes[obj_id] = pyrender_module().Mesh.from_trimesh(self.meshes[obj_id])
        return self._pr_meshes[obj_id]

    def _renderer(self, width: int, height: int):
        if (width, height) not in self._renderers:
            self._renderers[(width, height)] = pyrender_module().OffscreenRenderer(width, height)
        return self._renderers[(width, height)]

    def render(
        self, obj_ids: list[int], TCO: np.ndarray, K: np.ndarray, width: int, height: int, depth_only: bool = False
    ) -> tuple[np.ndarray | None, np.ndarray]:
        """Render B objects, each alone.

        Args:
            obj_ids: [B] object ids; TCO: [B,4,4] object-to-camera (m); K: [B,3,3] or [3,3].
        Returns:
            rgb [B,H,W,3] uint8 (None if depth_only) and depth [B,H,W] float32 metres (0 = background).
        """
        pyrender = pyrender_module()
        TCO = np.asarray(TCO, dtype=np.float64).reshape(-1, 4, 4)
        Ks = np.broadcast_to(np.asarray(K, dtype=np.float64), (len(obj_ids), 3, 3))
        renderer = self._renderer(width, height)
        flags = pyrender.RenderFlags.DEPTH_ONLY if depth_only else pyrender.RenderFlags.FLAT
        rgbs, depths = [], []
        for obj_id, T, Ki in zip(obj_ids, TCO, Ks):
            scene = pyrender.Scene(bg_color=[0, 0, 0, 0], ambient_light=[1.0, 1.0, 1.0])
            scene.add(self._mesh(int(obj_id)), pose=CV_TO_GL @ T)
            scene.add(intrinsics_camera(Ki), pose=np.eye(4))
            out = renderer.render(scene, flags=flags)
            if depth_only:
                depths.append(out.copy())
            else:
                rgbs.append(out[0][:, :, :3].copy())
                depths.append(out[1].copy())
        return (None if depth_only else np.stack(rgbs)), np.stack(depths)

    def delete(self) -> None:
        for r in self._renderers.values():
            r.delete()
        self._renderers.clear()
