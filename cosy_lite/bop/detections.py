"""2D detections: the per-image :class:`Detections` record, BOP22 detection JSON, oracle detections.

BOP22 2D detection / segmentation results (bop_toolkit ``inout.save_coco_results``,
``scripts/eval_bop22_coco.py``) are a JSON list, one entry per detection::

    {"scene_id": int, "image_id": int, "category_id": obj_id, "score": float,
     "bbox": [x, y, w, h] (pixels), "segmentation": {"size": [H, W], "counts": str (COCO RLE)},
     "time": seconds for the whole image (-1 if unknown)}

BOP's published default detections for each dataset use the same format, so
:func:`read_detections_json` loads those too (``segmentation`` may be compressed or uncompressed
RLE, and may be absent). Boxes inside the library are ``xyxy`` with exclusive right/bottom edges,
so ``[x, y, w, h] <-> [x, y, x + w, y + h]``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import torch

from cosy_lite.bop import io
from cosy_lite.errors import BopFormatError

ImageKey = tuple[int, int]  # (scene_id, im_id)
# A box narrower or lower than this has nothing to crop; its box-based starting pose would be
# hundreds of metres away (depth = focal length x diameter / box size). Such detections are skipped.
MIN_BOX_SIZE_PX = 1.0


@dataclass
class Detections:
    """Detections in one image (readers and the detector return them by decreasing score)."""

    boxes: torch.Tensor  # [N,4] float32 x0, y0, x1, y1 [px]
    obj_ids: torch.Tensor  # [N] int64 BOP object ids
    scores: torch.Tensor  # [N] float32
    masks: torch.Tensor | None = None  # [N,H,W] bool, or None when not available / not loaded
    time_s: float = -1.0  # seconds spent on the image (BOP "time"; -1 = unknown)

    def __post_init__(self) -> None:
        n = len(self.boxes)
        if self.boxes.shape != (n, 4) or self.obj_ids.shape != (n,) or self.scores.shape != (n,):
            raise ValueError(f"Detections: boxes {tuple(self.boxes.shape)}, obj_ids {tuple(self.obj_ids.shape)}, "
                             f"scores {tuple(self.scores.shape)} do not fit [N,4], [N], [N]")
        if self.masks is not None and (self.masks.ndim != 3 or len(self.masks) != n):
            raise ValueError(f"Detections: masks {tuple(self.masks.shape)} do not fit [{n},H,W]")

    def __len__(self) -> int:
        return len(self.boxes)

    @classmethod
    def empty(cls, image_size: tuple[int, int] | None = None) -> "Detections":
        """No detections; ``image_size=(H, W)`` gives an empty ``[0,H,W]`` mask tensor."""
        masks = None if image_size is None else torch.zeros((0, *image_size), dtype=torch.bool)
        return cls(torch.zeros((0, 4)), torch.zeros(0, dtype=torch.int64), torch.zeros(0), masks)

    def select(self, keep: torch.Tensor) -> "Detections":
        """Subset by a bool mask or index tensor (``time_s`` kept)."""
        return Detections(self.boxes[keep], self.obj_ids[keep], self.scores[keep],
                          None if self.masks is None else self.masks[keep], self.time_s)

    def to(self, device: torch.device | str) -> "Detections":
        return Detections(self.boxes.to(device), self.obj_ids.to(device), self.scores.to(device),
                          None if self.masks is None else self.masks.to(device), self.time_s)


def degenerate_boxes(det: Detections) -> torch.Tensor:
    """``[N]`` bool: boxes with a non-finite corner or a side under :data:`MIN_BOX_SIZE_PX`."""
    boxes = det.boxes.double()
    sides = boxes[:, 2:] - boxes[:, :2]
    return ~torch.isfinite(boxes).all(dim=1) | ~(sides >= MIN_BOX_SIZE_PX).all(dim=1)


def describe_boxes(det: Detections, which: torch.Tensor) -> str:
    """``obj_id N box [x1, y1, x2, y2]; ...`` of the detections ``which`` (bool [N]), for messages."""
    idx = which.nonzero().flatten().tolist()
    listed = [f"obj_id {int(det.obj_ids[i])} box {[round(float(v), 2) for v in det.boxes[i]]}" for i in idx[:5]]
    return "; ".join(listed) + (f"; ... ({len(idx)} in all)" if len(idx) > 5 else "")


# ----------------------------------------------------------------------------- masks <-> RLE


def mask_to_rle(mask: np.ndarray) -> dict[str, Any]:
    """``[H,W]`` bool -> compressed COCO RLE ``{"size": [H, W], "counts": str}`` (JSON-ready)."""
    from pycocotools import mask as mask_util

    rle = mask_util.encode(np.asfortranarray(mask.astype(np.uint8)))
    return {"size": [int(s) for s in rle["size"]], "counts": rle["counts"].decode("ascii")}


def rle_to_mask(rle: dict[str, Any]) -> np.ndarray:
    """Compressed (``counts`` str) or uncompressed (``counts`` list) COCO RLE -> ``[H,W]`` bool."""
    from pycocotools import mask as mask_util

    return mask_util.decode(compressed_rle(rle)).astype(bool)


def compressed_rle(rle: dict[str, Any]) -> dict[str, Any]:
    """A COCO RLE as pycocotools takes it: run lengths (a list) compressed, a string's counts as bytes."""
    from pycocotools import mask as mask_util

    h, w = rle["size"]
    if isinstance(rle["counts"], list):
        return mask_util.frPyObjects(rle, h, w)
    return {"size": [h, w], "counts": rle["counts"].encode("ascii") if isinstance(rle["counts"], str) else rle["counts"]}


