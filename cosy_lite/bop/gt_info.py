"""GT masks and ``scene_gt_info`` entries, computed as the BOP toolkit does
(``calc_gt_info.py`` / ``calc_gt_masks.py``): visibility on distance maps, 15 mm tolerance."""

from __future__ import annotations

import numpy as np

from cosy_lite.bop.io import GtInfo
from cosy_lite.geometry.depth import bbox_from_mask, depth_to_distance, visibility_mask
from cosy_lite.geometry.transforms import project_points, transform_points

DEFAULT_DELTA = 0.015  # metres


def projected_bbox(vertices: np.ndarray, TCO: np.ndarray, K: np.ndarray) -> list[int]:
    """[x, y, w, h] of the full (untruncated) silhouette from the model vertices, in the pixel
    convention of the renderer (pixel i is covered when its centre i + 0.5 is inside)."""
    uv = project_points(transform_points(TCO, vertices), K)
    lo = np.ceil(uv.min(0) - 0.5).astype(int)
    hi = np.floor(uv.max(0) - 0.5).astype(int)
    return [int(lo[0]), int(lo[1]), int(hi[0] - lo[0]), int(hi[1] - lo[1])]


def compute_gt_info(
    depth_image: np.ndarray,
    depth_object: np.ndarray,
    K: np.ndarray,
    bbox_obj: list[int],
    delta: float = DEFAULT_DELTA,
) -> tuple[np.ndarray, np.ndarray, GtInfo]:
    """Masks and statistics of one GT instance.

    Args:
        depth_image: [H,W] depth of the test image in metres as stored (0 = unknown).
        depth_object: [H,W] depth of the object rendered alone in its GT pose, metres (0 = background).
        K: [3,3] intrinsics; bbox_obj: box of the full silhouette (may extend beyond the image).
        delta: visibility tolerance in metres.
    Returns:
        mask (full silhouette inside the image), mask_visib, and the GtInfo entry.
    """
    dist_im = depth_to_distance(depth_image, K)
    dist_gt = depth_to_distance(depth_object, K)
    mask = dist_gt > 0
    mask_visib = visibility_mask(dist_im, dist_gt, delta)
    px_all = int(mask.sum())
    px_valid = int((dist_im[mask] > 0).sum())
    px_visib = int(mask_visib.sum())
    info = GtInfo(
        bbox_obj=list(bbox_obj) if px_visib > 0 else [-1, -1, -1, -1],
        bbox_visib=bbox_from_mask(mask_visib),
        px_count_all=px_all,
        px_count_valid=px_valid,
        px_count_visib=px_visib,
        visib_fract=px_visib / px_all if px_all > 0 else 0.0,
    )
    return mask, mask_visib, info
