"""Depth from an exact detection mask: the distance at which the object's silhouette best covers it.

An RGB pose's error is mostly its depth (bench/RESULTS.md, sessions 15 and 18): the refiner reads it
from the scale of its flow, to about 2 % of the distance. An exact mask (a ground-truth or
hand-checked one) pins the object's image size better: at the refined rotation and image position,
the depth is scaled by the ``k`` of :data:`SCALES` whose silhouette ``S(k)`` minimises
``|M \\ S(k)| + OUTSIDE_WEIGHT * |S(k) \\ M|``. ``S(k)`` is the silhouette rendered at the refined
pose, scaled by ``1/k`` about the projected object origin (the object moved along its line of sight,
weak perspective). The silhouette may overhang the mask at half the cost, where something hides the
object; a mask covering less than :data:`MIN_VISIBLE` of the silhouette keeps the refiner's depth:
with much of the object hidden, its visible part does not tell its size.

Measured (session 29, the set's poses, RGB AR of the 100 test images): GT masks 0.4225 -> 0.4409;
the detector's masks (Mask R-CNN's 28x28 grids) 0.2883 -> 0.2649: their edges are not exact enough,
so the reference set leaves it off (``InferenceConfig.depth_from_mask``).
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np
import torch
from torch import Tensor

from cosy_lite.render.renderer import Renderer

SCALES = np.round(np.arange(0.80, 1.2501, 0.005), 4)  # depth / refined depth tried; 1.0 among them
OUTSIDE_WEIGHT = 0.5  # cost of a silhouette pixel outside the mask, against 1 for a mask pixel left uncovered
MIN_VISIBLE = 0.8  # mask area / silhouette area at the refined pose under which the depth is kept


def depth_scale(silhouette: np.ndarray, mask: np.ndarray, centre: tuple[float, float]) -> float:
    """The depth factor (one of :data:`SCALES`, or 1.0 when kept) for one object: ``silhouette`` and
    ``mask`` ``[H,W]`` bool, ``centre`` (x, y) px of the projected object origin."""
    mask_area = int(mask.sum())
    both = silhouette | mask
    if mask_area == 0 or not silhouette.any() or mask_area < MIN_VISIBLE * int(silhouette.sum()):
        return 1.0
    H, W = mask.shape
    cx, cy = centre
    ys, xs = np.nonzero(both)
    # a window that holds S(k) for every k tried: 1.3 x the farthest pixel from the centre (k >= 0.8)
    radius = 1.3 * max(np.abs(xs - cx).max(), np.abs(ys - cy).max()) + 4
    x0, x1 = int(max(0, cx - radius)), int(min(W, cx + radius + 1))
    y0, y1 = int(max(0, cy - radius)), int(min(H, cy + radius + 1))
    if x1 <= x0 or y1 <= y0:  # the centre is far outside the image: nothing to compare
        return 1.0
    sil = silhouette[y0:y1, x0:x1].astype(np.float32)
    inside = mask[y0:y1, x0:x1]
    outside_window = mask_area - int(inside.sum())
    costs = np.empty(len(SCALES))
    for j, k in enumerate(SCALES):
        s = 1.0 / float(k)
        warp = np.array([[s, 0, (1 - s) * (cx - x0)], [0, s, (1 - s) * (cy - y0)]], dtype=np.float32)
        scaled = cv2.warpAffine(sil, warp, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR) > 0.5
        costs[j] = (inside & ~scaled).sum() + outside_window + OUTSIDE_WEIGHT * (scaled & ~inside).sum()
    # ties (a pixel grid cannot tell 1 % apart on a small object): the one nearest the refined depth
    return float(SCALES[np.lexsort((np.abs(SCALES - 1.0), costs))[0]])


def fit_depth_to_masks(TCO: Tensor, K: Tensor, masks: Tensor, obj_ids: Sequence[int], renderer: Renderer) -> Tensor:
    """``TCO [N,4,4]`` (m) with each translation scaled by :func:`depth_scale` of its object's
    silhouette (rendered with ``K [3,3]``) and ``masks [N,H,W]`` bool. Non-finite poses or poses
    behind the camera are returned as they are."""
    out = TCO.clone()
    N, H, W = masks.shape
    if N == 0:
        return out
    T = TCO.detach().double().cpu().numpy()
    K_np = K.detach().double().cpu().numpy()
    live = [i for i in range(N) if np.isfinite(T[i]).all() and T[i, 2, 3] > 0]
    if not live:
        return out
    _, depth = renderer.render_tensors([int(obj_ids[i]) for i in live], T[live], np.repeat(K_np[None], len(live), 0),
                                       (H, W), depth_only=True)
    silhouettes = (depth[:, 0] > 0).cpu().numpy()
    mask_np = masks.detach().cpu().numpy().astype(bool)
    for row, i in enumerate(live):
        c = K_np @ T[i, :3, 3]
        k = depth_scale(silhouettes[row], mask_np[i], (c[0] / c[2], c[1] / c[2]))
        if k != 1.0:
            out[i, :3, 3] = out[i, :3, 3] * torch.as_tensor(k, dtype=out.dtype)
    return out