def xyxy_to_xywh(boxes: torch.Tensor) -> torch.Tensor:
    """``[N,4]`` x0, y0, x1, y1 -> x, y, w, h."""
    return torch.cat([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]], dim=1)


def xywh_to_xyxy(boxes: torch.Tensor) -> torch.Tensor:
    """``[N,4]`` x, y, w, h -> x0, y0, x1, y1."""
    return torch.cat([boxes[:, :2], boxes[:, :2] + boxes[:, 2:]], dim=1)


# ----------------------------------------------------------------------------- writing


def detections_to_bop22(detections: Mapping[ImageKey, Detections]) -> list[dict[str, Any]]:
    """BOP22 result entries (see the module docstring), images in key order, detections in given order."""
    out = []
    for (scene_id, im_id), det in sorted(detections.items()):
        boxes = xyxy_to_xywh(det.boxes.detach().cpu().double()).tolist()
        masks = None if det.masks is None else det.masks.detach().cpu().numpy()
        for k in range(len(det)):
            entry = {"scene_id": int(scene_id), "image_id": int(im_id), "category_id": int(det.obj_ids[k]),
                     "score": float(det.scores[k]), "bbox": [float(v) for v in boxes[k]]}
            if masks is not None:
                entry["segmentation"] = mask_to_rle(masks[k])
            entry["time"] = float(det.time_s)
            out.append(entry)
    return out


def write_detections_json(path: str | Path, detections: Mapping[ImageKey, Detections]) -> None:
    """Write a BOP22 detection/segmentation results file (one detection per line), atomically.

    BOP expects the name ``METHOD_DATASET-SPLIT.json`` (e.g. ``cosylite_ycbv-test.json``).
    """
    write_bop22_entries(path, detections_to_bop22(detections))


def write_bop22_entries(path: str | Path, entries: list[dict[str, Any]]) -> None:
    """Write BOP22 entries (:func:`detections_to_bop22`) as a results file, one per line, atomically."""
    io.atomic_write_text(path, "[\n" + ",\n".join(json.dumps(e) for e in entries) + "\n]\n")


# ----------------------------------------------------------------------------- reading


