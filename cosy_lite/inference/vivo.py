"""The BOP19 ViVo task (6D localisation of a Varying number of instances of a Varying number of
objects): per test image, the objects to localise and how many instances of each
(``test_targets_bop19.json``); a method keeps, per image and object, its ``inst_count`` best
detections. The evaluator (:mod:`cosy_lite.eval.scoring`) then uses the ``inst_count`` estimates
with the highest scores of each target.
"""

from __future__ import annotations

from typing import Iterable, Mapping

import torch
from torch import Tensor

from cosy_lite.bop.detections import Detections
from cosy_lite.bop.io import Target

ImageKey = tuple[int, int]  # (scene_id, im_id)


def targets_by_image(targets: Iterable[Target]) -> dict[ImageKey, dict[int, int]]:
    """``{(scene_id, im_id): {obj_id: inst_count}}`` in (scene, image) order; targets of one image
    and object listed twice add up."""
    out: dict[ImageKey, dict[int, int]] = {}
    for t in targets:
        counts = out.setdefault((t.scene_id, t.im_id), {})
        counts[t.obj_id] = counts.get(t.obj_id, 0) + t.inst_count
    return dict(sorted(out.items()))


def select_top_instances(detections: Detections, inst_counts: Mapping[int, int]) -> Detections:
    """Per object of ``inst_counts`` (obj_id -> inst_count) its ``inst_count`` highest-scoring
    detections; other objects dropped. Returned by decreasing score (ties: input order)."""
    order = torch.argsort(detections.scores, descending=True, stable=True).tolist()
    keep = _first_per_object(order, detections.obj_ids.tolist(), inst_counts)
    return detections.select(torch.tensor(keep, dtype=torch.long))


def select_candidates(detections: Detections, inst_counts: Mapping[int, int], per_instance: int = 1,
                      score_ratio: float = 0.0) -> Detections:
    """Per object of ``inst_counts`` its ``per_instance x inst_count`` highest-scoring detections, those
    beyond its ``inst_count`` best only when they score at least ``score_ratio`` x its best (so with
    ``per_instance`` 1, :func:`select_top_instances`); other objects dropped. By decreasing score."""
    if per_instance < 1:
        raise ValueError(f"per_instance must be >= 1, got {per_instance}")
    top = select_top_instances(detections, {o: n * per_instance for o, n in inst_counts.items()})
    ids, scores = top.obj_ids.tolist(), top.scores.tolist()
    best: dict[int, float] = {}
    seen: dict[int, int] = {}
    keep = []
    for k, (obj, score) in enumerate(zip(ids, scores)):
        best.setdefault(obj, score)
        seen[obj] = seen.get(obj, 0) + 1
        if seen[obj] <= inst_counts.get(obj, 0) or score >= score_ratio * best[obj]:
            keep.append(k)
    return top.select(torch.tensor(keep, dtype=torch.long))


def most_confident(obj_ids: Tensor, confidence: Tensor, inst_counts: Mapping[int, int]) -> Tensor:
    """Indices (ascending) of the estimates to keep: per object its ``inst_count`` of highest
    ``confidence`` (ties: the earlier one); objects not in ``inst_counts`` keep none."""
    order = torch.argsort(confidence.double().cpu(), descending=True, stable=True).tolist()
    return torch.tensor(sorted(_first_per_object(order, obj_ids.tolist(), inst_counts)), dtype=torch.long)


def _first_per_object(order: list[int], obj_ids: list[int], inst_counts: Mapping[int, int]) -> list[int]:
    """The indices of ``order`` (a ranking) kept when each object takes its first ``inst_count``."""
    taken: dict[int, int] = {}
    keep = []
    for k in order:
        obj = int(obj_ids[k])
        if taken.get(obj, 0) < inst_counts.get(obj, 0):
            taken[obj] = taken.get(obj, 0) + 1
            keep.append(k)
    return keep
