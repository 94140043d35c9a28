"""Which detections get a pose: a score threshold, and at most one object per image region.

The detector keeps boxes above its own ``box_score_thresh`` (0.05) and suppresses overlaps within
one class only, so one object often comes out as two or three classes. :class:`DetectionFilter`
drops the detections under ``min_score`` and, with ``one_per_region``, every detection whose
region (mask, or box when there are no masks) overlaps a better-scored kept one by more than
``region_iou`` (IoU), whatever its class.

Measured on the ycbvsynth test split (bench/RESULTS.md, "Detection threshold"): for the BOP19
task neither helps AR. Its ViVo selection already keeps only the best detection per target object,
and a threshold only removes some right ones (detector + ICP: AR 0.3335 with all, 0.3329 from 0.1,
0.2920 from 0.5). One per region removes about as many right estimates as wrong ones. So
``cosy-lite infer`` defaults to no filter; they are for ``cosy-lite predict``, where every
detection becomes an estimate that someone reads.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from cosy_lite.bop.detections import Detections


@dataclass(frozen=True)
class DetectionFilter:
    """``min_score``: keep detections scoring at least this; ``one_per_region``: greedy by score,
    drop a detection overlapping a kept one (any class) by IoU > ``region_iou``; ``max_per_object``:
    at most this many detections of each object, the best scored."""

    min_score: float = 0.0
    one_per_region: bool = False
    region_iou: float = 0.5
    max_per_object: int = 0  # at most this many per object id, the best scored (0: no limit)

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_score <= 1.0:
            raise ValueError(f"min_score must be in [0, 1], got {self.min_score}")
        if not 0.0 < self.region_iou <= 1.0:
            raise ValueError(f"region_iou must be in (0, 1], got {self.region_iou}")

    @property
    def active(self) -> bool:
        return self.min_score > 0.0 or self.one_per_region or self.max_per_object > 0

    def __call__(self, det: Detections) -> Detections:
        """The kept detections of ``det``, by decreasing score (ties: input order)."""
        det = det.select(torch.argsort(det.scores, descending=True, stable=True))
        if self.min_score > 0:
            det = det.select(det.scores >= self.min_score)
        if self.max_per_object > 0:
            rank = [det.obj_ids[:i].tolist().count(int(o)) for i, o in enumerate(det.obj_ids.tolist())]
            det = det.select(torch.tensor(rank, dtype=torch.long) < self.max_per_object)
        if not self.one_per_region or len(det) < 2:
            return det
        overlap = region_ious(det)
        keep: list[int] = []
        for i in range(len(det)):
            if all(float(overlap[i, k]) <= self.region_iou for k in keep):
                keep.append(i)
        return det.select(torch.tensor(keep, dtype=torch.long))


def region_ious(det: Detections) -> Tensor:
    """``[N,N]`` IoU of the detections' masks (their boxes when ``det`` has no masks)."""
    if det.masks is not None:
        m = det.masks.flatten(1).float()
        inter = m @ m.T
        area = m.sum(dim=1)
    else:
        b = det.boxes.double()
        lo = torch.maximum(b[:, None, :2], b[None, :, :2])
        hi = torch.minimum(b[:, None, 2:], b[None, :, 2:])
        inter = (hi - lo).clamp(min=0).prod(dim=2)
        area = (b[:, 2:] - b[:, :2]).clamp(min=0).prod(dim=1)
    union = area[:, None] + area[None, :] - inter
    return torch.where(union > 0, inter / union.clamp(min=1e-12), torch.zeros_like(inter)).double()