def _int(path: Path, fld: str, v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise BopFormatError(path, fld, f"expected an integer, got {v!r}")
    return v


def _number(path: Path, fld: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise BopFormatError(path, fld, f"expected a finite number, got {v!r}")
    return float(v)


def _bbox(path: Path, fld: str, v: Any) -> list[float]:
    if not isinstance(v, list) or len(v) != 4:
        raise BopFormatError(path, fld, f"expected 4 numbers [x, y, w, h], got {v!r}")
    x, y, w, h = (_number(path, fld, c) for c in v)
    if w < 0 or h < 0:
        raise BopFormatError(path, fld, f"width and height must be >= 0, got {v!r}")
    return [x, y, w, h]


def _segmentation(path: Path, fld: str, v: Any) -> dict[str, Any]:
    if not isinstance(v, dict) or "counts" not in v or "size" not in v:
        raise BopFormatError(path, fld, "expected a COCO RLE {'size': [H, W], 'counts': str or list}")
    size = v["size"]
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(s, int) and s > 0 for s in size)):
        raise BopFormatError(path, fld + ".size", f"expected [H, W] positive ints, got {size!r}")
    if size[0] * size[1] > io.MAX_IMAGE_PIXELS:  # a mask is decoded to [H, W]: the limit of every image read
        raise BopFormatError(path, fld + ".size", f"{size[1]} x {size[0]} pixels: more than the limit of "
                             f"{io.MAX_IMAGE_PIXELS / 1e6:.0f} MP (cosy_lite.bop.io.MAX_IMAGE_PIXELS)")
    counts = v["counts"]
    if not isinstance(counts, str) and not (isinstance(counts, list) and all(isinstance(c, int) for c in counts)):
        raise BopFormatError(path, fld + ".counts", "expected a compressed RLE string or a list of ints")
    if isinstance(counts, list) and sum(counts) != size[0] * size[1]:
        raise BopFormatError(path, fld + ".counts", f"run lengths sum to {sum(counts)}, not H*W = {size[0] * size[1]}")
    return v


@dataclass
class _Entry:
    scene_id: int
    im_id: int
    obj_id: int
    score: float
    bbox: list[float] | None
    segmentation: dict[str, Any] | None
    time: float


def _parse_entry(path: Path, i: int, d: Any, valid_obj_ids: set[int] | None) -> _Entry:
    where = f"[{i}]"
    if not isinstance(d, dict):
        raise BopFormatError(path, where, f"expected an object, got {type(d).__name__}")
    for key in ("scene_id", "image_id", "category_id", "score"):
        if key not in d:
            raise BopFormatError(path, f"{where}.{key}", "missing key")
    obj_id = _int(path, f"{where}.category_id", d["category_id"])
    if valid_obj_ids is not None and obj_id not in valid_obj_ids:
        raise BopFormatError(path, f"{where}.category_id", f"unknown obj_id {obj_id} (known: {sorted(valid_obj_ids)})")
    bbox = d.get("bbox")
    bbox = _bbox(path, f"{where}.bbox", bbox) if bbox not in (None, []) else None
    seg = d.get("segmentation")
    seg = _segmentation(path, f"{where}.segmentation", seg) if seg not in (None, {}) else None
    if bbox is None and seg is None:
        raise BopFormatError(path, f"{where}.bbox", "missing key (and no segmentation to derive it from)")
    time = _number(path, f"{where}.time", d["time"]) if "time" in d else -1.0
    return _Entry(_int(path, f"{where}.scene_id", d["scene_id"]), _int(path, f"{where}.image_id", d["image_id"]),
                  obj_id, _number(path, f"{where}.score", d["score"]), bbox, seg, time)


def _image_detections(path: Path, entries: list[tuple[int, _Entry]], with_masks: bool) -> Detections:
    from pycocotools import mask as mask_util

    entries = sorted(entries, key=lambda ie: -ie[1].score)
    boxes = []
    for _, e in entries:
        if e.bbox is not None:
            boxes.append(e.bbox)
        else:
            assert e.segmentation is not None  # _parse_entry rejects an entry with neither
            boxes.append(mask_util.toBbox(compressed_rle(e.segmentation)).tolist())
    masks = None
    if with_masks and any(e.segmentation is not None for _, e in entries):  # none has one: boxes only
        arrays = []
        for i, e in entries:
            if e.segmentation is None:
                raise BopFormatError(path, f"[{i}].segmentation", "missing key (masks were asked for)")
            arrays.append(rle_to_mask(e.segmentation))
        shapes = {a.shape for a in arrays}
        if len(shapes) > 1:
            raise BopFormatError(path, f"[{entries[0][0]}].segmentation.size", f"masks of one image differ in size: {shapes}")
        masks = torch.from_numpy(np.stack(arrays))
    times = {e.time for _, e in entries}
    return Detections(
        boxes=xywh_to_xyxy(torch.tensor(boxes, dtype=torch.float64).reshape(-1, 4)).float(),
        obj_ids=torch.tensor([e.obj_id for _, e in entries], dtype=torch.int64),
        scores=torch.tensor([e.score for _, e in entries], dtype=torch.float32),
        masks=masks, time_s=max(times),
    )


