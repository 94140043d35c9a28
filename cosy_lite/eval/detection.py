"""COCO box and mask AP of 2D detections against BOP ground truth (pycocotools).

Ground truth as the BOP toolkit builds it for its BOP22 2D evaluation (``scripts/calc_gt_coco.py``):
one annotation per GT instance with at least one visible pixel, mask = ``mask_visib`` (RLE),
``ignore`` set when ``visib_fract < 0.1`` (pycocotools' ``COCOeval`` overwrites that flag with
``iscrowd``, so, as in the toolkit's evaluation, these instances count like the others). Boxes:
``"modal"`` = ``bbox_visib`` (what :mod:`cosy_lite.nets.detector` is trained to output) or
``"amodal"`` = ``bbox_obj`` clipped to the image (the toolkit's BOP22 default uses the box of the
full ``mask/``, which this matches up to the rounding of the projected box).
"""

from __future__ import annotations

import contextlib
import io as _io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from cosy_lite.bop import io
from cosy_lite.bop.detections import (
    Detections,
    ImageKey,
    compressed_rle,
    detections_to_bop22,
    mask_to_rle,
    read_bop22_entries,
    read_detections_json,
)

VISIB_IGNORE = 0.1  # toolkit: GT less visible than this gets the ignore flag
BBOX_TYPES = ("modal", "amodal")
# the BOP 2D tasks: cosy-lite eval --task -> COCO annotation type (the toolkit's --ann_type)
ANN_TYPES = {"2d-detection": "bbox", "2d-segmentation": "segm"}
# keys of the toolkit's scores_bop22_coco_*.json, in COCOeval.stats order
COCO_KEYS = ("AP", "AP50", "AP75", "AP_small", "AP_medium", "AP_large", "AR1", "AR10", "AR100", "AR_small",
             "AR_medium", "AR_large")


@dataclass
class DetectionScores:
    """COCO average precisions in [0, 1] (NaN: not evaluated, e.g. no masks or no GT)."""

    ap: float  # box AP @ IoU 0.50:0.95
    ap50: float
    ap75: float
    mask_ap: float
    mask_ap50: float
    n_images: int
    n_gt: int
    n_detections: int


def _gt_box(info: io.GtInfo, bbox_type: str, size: tuple[int, int]) -> list[float]:
    if bbox_type == "modal":
        return [float(v) for v in info.bbox_visib]
    x, y, w, h = info.bbox_obj
    x0, y0 = max(x, 0), max(y, 0)
    x1, y1 = min(x + w, size[1]), min(y + h, size[0])
    return [float(x0), float(y0), float(max(x1 - x0, 0)), float(max(y1 - y0, 0))]


def coco_ground_truth(dataset, records: Iterable, bbox_type: str = "modal") -> tuple[dict[str, Any], dict[ImageKey, int]]:
    """A COCO ground-truth dict for ``records`` and the ``(scene_id, im_id) -> COCO image id`` map.

    Args:
        dataset: the :class:`~cosy_lite.bop.dataset.BopDataset`.
        records: its :class:`~cosy_lite.bop.dataset.ImageRecord` s (with ``gt_info`` and ``mask_visib/``).
        bbox_type: ``"modal"`` or ``"amodal"`` (module docstring).
    """
    if bbox_type not in BBOX_TYPES:
        raise ValueError(f"bbox_type {bbox_type!r} unknown; use one of {BBOX_TYPES}")
    images: list[dict[str, Any]] = []
    annotations: list[dict[str, Any]] = []
    index: dict[ImageKey, int] = {}
    for rec in records:
        if rec.gt_info is None:
            raise ValueError(f"{dataset.scene_dir(rec.split, rec.scene_id) / 'scene_gt_info.json'}: needed for detection AP")
        key = (rec.scene_id, rec.im_id)
        index[key] = len(index) + 1
        size = None
        for k, (gt, info) in enumerate(zip(rec.gt, rec.gt_info)):
            if info.px_count_visib <= 0:
                continue
            mask = io.load_mask(dataset.mask_path(rec.split, rec.scene_id, rec.im_id, k, visib=True))
            size = mask.shape
            annotations.append({
                "id": len(annotations) + 1, "image_id": index[key], "category_id": int(gt.obj_id), "iscrowd": 0,
                "area": int(mask.sum()), "bbox": _gt_box(info, bbox_type, size), "segmentation": mask_to_rle(mask),
                "ignore": int(info.visib_fract < VISIB_IGNORE),
            })
        if size is None:
            size = io.load_image(rec.rgb_path).shape[:2]
        images.append({"id": index[key], "width": int(size[1]), "height": int(size[0]),
                       "file_name": str(rec.rgb_path), "scene_id": rec.scene_id, "im_id": rec.im_id})
    categories = [{"id": int(i), "name": str(i)} for i in dataset.obj_ids]
    return {"images": images, "annotations": annotations, "categories": categories}, index


