"""Depth of one triangle mesh inside an image window, rasterised on the CPU (numba).

The evaluator's renderer (VSD needs the depth of one object at a time, inside the window the object
covers): no GL context, no draw call, no read-back; one compiled loop over the triangles. Its
conventions are those of the BOP toolkit's renderer: OpenCV camera, the pixel of row ``r``, column
``c`` sampled at ``(u, v) = (c + 0.5, r + 0.5)``; depth = camera Z of the nearest surface,
interpolated perspective-correctly (``1 / z`` is linear in the image), 0 where nothing is drawn;
faces two-sided (a closed mesh may skip its back faces, :func:`back_face_sign`: the same pixels);
triangles clipped by the plane ``z = znear``. Which samples a triangle covers is
decided as a GL rasteriser decides it (the toolkit's renders come from one): corners snapped to
1/256 px, a sample on an edge taken by the triangle whose top or left edge it is; the depth comes
from the exact corners. On the demo's results files the AR equals that of the GL pass this
replaced, and the toolkit's.

The compiled loop (:mod:`cosy_lite.render._raster_kernels`, imported on first use) is cached next
to it (``numba``'s ``cache=True``): the first call in a fresh install compiles (~3 s), later
processes load it.
"""

from __future__ import annotations

import numpy as np


def rasterize_depth(vertices: np.ndarray, faces: np.ndarray, TCO: np.ndarray, K: np.ndarray,
                    window: tuple[int, int, int, int], znear: float = 1e-3, cull: float = 0.0) -> np.ndarray:
    """Depth [y1 - y0, x1 - x0] float32 (m, 0 = background) of the mesh at ``TCO`` [4,4] in the
    image rows ``y0:y1``, columns ``x0:x1`` (``window = (x0, y0, x1, y1)``) of the camera ``K``
    [3,3] (OpenCV, no skew): those pixels of a full-image render, exactly.

    Args:
        vertices: [N,3] float64 (m); faces: [F,3] int32 indices into them (see :func:`mesh_arrays`).
        znear: clipping plane (m, > 0); the part of the mesh nearer than it is not drawn.
        cull: :func:`back_face_sign` of the mesh (its back faces are skipped: ~1.6x faster), or 0
            (default) to draw every face both ways.
    """
    from cosy_lite.render._raster_kernels import draw_mesh, finish

    x0, y0, x1, y1 = (int(v) for v in window)
    if x1 <= x0 or y1 <= y0:
        return np.zeros((max(0, y1 - y0), max(0, x1 - x0)), np.float32)
    if not znear > 0:
        raise ValueError(f"znear must be > 0, got {znear}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or K[0, 1] != 0:
        raise ValueError(f"K must be a [3,3] camera matrix without skew, got {K.tolist()}")
    TCO = np.asarray(TCO, dtype=np.float64)
    if cull not in (-1.0, 0.0, 1.0):
        raise ValueError(f"cull must be -1, 0 or 1 (back_face_sign), got {cull}")
    out = np.zeros((y1 - y0, x1 - x0))  # 1 / z, 0 = empty
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    draw_mesh(out, vertices, faces, np.ascontiguousarray(TCO[:3, :3]), np.ascontiguousarray(TCO[:3, 3]),
              fx, fy, cx, cy, x0, y0, float(znear), float(cull))
    depth = np.zeros(out.shape, np.float32)
    finish(out, depth)
    return depth


def warm_up() -> None:
    """Load (or compile) the rasteriser now, e.g. before forking processes that will use it."""
    rasterize_depth(np.eye(3), np.array([[0, 1, 2]], np.int32), np.eye(4), np.eye(3), (0, 0, 1, 1))


def back_face_sign(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The ``cull`` argument of :func:`rasterize_depth` for a mesh (as :func:`mesh_arrays` returns it):
    +1 or -1 if the mesh is closed and each of its parts encloses its volume the same way round,
    0 otherwise (drawn two-sided).

    Closed: with vertices of equal position merged, each directed edge a -> b occurs as often as
    b -> a. Then every image sample (GL's edge rule breaks ties as a fixed infinitesimal shift of
    the sample would) is covered by as many triangles of one winding as of the other, so the back
    faces cover no sample the front faces miss; and a ray from a camera outside the mesh (no
    vertex behind the near plane, checked per render) enters it, through a front face, before it
    meets any back face. Which winding is the back one follows from the sign of the volume.
    """
    from cosy_lite.render._raster_kernels import component_labels

    order = np.lexsort(vertices.T[::-1])  # equal positions next to each other
    ranked = vertices[order]
    welded = np.empty(len(vertices), np.int64)  # vertex -> index of its position
    welded[order] = np.cumsum(np.r_[True, np.any(ranked[1:] != ranked[:-1], axis=1)]) - 1
    f = welded[faces]
    n = int(welded.max()) + 1
    a, b = f.ravel(), f[:, [1, 2, 0]].ravel()
    if not np.array_equal(np.sort(a * n + b), np.sort(b * n + a)):
        return 0.0
    v = vertices[faces]
    volumes = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2]))  # 6x the signed tetrahedra
    part = component_labels(f, n)[f[:, 0]]  # each face's connected part
    parts = np.bincount(part, weights=volumes)[np.unique(part)]
    if np.all(parts > 0):
        return 1.0
    return -1.0 if np.all(parts < 0) else 0.0


def mesh_arrays(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vertices [N,3] float64 C-contiguous, faces [F,3] int32) as :func:`rasterize_depth` takes
    them; ValueError if they are not a triangle mesh."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0 or f.size == 0 or f.size % 3 or f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"expected vertices [N,3] and faces [F,3] indexing them, got {v.shape} and {f.shape}")
    if not np.isfinite(v).all():
        raise ValueError("vertices are not all finite")
    return v, np.ascontiguousarray(f.reshape(-1, 3), dtype=np.int32)