def read_detections_json(path: str | Path, valid_obj_ids: Iterable[int] | None = None,
                         with_masks: bool = False) -> dict[ImageKey, Detections]:
    """Read a BOP22 detection file (ours or BOP's default detections) into per-image detections.

    Args:
        path: the JSON file.
        valid_obj_ids: if given, any other ``category_id`` is an error.
        with_masks: decode the RLE masks (every entry of an image then needs ``segmentation``, unless
            none has one: then its detections are boxes only); off by default because full-image
            masks of a whole test split take gigabytes.
    Returns:
        ``{(scene_id, im_id): Detections}`` sorted by decreasing score within each image; images
        without any detection are absent. A missing ``bbox`` is derived from the mask.
    Raises:
        BopFormatError naming the entry and key (e.g. ``[12].score``) for malformed content.
    """
    path = Path(path)
    per_image: dict[ImageKey, list[tuple[int, _Entry]]] = {}
    for i, e in enumerate(_read_entries(path, valid_obj_ids)):
        per_image.setdefault((e.scene_id, e.im_id), []).append((i, e))
    return {key: _image_detections(path, entries, with_masks) for key, entries in sorted(per_image.items())}


def _read_entries(path: Path, valid_obj_ids: Iterable[int] | None) -> list[_Entry]:
    data = io.load_json(path)
    if not isinstance(data, list):
        raise BopFormatError(path, "", f"expected a JSON list of detections, got {type(data).__name__}")
    valid = None if valid_obj_ids is None else {int(i) for i in valid_obj_ids}
    return [_parse_entry(path, i, d, valid) for i, d in enumerate(data)]


def read_bop22_entries(path: str | Path, valid_obj_ids: Iterable[int] | None = None) -> list[dict[str, Any]]:
    """The entries of a BOP22 detection file, checked as :func:`read_detections_json` checks them
    (errors name the entry and key), in file order, masks left as RLE (nothing decoded): dicts with
    ``scene_id, image_id, category_id, score``, ``bbox`` and ``segmentation`` (None where absent)
    and ``time`` (-1 where absent)."""
    return [{"scene_id": e.scene_id, "image_id": e.im_id, "category_id": e.obj_id, "score": e.score,
             "bbox": e.bbox, "segmentation": e.segmentation, "time": e.time}
            for e in _read_entries(Path(path), valid_obj_ids)]


# ----------------------------------------------------------------------------- oracle


def oracle_detections(dataset, record, with_masks: bool = True, min_visib_fract: float = 0.0) -> Detections:
    """Detections from the ground truth: ``bbox_visib`` boxes, ``mask_visib`` masks, score 1.

    Args:
        dataset: the :class:`~cosy_lite.bop.dataset.BopDataset` of ``record``.
        record: an :class:`~cosy_lite.bop.dataset.ImageRecord` with ``gt_info``.
        with_masks: load the visible masks.
        min_visib_fract: instances less visible than this are left out (no visible pixel: always).
    """
    if record.gt_info is None:
        raise BopFormatError(dataset.scene_dir(record.split, record.scene_id) / "scene_gt_info.json", "",
                             "file not found (oracle detections need bbox_visib)")
    keep = [k for k, info in enumerate(record.gt_info)
            if info.px_count_visib > 0 and info.visib_fract >= min_visib_fract]
    boxes = torch.tensor([record.gt_info[k].bbox_visib for k in keep], dtype=torch.float32).reshape(-1, 4)
    masks = None
    if with_masks:
        arrays = [io.load_mask(dataset.mask_path(record.split, record.scene_id, record.im_id, k, visib=True)) for k in keep]
        size = arrays[0].shape if arrays else io.load_image(record.rgb_path).shape[:2]
        masks = torch.from_numpy(np.stack(arrays)) if arrays else torch.zeros((0, *size), dtype=torch.bool)
    return Detections(
        boxes=xywh_to_xyxy(boxes), obj_ids=torch.tensor([record.gt[k].obj_id for k in keep], dtype=torch.int64),
        scores=torch.ones(len(keep)), masks=masks,
    )