def _coco_eval(gt: dict[str, Any], results: list[dict[str, Any]], iou_type: str) -> np.ndarray:
    """COCOeval stats (12 numbers, -1 where undefined), pycocotools' printing silenced."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    with contextlib.redirect_stdout(_io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = gt
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes([dict(r) for r in results])  # loadRes adds keys to the entries
        ev = COCOeval(coco_gt, coco_dt, iou_type)
        ev.params.imgIds = sorted(coco_gt.getImgIds())
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    return ev.stats


def _score(v: float) -> float:
    return float("nan") if v < 0 else float(v)


def evaluate_detections(dataset, records: Iterable, detections: Mapping[ImageKey, Detections],
                        bbox_type: str = "modal") -> DetectionScores:
    """Box and mask COCO AP of ``detections`` on the images of ``records``.

    Detections of other images are ignored; images without an entry have no detections. Mask
    AP is NaN unless every evaluated detection has a mask.
    """
    gt, index = coco_ground_truth(dataset, records, bbox_type)
    entries = detections_to_bop22({k: d for k, d in detections.items() if k in index})
    for e in entries:
        e["image_id"] = index[(e.pop("scene_id"), e["image_id"])]
    n_gt = len(gt["annotations"])
    if not entries or n_gt == 0:
        nan = float("nan") if n_gt == 0 else 0.0
        return DetectionScores(nan, nan, nan, nan, nan, len(index), n_gt, len(entries))
    has_masks = all("segmentation" in e for e in entries)
    box = _coco_eval(gt, entries, "bbox")
    mask = _coco_eval(gt, entries, "segm") if has_masks else np.full(12, -1.0)
    return DetectionScores(_score(box[0]), _score(box[1]), _score(box[2]),
                           _score(mask[0]) if has_masks else math.nan, _score(mask[1]) if has_masks else math.nan,
                           len(index), n_gt, len(entries))


def evaluate_detections_file(dataset, records: Iterable, path: str | Path, bbox_type: str = "modal") -> DetectionScores:
    """:func:`evaluate_detections` of a BOP22 detection JSON file (masks used when present)."""
    records = list(records)
    with_masks = _all_have_segmentation(path)
    dets = read_detections_json(path, dataset.obj_ids, with_masks=with_masks)
    return evaluate_detections(dataset, records, dets, bbox_type)


def _all_have_segmentation(path: str | Path) -> bool:
    data = io.load_json(path)
    return isinstance(data, list) and bool(data) and all(isinstance(d, dict) and d.get("segmentation") for d in data)


def bop22_coco_scores(dataset, records: Iterable, path: str | Path, ann_type: str,
                      bbox_type: str = "amodal") -> dict[str, float]:
    """The BOP 2D detection (``ann_type="bbox"``) or segmentation (``"segm"``) scores of a BOP22
    results JSON, as the toolkit's ``eval_bop22_coco.py`` computes them: only the images of
    ``records`` (the targets' images) and the entries on them that have a box (bbox) or a mask
    (segm); COCO AP with pycocotools (at most 100 detections per image, the highest scores); the
    ground truth of :func:`coco_ground_truth`. Returns :data:`COCO_KEYS` (-1 where undefined, and
    all -1 when no entry is left, as the toolkit) and ``average_time_per_image`` (the mean of the
    images' ``time``, -1 when an entry has none or an image's entries disagree).
    """
    if ann_type not in ("bbox", "segm"):
        raise ValueError(f"ann_type must be 'bbox' or 'segm', got {ann_type!r}")
    records = list(records)
    gt, index = coco_ground_truth(dataset, records, bbox_type)
    entries = [e for e in read_bop22_entries(path, dataset.obj_ids) if (e["scene_id"], e["image_id"]) in index]
    times: dict[ImageKey, set[float]] = {}
    for e in entries:
        times.setdefault((e["scene_id"], e["image_id"]), set()).add(e["time"])
    consistent = all(len(t) == 1 and min(t) >= 0 for t in times.values())
    avg_time = float(np.mean([min(t) for t in times.values()])) if times and consistent else -1.0
    results = []
    for e in entries:
        if e["bbox" if ann_type == "bbox" else "segmentation"] is None:
            continue
        r = {"image_id": index[(e["scene_id"], e["image_id"])], "category_id": e["category_id"], "score": e["score"]}
        if ann_type == "bbox":
            r["bbox"] = e["bbox"]
        else:
            r["segmentation"] = compressed_rle(e["segmentation"])
        results.append(r)
    stats = _coco_eval(gt, results, ann_type) if results and gt["annotations"] else np.full(len(COCO_KEYS), -1.0)
    return {**{k: float(v) for k, v in zip(COCO_KEYS, stats)}, "average_time_per_image": avg_time}

