"""Depth maps, distance maps and the BOP19 visibility test (shared by the generator and VSD).

A depth map stores the Z coordinate of the 3D point seen at a pixel; a distance map stores its
distance from the camera centre. Both in metres here, 0 = no measurement / not rendered.
"""

from __future__ import annotations

import numpy as np


def depth_to_distance(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """[H,W] depth -> [H,W] distance from the camera centre (same units), for pinhole ``K``."""
    h, w = depth.shape
    xs = (np.arange(w, dtype=np.float64) - K[0, 2]) / K[0, 0]
    ys = (np.arange(h, dtype=np.float64) - K[1, 2]) / K[1, 1]
    scale = np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)
    return (depth * scale).astype(depth.dtype)


def visibility_mask(dist_test: np.ndarray, dist_model: np.ndarray, delta: float) -> np.ndarray:
    """BOP19 visibility of a rendered model in a test image.

    A pixel is visible where the model is rendered and it is not behind the test surface by more
    than ``delta``; pixels with no test measurement (0) count as visible. (VSD applies the same test
    pixel by pixel in its compiled loop, :mod:`cosy_lite.eval._vsd_kernel`.)
    """
    diff = dist_model.astype(np.float32) - dist_test.astype(np.float32)
    return np.logical_and(np.logical_or(diff <= delta, dist_test == 0), dist_model > 0)


def mask_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """Half-open (x0, y0, x1, y1) of a boolean [H,W] mask (x1 = its last column + 1), None if empty;
    as ``[x0, y0, x1 - x0, y1 - y0]`` it is COCO's box of the mask (the BOP toolkit's ``bbox_from_binary_mask``)."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return None
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def bbox_from_mask(mask: np.ndarray) -> list[int]:
    """[x, y, w, h] of a boolean mask as the BOP toolkit computes it (w = x_max - x_min); [-1]*4 if empty."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())]
