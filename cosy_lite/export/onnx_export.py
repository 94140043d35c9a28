"""Export the detector, coarse, refiner and coarse scorer networks to ONNX with self-describing metadata.

- Pose networks: :class:`~cosy_lite.nets.pose_net.PoseNet` traced as it is, ``images
  [batch, 6, h, w]`` float32 in [0, 1] (crop, rendering) -> ``delta [batch, 9]``; dynamic batch,
  fixed crop size (the one it was trained at). After export the graph runs in onnxruntime on a
  random batch and its largest difference to torch is recorded (``check``).
- Detector: torchvision's Mask R-CNN (:attr:`Detector.net`) with its pre- and post-processing
  (resize, normalisation, NMS, mask pasting): ``image [3, height, width]`` float32 in [0, 1] ->
  ``boxes [n, 4]`` (xyxy px), ``labels [n]`` int64 (1..; obj_id = obj_ids[label - 1]),
  ``scores [n]``, ``masks [n, 1, height, width]`` (probabilities). The legacy TorchScript-based
  exporter is used (the dynamo exporter fails on torchvision's NMS). torchvision's ONNX version of
  the mask pasting is a loop that grows its output by concatenation (0.75 s of 0.9 s for 100
  detections at 640x480 in onnxruntime); while exporting it is replaced by
  :func:`paste_masks_separable`, the same bilinear resize-and-place written as two batched matrix
  products.
- Coarse scorer (:class:`~cosy_lite.nets.appearance_scorer.AppearanceScorer`, ``start="appearance"``):
  ``crops [batch, 3, 64, 64]`` float32 in [0, 1] (the detection, turned and cut as the templates
  are) -> ``descriptors [batch, D]``; its trunk, template shading and ``iou_weight`` go into the
  metadata. The templates' descriptors stay those of the frozen trunk, rendered and cached once
  at run time.

Each file gets ``metadata_props`` (:data:`~cosy_lite.export.manifest.META_KEYS`) and passes
``onnx.checker``; :func:`export_models` writes the folder and its ``manifest.json``.
"""

from __future__ import annotations

import copy
import json
import warnings
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Sequence, cast

import numpy as np
import torch
from torch import Tensor, nn

from cosy_lite.export.manifest import (
    POSE_INPUT_CHANNELS,
    SCORER_INPUT_CHANNELS,
    SCORER_KIND,
    Manifest,
    ModelEntry,
    file_digest,
    metadata_of,
    write_metadata,
)

if TYPE_CHECKING:
    from cosy_lite.nets.detector import Detector
    from cosy_lite.weights.loaders import ScorerModel

OPSET = 17  # >= 11 for Mask R-CNN (NMS, RoiAlign); 17 is what the legacy exporter knows well
POSE_INPUT, POSE_OUTPUT = "images", "delta"
DETECTOR_INPUT = "image"
DETECTOR_OUTPUTS = ("boxes", "labels", "scores", "masks")
SCORER_INPUT, SCORER_OUTPUT = "crops", "descriptors"
CHECK_BATCH = 2


def _finish(path: Path, entry: ModelEntry, config: dict[str, Any]) -> ModelEntry:
    write_metadata(path, metadata_of(entry, config))
    entry.bytes, entry.sha256 = file_digest(path)
    return entry


