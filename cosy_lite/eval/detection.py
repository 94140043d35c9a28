"""COCO box and mask AP of 2D detections against BOP ground truth (pycocotools).

Ground truth as the BOP toolkit builds it for its BOP22 2D evaluation (``scripts/calc_gt_coco.py``):
one annotation per GT instance with at least one visible pixel, mask = ``mask_visib`` (RLE), area =
its pixel count, ``ignore`` set when ``visib_fract < 0.1``. Boxes are the tight boxes of masks
(``[x, y, w, h]``, the last pixel included): ``"modal"`` the box of ``mask_visib`` (what
:mod:`cosy_lite.nets.detector` is trained to output), ``"amodal"`` the box of the full ``mask/``
(an instance whose full mask is empty is left out, as the toolkit). The toolkit scores with its
pinned pycocotools fork, whose ``COCOeval`` keeps the ``ignore`` flag (PyPI's replaces it with
``iscrowd``): :func:`_coco_eval` does the same, so a GT instance under 10 % visible neither costs
recall when missed nor counts a detection on it as a false positive.
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
from cosy_lite.errors import BopFormatError
from cosy_lite.geometry.depth import mask_box

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


def _coco_box(mask: np.ndarray) -> list[float]:
    """COCO's ``[x, y, w, h]`` of a non-empty mask, its last row and column included (the toolkit's
    ``pycoco_utils.bbox_from_binary_mask``)."""
    box = mask_box(mask)
    assert box is not None
    x0, y0, x1, y1 = box
    return [float(x0), float(y0), float(x1 - x0), float(y1 - y0)]


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
            if not mask.any():
                continue
            box_mask = mask if bbox_type == "modal" else _full_mask(dataset, rec, k)
            if not box_mask.any():
                continue
            annotations.append({
                "id": len(annotations) + 1, "image_id": index[key], "category_id": int(gt.obj_id), "iscrowd": 0,
                "area": int(mask.sum()), "bbox": _coco_box(box_mask),
                "segmentation": mask_to_rle(mask), "ignore": int(info.visib_fract < VISIB_IGNORE),
            })
        if size is None:
            size = io.load_image(rec.rgb_path).shape[:2]
        images.append({"id": index[key], "width": int(size[1]), "height": int(size[0]),
                       "file_name": str(rec.rgb_path), "scene_id": rec.scene_id, "im_id": rec.im_id})
    categories = [{"id": int(i), "name": str(i)} for i in dataset.obj_ids]
    return {"images": images, "annotations": annotations, "categories": categories}, index


def _full_mask(dataset, rec, k: int) -> np.ndarray:
    path = dataset.mask_path(rec.split, rec.scene_id, rec.im_id, k, visib=False)
    if not path.is_file():
        raise BopFormatError(path, "mask", "full object mask not found (amodal boxes are the boxes of mask/; "
                             "use --bbox-type modal for the boxes of mask_visib/)")
    return io.load_mask(path)


def _keep_ignore_flags(ev) -> None:
    """Make ``COCOeval`` ``ev`` keep the GT ``ignore`` flags, as the toolkit's pycocotools fork does
    (PyPI's ``_prepare`` sets every GT's ``ignore`` to its ``iscrowd``)."""
    flags = {a["id"]: bool(a.get("ignore", 0)) for a in ev.cocoGt.dataset["annotations"]}
    prepare = ev._prepare

    def _prepare() -> None:
        prepare()
        for gts in ev._gts.values():
            for g in gts:
                g["ignore"] = flags[g["id"]]

    ev._prepare = _prepare


def _coco_eval(gt: dict[str, Any], results: list[dict[str, Any]], iou_type: str) -> np.ndarray:
    """COCOeval stats (12 numbers, -1 where undefined) with the toolkit's ``ignore`` rule
    (:func:`_keep_ignore_flags`), pycocotools' printing silenced."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    with contextlib.redirect_stdout(_io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = {**gt, "annotations": [dict(a) for a in gt["annotations"]]}  # COCOeval writes into them
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes([dict(r) for r in results])  # loadRes adds keys to the entries
        ev = COCOeval(coco_gt, coco_dt, iou_type)
        _keep_ignore_flags(ev)
        ev.params.imgIds = sorted(coco_gt.getImgIds())
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    return ev.stats


def _toolkit_order(entries: list[dict[str, Any]], scene_order: list[int]) -> list[dict[str, Any]]:
    """``entries`` grouped by scene in the order the targets list the scenes, file order within a
    scene: the order in which ``eval_bop22_coco.py`` hands the results to pycocotools."""
    rank = {s: k for k, s in enumerate(dict.fromkeys(scene_order))}
    return sorted(entries, key=lambda e: rank[e["scene_id"]])


def _boxes_decide_areas(results: list[dict[str, Any]]) -> None:
    """Segmentation results whose first entry has a box: pycocotools' ``loadRes`` then gives every
    result the area of its box (not of its mask), and that area decides the small / medium / large
    class of an unmatched detection. An entry without a box (where the toolkit stops with a
    ``KeyError``) gets the box of its mask."""
    from pycocotools import mask as mask_util

    for r in results:
        if "bbox" not in r:
            r["bbox"] = [float(v) for v in mask_util.toBbox(r["segmentation"])]


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
    (segm), in the toolkit's order (:func:`_toolkit_order`); a segmentation keeps its box where it
    has one (:func:`_boxes_decide_areas`); COCO AP with pycocotools and the toolkit's ``ignore``
    rule (at most 100 detections per image, the highest scores); the ground truth of
    :func:`coco_ground_truth`. Returns :data:`COCO_KEYS` (-1 where undefined, and
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
    for e in _toolkit_order(entries, [k[0] for k in index]):
        if e["bbox" if ann_type == "bbox" else "segmentation"] is None:
            continue
        r = {"image_id": index[(e["scene_id"], e["image_id"])], "category_id": e["category_id"], "score": e["score"]}
        if e["bbox"] is not None:
            r["bbox"] = e["bbox"]
        if ann_type == "segm":
            r["segmentation"] = compressed_rle(e["segmentation"])
        results.append(r)
    if ann_type == "segm" and results and "bbox" in results[0]:
        _boxes_decide_areas(results)
    stats = _coco_eval(gt, results, ann_type) if results and gt["annotations"] else np.full(len(COCO_KEYS), -1.0)
    return {**{k: float(v) for k, v in zip(COCO_KEYS, stats)}, "average_time_per_image": avg_time}

