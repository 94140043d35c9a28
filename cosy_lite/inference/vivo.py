"""The BOP19 ViVo task (6D localisation of a Varying number of instances of a Varying number of
objects): per test image, the objects to localise and how many instances of each
(``test_targets_bop19.json``); a method keeps, per image and object, its ``inst_count`` best
detections. The evaluator (:mod:`cosy_lite.eval.scoring`) then uses the ``inst_count`` estimates
with the highest scores of each target.
"""

from __future__ import annotations

from typing import Iterable, Mapping

import torch

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
    ids = detections.obj_ids.tolist()
    taken: dict[int, int] = {}
    keep = []
    for k in order:
        obj = int(ids[k])
        if taken.get(obj, 0) < inst_counts.get(obj, 0):
            taken[obj] = taken.get(obj, 0) + 1
            keep.append(k)
    return detections.select(torch.tensor(keep, dtype=torch.long))