def _legacy_export(module: nn.Module, args: tuple, path: Path, **kwargs: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():  # tracer warnings about Python-side shape arithmetic, deprecation notes
        warnings.simplefilter("ignore")
        torch.onnx.export(module, args, str(path), dynamo=False, opset_version=kwargs.pop("opset", OPSET),
                          do_constant_folding=True, **kwargs)


def export_pose_net(net: nn.Module, path: str | Path, kind: str, crop_resolution: Sequence[int],
                    obj_ids: Sequence[int], config: dict[str, Any] | None = None, source: str = "",
                    opset: int = OPSET, seed: int = 0) -> ModelEntry:
    """Write ``net`` (a PoseNet, eval mode is set on a copy) to ``path``; returns its manifest entry.

    Args:
        kind: "coarse" or "refiner"; crop_resolution: (h, w) px of its input crops;
        obj_ids: objects it was trained on; config: its PoseNetConfig as a dict (stored as metadata);
        source: where the weights came from (a checkpoint path).
    ``check`` of the entry: max |torch - onnxruntime| on a random batch of :data:`CHECK_BATCH`.
    """
    path = Path(path)
    h, w = (int(v) for v in crop_resolution)
    module = copy.deepcopy(net).float().cpu().eval()
    x = torch.rand(CHECK_BATCH, POSE_INPUT_CHANNELS, h, w, generator=torch.Generator().manual_seed(seed))
    # A flow refiner is fully convolutional: its crops may be larger than it was trained on
    # (InferenceConfig.refiner_fine_iterations), so its graph takes any height and width.
    flow = getattr(net, "output", "delta") == "flow"
    dynamic = ({POSE_INPUT: {0: "batch", 2: "height", 3: "width"}, POSE_OUTPUT: {0: "batch", 2: "cells_y", 3: "cells_x"}}
               if flow else {POSE_INPUT: {0: "batch"}, POSE_OUTPUT: {0: "batch"}})
    _legacy_export(module, (x,), path, opset=opset, input_names=[POSE_INPUT], output_names=[POSE_OUTPUT],
                   dynamic_axes=dynamic)
    entry = ModelEntry(file=path.name, kind=kind, obj_ids=sorted(int(i) for i in obj_ids), input_name=POSE_INPUT,
                       input_shape=["batch", POSE_INPUT_CHANNELS, h, w], crop_resolution=[h, w], opset=opset,
                       source=str(source))
    return _checked(_finish(path, entry, dict(config or {})), path, module, {POSE_INPUT: x})


def _checked(entry: ModelEntry, path: Path, module: nn.Module, feeds: dict[str, Tensor]) -> ModelEntry:
    """``entry`` with its ``check``: max |torch - onnxruntime| of ``module`` on ``feeds``."""
    with torch.no_grad():
        ref = module(*feeds.values()).numpy()
    out = _run_once(path, {k: v.numpy() for k, v in feeds.items()})[0]
    entry.check = {"batch": CHECK_BATCH, "max_abs_diff": float(np.abs(out - ref).max()),
                   "max_abs_output": float(np.abs(ref).max())}
    return entry


def export_scorer(scorer: ScorerModel, path: str | Path, source: str = "", opset: int = OPSET,
                  seed: int = 0) -> ModelEntry:
    """Write a coarse scorer (:func:`~cosy_lite.weights.loaders.load_scorer`) to ``path``: ``crops
    [batch, 3, S, S]`` -> ``descriptors [batch, D]``; returns its manifest entry (``check`` as
    :func:`export_pose_net`). Its trunk, template shading and ``iou_weight`` go into the metadata."""
    from cosy_lite.nets.appearance_templates import CROP_SIZE

    path = Path(path)
    module = copy.deepcopy(scorer.net).float().cpu().eval()
    x = torch.rand(CHECK_BATCH, SCORER_INPUT_CHANNELS, CROP_SIZE, CROP_SIZE,
                   generator=torch.Generator().manual_seed(seed))
    _legacy_export(module, (x,), path, opset=opset, input_names=[SCORER_INPUT], output_names=[SCORER_OUTPUT],
                   dynamic_axes={SCORER_INPUT: {0: "batch"}, SCORER_OUTPUT: {0: "batch"}})
    entry = ModelEntry(file=path.name, kind=SCORER_KIND, obj_ids=list(scorer.obj_ids), input_name=SCORER_INPUT,
                       input_shape=["batch", SCORER_INPUT_CHANNELS, CROP_SIZE, CROP_SIZE],
                       crop_resolution=[CROP_SIZE, CROP_SIZE], opset=opset, source=str(source))
    config = {"trunk": str(module.trunk_name), "template_shading": scorer.shading,
              "iou_weight": float(cast(Tensor, module.iou_weight))}
    return _checked(_finish(path, entry, config), path, module, {SCORER_INPUT: x})


def export_detector(detector: Detector, path: str | Path, source: str = "", opset: int = OPSET,
                    seed: int = 0) -> ModelEntry:
    """Write a :class:`~cosy_lite.nets.detector.Detector` (its Mask R-CNN with pre/post-processing)
    to ``path``; returns its manifest entry. The label map and config go into the metadata."""
    path = Path(path)
    cfg = detector.config
    net = copy.deepcopy(detector.net).float().cpu().eval()
    image = torch.rand(3, int(cfg.min_size), int(cfg.max_size), generator=torch.Generator().manual_seed(seed))
    with _separable_mask_paste():
        _legacy_export(net, ([image],), path, opset=opset, input_names=[DETECTOR_INPUT],
                       output_names=list(DETECTOR_OUTPUTS),
                       dynamic_axes={DETECTOR_INPUT: {1: "height", 2: "width"}, "boxes": {0: "n"}, "labels": {0: "n"},
                                     "scores": {0: "n"}, "masks": {0: "n", 2: "height", 3: "width"}})
    entry = ModelEntry(file=path.name, kind="detector", obj_ids=list(detector.label_map.obj_ids),
                       input_name=DETECTOR_INPUT, input_shape=[3, "height", "width"], opset=opset, source=str(source))
    return _finish(path, entry, asdict(cfg))


def _interpolation_matrix(start: Tensor, size: Tensor, length: Tensor | int, n_src: int) -> Tensor:
    """``[N, length, n_src]`` weights that resize ``n_src`` samples to ``size[n]`` samples placed at
    ``start[n]`` on an axis of ``length`` pixels (bilinear, ``align_corners=False``, as
    ``F.interpolate``; zero outside the placed span)."""
    pos = torch.arange(length, dtype=torch.int64)  # type: ignore[arg-type]  # a 0-dim tensor when traced; stub: Number
    r = pos[None, :] - start[:, None]  # [N, L] index into the resized mask
    valid = (r >= 0) & (r < size[:, None])
    scale = torch.full_like(size, n_src, dtype=torch.float32) / size.to(torch.float32)
    src = ((r.to(torch.float32) + 0.5) * scale[:, None] - 0.5).clamp(min=0.0)
    i0 = src.floor()
    l1 = src - i0
    i0 = i0.to(torch.int64)
    i1 = (i0 + 1).clamp(max=n_src - 1)
    idx = torch.arange(n_src, dtype=torch.int64)
    w = (1.0 - l1)[..., None] * (i0[..., None] == idx).to(torch.float32) \
        + l1[..., None] * (i1[..., None] == idx).to(torch.float32)
    return w * valid[..., None].to(torch.float32)


def paste_masks_separable(masks: Tensor, boxes: Tensor, img_shape: tuple, padding: int = 1) -> Tensor:
    """torchvision's ``paste_masks_in_image`` (``masks [N,1,M,M]`` probabilities, ``boxes [N,4]``
    xyxy px -> ``[N,1,H,W]``) as ``Ry @ mask @ Rx^T``: bilinear resizing is separable, so each
    pasted mask is two products with per-box interpolation matrices (same boxes, padding and
    integer rounding as torchvision; equal to ~1e-6)."""
    from torchvision.models.detection.roi_heads import expand_boxes, expand_masks

    padded, scale = expand_masks(masks, padding=padding)
    boxes = expand_boxes(boxes, scale).to(dtype=torch.int64)
    im_h, im_w = img_shape
    n_src = int(padded.shape[-1])
    one = torch.ones_like(boxes[:, 0])
    w = torch.maximum(boxes[:, 2] - boxes[:, 0] + 1, one)
    h = torch.maximum(boxes[:, 3] - boxes[:, 1] + 1, one)
    ry = _interpolation_matrix(boxes[:, 1], h, im_h, n_src)  # [N, H, S]
    rx = _interpolation_matrix(boxes[:, 0], w, im_w, n_src)  # [N, W, S]
    # [N,1,H,S] @ ([N,1,S,S] @ [N,1,S,W]): the large result is made 4-D, not reshaped after (a copy in onnxruntime)
    return torch.matmul(ry[:, None], torch.matmul(padded, rx.transpose(1, 2)[:, None]))


@contextmanager
def _separable_mask_paste() -> Iterator[None]:
    """torchvision's detection transform pastes masks with :func:`paste_masks_separable` (export only)."""
    from torchvision.models.detection import transform

    original = transform.paste_masks_in_image
    transform.paste_masks_in_image = paste_masks_separable
    try:
        yield
    finally:
        transform.paste_masks_in_image = original


def _run_once(path: Path, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return session.run(None, feeds)


def _pose_net_from_checkpoint(path: Path, kind: str) -> tuple[nn.Module, tuple[int, int], list[int], dict[str, Any]]:
    from cosy_lite.weights.checkpoint import load_checkpoint
    from cosy_lite.weights.loaders import load_pose_model

    model = load_pose_model(path, kind)
    ckpt = load_checkpoint(path, kind=kind)
    config = ckpt.meta.get("net", ckpt.config.get("net", {}))
    assert isinstance(model.net, nn.Module)  # built from the checkpoint's config (not an ONNX callable)
    return model.net, model.crop_resolution, model.obj_ids, dict(config)


def export_models(out_dir: str | Path, detector: str | Path | None = None, coarse: str | Path | None = None,
                  refiner: str | Path | None = None, quantize: str | None = None, opset: int = OPSET,
                  inference: dict[str, Any] | None = None, scorer: str | Path | None = None) -> Manifest:
    """Export the given checkpoints into ``out_dir`` (``detector.onnx``, ``coarse.onnx``,
    ``refiner.onnx``, ``scorer.onnx``; with ``quantize="int8"`` also ``coarse.int8.onnx``,
    ``refiner.int8.onnx``) and write ``manifest.json`` with ``inference``, how they are meant to
    run (InferenceConfig's fields, e.g. a reference set's; None: the defaults).
    At least one pose or detector checkpoint is needed (a scorer alone poses nothing).

    Raises CheckpointError naming a checkpoint that is missing, unreadable, refused (not
    weights-only) or of the wrong kind; every checkpoint is checked before a file is written.
    """
    from cosy_lite.export.quantize import QUANTIZERS
    from cosy_lite.weights.loaders import load_detector, load_scorer

    if detector is None and coarse is None and refiner is None:
        raise ValueError("nothing to export: give at least one of detector, coarse, refiner")
    if quantize is not None and quantize not in QUANTIZERS:
        raise ValueError(f"quantize must be one of {sorted(QUANTIZERS)}, got {quantize!r}")
    # Every checkpoint is read (weights-only) and checked before anything is written.
    det_model = load_detector(detector) if detector is not None else None
    pose = {kind: _pose_net_from_checkpoint(Path(ckpt), kind)
            for kind, ckpt in (("coarse", coarse), ("refiner", refiner)) if ckpt is not None}
    scorer_model = load_scorer(scorer) if scorer is not None else None
    sources = {"coarse": coarse, "refiner": refiner}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    entries: dict[str, ModelEntry] = {}
    if det_model is not None:
        entries["detector"] = export_detector(det_model, out_dir / "detector.onnx", str(detector), opset)
    for kind, (net, crop, obj_ids, config) in pose.items():
        entries[kind] = export_pose_net(net, out_dir / f"{kind}.onnx", kind, crop, obj_ids, config,
                                        str(sources[kind]), opset)
        if quantize is not None:
            entries[f"{kind}.{quantize}"] = QUANTIZERS[quantize](out_dir / f"{kind}.onnx",
                                                                 out_dir / f"{kind}.{quantize}.onnx", entries[kind],
                                                                 config)
    if scorer_model is not None:
        entries[SCORER_KIND] = export_scorer(scorer_model, out_dir / "scorer.onnx", str(scorer), opset)
    manifest = Manifest(out_dir, entries, inference=dict(inference or {}))
    manifest.write()
    return manifest


def describe(manifest: Manifest) -> list[str]:
    """One line per exported file (for the command's output)."""
    lines = []
    for name, e in sorted(manifest.models.items()):
        extra = f", crop {e.crop_resolution[0]}x{e.crop_resolution[1]}" if e.crop_resolution else ""
        check = f", {json.dumps(e.check)}" if e.check else ""
        lines.append(f"{manifest.root / e.file}: {name} ({e.bytes / 1e6:.1f} MB, obj_ids {e.obj_ids}{extra}{check})")
    return lines
