"""What an exact detection mask (a ground-truth or hand-checked one) tells the refined poses.

Two settings of :class:`~cosy_lite.inference.settings.InferenceConfig`, each measured with GT masks
and with the detector's on the 100 test images and on a second split of 100 (bench/RESULTS.md,
session 29); the detector's masks (Mask R-CNN's 28x28 grids) are not exact enough for either, so the
reference set leaves both off:

* ``silhouette_guard`` (:func:`guarded_iterations`): the refiner, from a start within 10 deg, ends
  beyond 30 deg for 4 % of the instances. Its last iteration is kept unless its silhouette's IoU with
  the mask falls short of an earlier iteration's by more than the margin; then that earlier one is.
* ``depth_from_mask`` (:func:`fit_depth_to_masks`): an RGB pose's error is mostly its depth (the
  refiner reads it from the scale of its flow, to about 2 % of the distance). At the refined rotation
  and image position the depth is scaled by the ``k`` of :data:`SCALES` whose silhouette ``S(k)``
  minimises ``|M \\ S(k)| + OUTSIDE_WEIGHT * |S(k) \\ M|``: the silhouette rendered at the refined
  pose, scaled by ``1/k`` about the projected object origin (the object moved along its line of
  sight, weak perspective). The silhouette may overhang the mask at half the cost, where something
  hides the object; a mask covering less than :data:`MIN_VISIBLE` of the silhouette keeps the
  refiner's depth: with much of the object hidden, its visible part does not tell its size.

RGB AR of the 100 test images with the reference set's poses (the second split in brackets): GT
masks 0.4225 (0.4177), with depth_from_mask 0.4423 (0.4446), with both 0.4520 (0.4521); the
detector's masks 0.2883 (0.2893), with depth_from_mask 0.2652, with silhouette_guard 0.2763 (0.2753).
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


def _silhouettes(TCO: Tensor, K: Tensor, size: tuple[int, int], obj_ids: Sequence[int],
                 renderer: Renderer) -> tuple[list[int], np.ndarray]:
    """(the rows of ``TCO [N,4,4]`` that can be rendered: finite, in front of the camera; their full-image
    silhouettes ``[n,H,W]`` bool, rendered with ``K [3,3]``)."""
    T = TCO.detach().double().cpu().numpy()
    live = [i for i in range(len(T)) if np.isfinite(T[i]).all() and T[i, 2, 3] > 0]
    if not live:
        return live, np.zeros((0, *size), dtype=bool)
    _, depth = renderer.render_tensors([int(obj_ids[i]) for i in live], T[live],
                                       np.repeat(K.detach().double().cpu().numpy()[None], len(live), 0), size,
                                       depth_only=True)
    return live, (depth[:, 0] > 0).cpu().numpy()


def silhouette_ious(TCO: Tensor, K: Tensor, masks: Tensor, obj_ids: Sequence[int], renderer: Renderer) -> np.ndarray:
    """``[N]`` float64: the IoU of each object's silhouette at ``TCO [N,4,4]`` (rendered with ``K [3,3]``)
    with its mask in ``masks [N,H,W]`` bool; -1 for a non-finite pose or one behind the camera."""
    ious = np.full(len(masks), -1.0)
    live, sil = _silhouettes(TCO, K, (int(masks.shape[1]), int(masks.shape[2])), obj_ids, renderer)
    if live:
        m = masks.detach().cpu().numpy().astype(bool)[live]
        inter = (sil & m).reshape(len(live), -1).sum(1)
        ious[live] = inter / np.maximum((sil | m).reshape(len(live), -1).sum(1), 1)
    return ious


def guarded_iterations(iterations: Sequence[Tensor], K: Tensor, masks: Tensor, obj_ids: Sequence[int],
                       renderer: Renderer, margin: float) -> Tensor:
    """``[N]`` int64: for each object, the index into ``iterations`` (the refiner's poses ``[N,4,4]`` after
    each iteration) of the pose to keep: the last, unless its silhouette IoU with the mask is under an
    earlier iteration's best by more than ``margin``; then that earlier one."""
    last = len(iterations) - 1
    keep = torch.full((len(masks),), last, dtype=torch.long)
    if last < 1 or len(masks) == 0:
        return keep
    ious = np.stack([silhouette_ious(T, K, masks, obj_ids, renderer) for T in iterations])  # [n_iterations, N]
    best = ious[:last].argmax(axis=0)
    worse = ious[last] < ious[best, np.arange(len(masks))] - margin
    keep[torch.from_numpy(worse)] = torch.from_numpy(best[worse])
    return keep


def depth_scale(silhouette: np.ndarray, mask: np.ndarray, centre: tuple[float, float]) -> float:
    """The depth factor (one of :data:`SCALES`, or 1.0 when kept) for one object: ``silhouette`` and
    ``mask`` ``[H,W]`` bool, ``centre`` (x, y) px of the projected object origin."""
    mask_area = int(mask.sum())
    if mask_area == 0 or not silhouette.any() or mask_area < MIN_VISIBLE * int(silhouette.sum()):
        return 1.0
    H, W = mask.shape
    cx, cy = centre
    ys, xs = np.nonzero(silhouette | mask)
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
    live, silhouettes = _silhouettes(TCO, K, (int(masks.shape[1]), int(masks.shape[2])), obj_ids, renderer)
    T, K_np = TCO.detach().double().cpu().numpy(), K.detach().double().cpu().numpy()
    mask_np = masks.detach().cpu().numpy().astype(bool)
    for row, i in enumerate(live):
        c = K_np @ T[i, :3, 3]
        k = depth_scale(silhouettes[row], mask_np[i], (c[0] / c[2], c[1] / c[2]))
        if k != 1.0:
            out[i, :3, 3] = out[i, :3, 3] * torch.as_tensor(k, dtype=out.dtype)
    return out
