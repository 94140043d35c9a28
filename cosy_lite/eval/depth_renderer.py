"""Depth of single objects inside image windows, for VSD.

VSD only needs the depth of one object at a time, and only where the object is: each render
covers only a *window* of the image (the projected bounds of the object, see
:func:`object_window`), with the full image's projection, so the pixels inside the window are
exactly those of a full-image render (no principal-point shift, no resampling). The rasteriser is
:func:`cosy_lite.render.depth_raster.rasterize_depth` (CPU, no GL context: the toolkit's
conventions, two-sided faces); this module adds the windows and the near clipping plane.

Conventions (as bop_toolkit's ``renderer_vispy``): OpenCV camera, the pixel of row ``r``, column
``c`` is sampled at ``(u, v) = (c + 0.5, r + 0.5)``; depth = the camera Z of the visible surface
(m), 0 where the object is not rendered.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Window:
    """Image window ``[x0, x1) x [y0, y1)`` in pixels (columns x, rows y)."""

    x0: int
    y0: int
    x1: int
    y1: int

    @property
    def empty(self) -> bool:
        return self.x1 <= self.x0 or self.y1 <= self.y0

    @property
    def shape(self) -> tuple[int, int]:
        return max(0, self.y1 - self.y0), max(0, self.x1 - self.x0)

    def union(self, other: Window) -> Window:
        if self.empty:
            return other
        if other.empty:
            return self
        return Window(min(self.x0, other.x0), min(self.y0, other.y0), max(self.x1, other.x1), max(self.y1, other.y1))


EMPTY_WINDOW = Window(0, 0, 0, 0)
NEAR_MIN_M = 1e-3  # nearest clipping plane allowed (m)


def object_window(pts: np.ndarray, TCO: np.ndarray, K: np.ndarray, width: int, height: int, margin: int = 2) -> Window:
    """Pixels that can be covered by an object: bounds of its projected points, plus ``margin``.

    Args:
        pts: [N,3] points whose convex hull contains the model (e.g. its hull vertices), m.
        TCO: [4,4] object-to-camera; K: [3,3]; width, height: image size (px).
    Returns:
        The window clipped to the image; the whole image if a point is closer than
        ``NEAR_MIN_M`` to the camera plane (its projection is unbounded); empty if all are behind.
    """
    from cosy_lite.render._raster_kernels import projected_bounds

    TCO = np.asarray(TCO, dtype=np.float64)
    u0, u1, v0, v1, z0, z1 = projected_bounds(np.asarray(pts, dtype=np.float64), np.ascontiguousarray(TCO[:3, :3]),
                                              np.ascontiguousarray(TCO[:3, 3]), np.asarray(K, dtype=np.float64))
    if z1 <= 0:
        return EMPTY_WINDOW
    if z0 < NEAR_MIN_M:
        return Window(0, 0, width, height)
    # A pixel (c, r) is sampled at (c + 0.5, r + 0.5); triangles cover samples inside their projection.
    x0 = int(np.floor(u0 - 0.5)) - margin
    x1 = int(np.ceil(u1 - 0.5)) + margin + 1
    y0 = int(np.floor(v0 - 0.5)) - margin
    y1 = int(np.ceil(v1 - 0.5)) + margin + 1
    w = Window(max(0, x0), max(0, y0), min(width, x1), min(height, y1))
    return EMPTY_WINDOW if w.empty else w


class WindowDepthRenderer:
    """Depth of one object at a time, inside a window (see module docstring).

    Args:
        meshes: obj_id -> (vertices [N,3] m, faces [F,3] int).
        width, height: image size (px).
    """

    def __init__(self, meshes: dict[int, tuple[np.ndarray, np.ndarray]], width: int, height: int):
        from cosy_lite.render.depth_raster import back_face_sign, mesh_arrays

        self.width, self.height = int(width), int(height)
        self._meshes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._cull: dict[int, float] = {}  # obj_id -> back_face_sign (0: drawn two-sided)
        self._corners: dict[int, np.ndarray] = {}  # obj_id -> [8,3] bounding box corners (m)
        for obj_id, (vertices, faces) in meshes.items():
            try:
                v, f = self._meshes[int(obj_id)] = mesh_arrays(vertices, faces)
            except ValueError as e:
                raise ValueError(f"obj_id {obj_id}: {e}") from None
            self._cull[int(obj_id)] = back_face_sign(v, f)
            lo, hi = v.min(axis=0), v.max(axis=0)
            self._corners[int(obj_id)] = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), axis=-1).reshape(-1, 3)

    def render(self, obj_id: int, TCO: np.ndarray, K: np.ndarray, window: Window) -> np.ndarray:
        """Depth [h,w] float32 (m, 0 = background) of object ``obj_id`` at ``TCO`` [4,4] inside ``window``.

        ``K`` [3,3] is the full image's intrinsics; the result equals ``full[y0:y1, x0:x1]`` of a
        full-image render wherever the object's projection lies inside the window.
        """
        from cosy_lite.render.depth_raster import rasterize_depth

        if obj_id not in self._corners:
            raise KeyError(f"no mesh for obj_id {obj_id}; known: {sorted(self._corners)}")
        outside = window.x0 < 0 or window.y0 < 0 or window.x1 > self.width or window.y1 > self.height
        if outside and not window.empty:
            raise ValueError(f"{window} is not inside the {self.width}x{self.height} image")
        TCO = np.asarray(TCO, dtype=np.float64)
        z = (self._corners[obj_id] @ TCO[:3, :3].T + TCO[:3, 3])[:, 2]
        if window.empty or z.max() <= NEAR_MIN_M:
            return np.zeros(window.shape, np.float32)
        near = max(NEAR_MIN_M, 0.5 * float(z.min()))  # as the toolkit: the plane only cuts what touches the camera
        return rasterize_depth(*self._meshes[obj_id], TCO, K, (window.x0, window.y0, window.x1, window.y1), near,
                               self._cull[obj_id])

    def render_many(self, items: list[tuple[int, np.ndarray, Window]], K: np.ndarray) -> list[np.ndarray]:
        """:meth:`render` of every ``(obj_id, TCO, window)``."""
        return [self.render(obj_id, TCO, K, window) for obj_id, TCO, window in items]
