"""onnxruntime sessions of the exported networks, called like the torch modules the pipeline uses.

- :class:`OnnxPoseNet`: ``images [B,6,h,w]`` float32 in [0, 1] -> ``delta [B,9]`` (numpy in ->
  numpy out with :meth:`~OnnxPoseNet.run`; torch tensors in -> tensor out when called, so it
  drops into :func:`~cosy_lite.nets.render_and_compare.iterate_poses`).
- :class:`OnnxDetector`: ``rgb [H,W,3]`` uint8 -> boxes, obj_ids, scores, masks (numpy,
  :meth:`~OnnxDetector.run`) or :class:`~cosy_lite.bop.detections.Detections` (:meth:`~OnnxDetector.detect`).
- :class:`OnnxScorer`: the coarse scorer, ``crops [B,3,64,64]`` -> ``descriptors [B,D]`` (tensor in,
  tensor out), with the ``iou_weight`` and template shading it was trained with.
- :func:`load_onnx_models`: an export folder (``manifest.json`` + ``.onnx`` files) -> these
  sessions, the pose networks as :class:`~cosy_lite.weights.loaders.PoseModel` (precision fp32
  or int8), in :class:`OnnxModels`.

The sessions themselves need only numpy and onnxruntime (torch is imported only to wrap tensors).
Sessions run with every graph optimisation on, ``threads`` intra-op threads, denormals flushed to
zero, and by default idle threads that sleep instead of spinning (spinning threads made networks
several times slower on CPUs shared with other jobs, as OpenMP's did for torch). Each file is
checked against its own metadata and, when given, its manifest entry: kind, obj_ids, crop size,
input layout; every mismatch raises :class:`~cosy_lite.export.manifest.OnnxModelError` naming
the file and the field.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from cosy_lite.export.manifest import (
    POSE_INPUT_CHANNELS,
    POSE_KINDS,
    REQUIRED_META,
    SCORER_INPUT_CHANNELS,
    SCORER_KIND,
    Manifest,
    ModelEntry,
    OnnxModelError,
    parse_json_meta,
)
from cosy_lite.nets.detection_masks import MASK_THRESHOLD, binary_masks
from cosy_lite.nets.flow_pose_net import DEPTH_CHANNELS, FLOW_CHANNELS
from cosy_lite.nets.flow_pose_solver import FLOW_STRIDE

if TYPE_CHECKING:
    from cosy_lite.nets.detector import LabelMap
    from cosy_lite.weights.loaders import PoseModel

PROVIDERS = ("CPUExecutionProvider",)
POSE_OUTPUTS = 9


def session_options(threads: int | None = None, spinning: bool = False) -> Any:
    """onnxruntime ``SessionOptions``: all graph optimisations, ``threads`` intra-op threads (None:
    onnxruntime's default, one per physical core), sequential execution, denormals as zero, idle
    threads spinning only if ``spinning``."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    if threads is not None:
        if int(threads) < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        so.intra_op_num_threads = int(threads)
    so.inter_op_num_threads = 1
    so.add_session_config_entry("session.set_denormal_as_zero", "1")
    so.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
    so.add_session_config_entry("session.inter_op.allow_spinning", "1" if spinning else "0")
    so.log_severity_level = 3  # errors only
    return so


def open_session(path: str | Path, threads: int | None = None, spinning: bool = False,
                 providers: Sequence[str] = PROVIDERS) -> Any:
    """An ``InferenceSession`` of ``path``; OnnxModelError naming the file when it is missing or
    not a loadable ONNX model (truncated, not protobuf, unsupported operators)."""
    import onnxruntime as ort

    path = Path(path)
    if not path.is_file():
        raise OnnxModelError(path, "", "ONNX file not found")
    try:
        return ort.InferenceSession(str(path), session_options(threads, spinning), providers=list(providers))
    except Exception as e:  # noqa: BLE001 - onnxruntime raises its own Fail/InvalidProtobuf/... types
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise OnnxModelError(path, "", f"not a loadable ONNX model ({type(e).__name__}: {first[:300]})") from None


def _metadata(session: Any, path: Path) -> dict[str, str]:
    meta = dict(session.get_modelmeta().custom_metadata_map)
    missing = [k for k in REQUIRED_META if k not in meta]
    if missing:
        raise OnnxModelError(path, f"metadata_props[{missing[0]}]",
                             f"missing {missing} (not exported by cosy-lite export?)")
    return meta


def _check_against(path: Path, entry: ModelEntry | None, name: str, facts: dict[str, Any]) -> None:
    """Each fact of the file (metadata key -> value) must equal the manifest entry's field."""
    if entry is None:
        return
    fields = {"cosy_lite.kind": entry.kind, "cosy_lite.obj_ids": list(entry.obj_ids),
              "cosy_lite.crop_resolution": entry.crop_resolution, "cosy_lite.quantization": entry.quantization}
    for key, value in facts.items():
        if key in fields and fields[key] != value:
            raise OnnxModelError(path, f"metadata_props[{key}]", f"is {value}, but manifest.json models.{name}."
                                 f"{key.split('.', 1)[1]} says {fields[key]} (file from another export?)")


class OnnxPoseNet:
    """A coarse or refiner network in onnxruntime.

    Args:
        path: the ``.onnx`` file; threads, spinning: see :func:`session_options`.
        kind: expected kind ("coarse" | "refiner"; None: any pose network).
        entry, name: its manifest entry and name, checked against the file's metadata.
    Attributes: kind, obj_ids, crop_resolution (h, w), quantization, config (dict), path.
    """

    def __init__(self, path: str | Path, threads: int | None = None, kind: str | None = None,
                 entry: ModelEntry | None = None, name: str = "", spinning: bool = False):
        self.path = Path(path)
        self.session = open_session(self.path, threads, spinning)
        meta = _metadata(self.session, self.path)
        self.kind = meta["cosy_lite.kind"]
        wanted = (kind,) if kind else POSE_KINDS
        if self.kind not in wanted:
            raise OnnxModelError(self.path, "metadata_props[cosy_lite.kind]",
                                 f"{self.kind!r}, expected {' or '.join(map(repr, wanted))}")
        self.obj_ids = [int(i) for i in parse_json_meta(meta, "cosy_lite.obj_ids", self.path)]
        crop = parse_json_meta(meta, "cosy_lite.crop_resolution", self.path)
        self.crop_resolution = (int(crop[0]), int(crop[1]))
        self.quantization = meta.get("cosy_lite.quantization", "none")
        self.config = json.loads(meta.get("cosy_lite.config", "{}"))
        _check_against(self.path, entry, name or self.kind, {
            "cosy_lite.kind": self.kind, "cosy_lite.obj_ids": self.obj_ids,
            "cosy_lite.crop_resolution": list(self.crop_resolution), "cosy_lite.quantization": self.quantization})
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if len(inputs) != 1 or len(outputs) != 1:
            raise OnnxModelError(self.path, "graph inputs/outputs", f"{len(inputs)} inputs and {len(outputs)} outputs, "
                                 "expected 1 and 1 (images -> delta)")
        shape = list(inputs[0].shape)
        h, w = self.crop_resolution
        # a flow refiner's graph takes any crop size (symbolic height and width); other graphs only their own
        self.any_size = len(shape) == 4 and all(isinstance(v, str) for v in shape[2:])
        if len(shape) != 4 or shape[1] != POSE_INPUT_CHANNELS or not (self.any_size or shape[2:] == [h, w]):
            raise OnnxModelError(self.path, f"input {inputs[0].name} shape", f"{shape}, expected "
                                 f"[batch, {POSE_INPUT_CHANNELS}, {h}, {w}] (6 channels: crop + rendering; "
                                 f"metadata crop_resolution {h}x{w})")
        self.output = "flow" if self.config.get("arch") == "flow" else "delta"
        channels = DEPTH_CHANNELS if self.config.get("depth_head") else FLOW_CHANNELS  # (dx, dy, confidence[, depth])
        stride = int(self.config.get("flow_stride", FLOW_STRIDE))  # exports before net.flow_stride: 8
        expected = [channels, h // stride, w // stride] if self.output == "flow" else [POSE_OUTPUTS]
        got = list(outputs[0].shape)[1:]  # symbolic (str) sizes of traced spatial dims match any value
        if len(got) != len(expected) or any(isinstance(g, int) and g != e for g, e in zip(got, expected)):
            raise OnnxModelError(self.path, f"output {outputs[0].name} shape", f"{list(outputs[0].shape)}, expected "
                                 f"[batch, {', '.join(map(str, expected))}] (metadata config arch: {self.output})")
        self.input_name = inputs[0].name

    def run(self, images: np.ndarray) -> np.ndarray:
        """``images [B,6,h,w]`` float32 in [0, 1] -> ``delta [B,9]`` (or a flow refiner's ``[B,3 or 4,h/8,w/8]``) float32."""
        x = np.ascontiguousarray(images, dtype=np.float32)
        size_ok = (x.ndim == 4 and x.shape[2] % 16 == 0 and x.shape[3] % 16 == 0 if self.any_size
                   else x.shape[2:] == self.crop_resolution)
        if x.ndim != 4 or x.shape[1] != POSE_INPUT_CHANNELS or not size_ok:
            size = "H,W] (H and W multiples of 16)" if self.any_size else f"{self.crop_resolution[0]},{self.crop_resolution[1]}]"
            raise ValueError(f"{self.path.name}: images must be [B,{POSE_INPUT_CHANNELS},{size}, got {x.shape}")
        return self.session.run(None, {self.input_name: x})[0]

    def __call__(self, images: Any) -> Any:
        """As :meth:`run`; a torch tensor in gives a torch tensor out (on the input's device)."""
        if isinstance(images, np.ndarray):
            return self.run(images)
        import torch

        out = self.run(images.detach().to("cpu", torch.float32).contiguous().numpy())
        return torch.from_numpy(out).to(images.device)

    def describe(self) -> str:
        return str(self.path)


class OnnxDetector:
    """The exported Mask R-CNN (pre- and post-processing inside the graph) in onnxruntime.

    Args: as :class:`OnnxPoseNet`. Attributes: obj_ids (label k -> obj_ids[k - 1]), config (the
    DetectorConfig as a dict), path.
    """

    def __init__(self, path: str | Path, threads: int | None = None, entry: ModelEntry | None = None,
                 name: str = "detector", spinning: bool = False):
        self.path = Path(path)
        self.session = open_session(self.path, threads, spinning)
        meta = _metadata(self.session, self.path)
        kind = meta["cosy_lite.kind"]
        if kind != "detector":
            raise OnnxModelError(self.path, "metadata_props[cosy_lite.kind]", f"{kind!r}, expected 'detector'")
        self.obj_ids = [int(i) for i in parse_json_meta(meta, "cosy_lite.obj_ids", self.path)]
        self.config = json.loads(meta.get("cosy_lite.config", "{}"))
        _check_against(self.path, entry, name, {"cosy_lite.kind": kind, "cosy_lite.obj_ids": self.obj_ids})
        inputs = self.session.get_inputs()
        outputs = [o.name for o in self.session.get_outputs()]
        if len(inputs) != 1 or len(inputs[0].shape) != 3 or inputs[0].shape[0] != 3:
            raise OnnxModelError(self.path, "graph input", f"{[(i.name, i.shape) for i in inputs]}, "
                                 "expected one image [3, height, width]")
        if outputs != ["boxes", "labels", "scores", "masks"]:
            raise OnnxModelError(self.path, "graph outputs",
                                 f"{outputs}, expected ['boxes', 'labels', 'scores', 'masks']")
        self.input_name = inputs[0].name
        self._table = np.asarray([0, *self.obj_ids], dtype=np.int64)

    @property
    def label_map(self) -> LabelMap:
        """The :class:`~cosy_lite.nets.detector.LabelMap` of the export (imports torchvision)."""
        from cosy_lite.nets.detector import LabelMap

        return LabelMap(tuple(self.obj_ids))

    def run(self, rgb: np.ndarray,
            mask_threshold: float = MASK_THRESHOLD) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``rgb [H,W,3]`` uint8 -> (boxes [N,4] float32 xyxy px, obj_ids [N] int64, scores [N]
        float32, masks [N,H,W] bool: probabilities above ``mask_threshold``), in the network's order
        (decreasing score per class)."""
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be [H,W,3] uint8, got {rgb.dtype} {rgb.shape}")
        image = np.ascontiguousarray(rgb.transpose(2, 0, 1), dtype=np.float32) / np.float32(255.0)
        boxes, labels, scores, masks = self.session.run(None, {self.input_name: image})
        return (boxes.astype(np.float32, copy=False), self._table[labels.astype(np.int64)],
                scores.astype(np.float32, copy=False), binary_masks(masks[:, 0], mask_threshold))

    def detect(self, rgb: np.ndarray, mask_threshold: float = MASK_THRESHOLD) -> Any:
        """:class:`~cosy_lite.bop.detections.Detections` of ``rgb`` (``time_s``: seconds of the network)."""
        import torch

        from cosy_lite.bop.detections import Detections

        t0 = time.perf_counter()
        boxes, obj_ids, scores, masks = self.run(rgb, mask_threshold)
        det = Detections(torch.from_numpy(boxes), torch.from_numpy(obj_ids), torch.from_numpy(scores),
                         torch.from_numpy(masks))
        det.time_s = time.perf_counter() - t0
        return det

    def describe(self) -> str:
        return str(self.path)


class OnnxScorer:
    """The coarse scorer of ``start="appearance"`` in onnxruntime: ``crops [B,3,S,S]`` float32 in
    [0, 1] (a torch tensor, as :func:`~cosy_lite.nets.appearance_templates.detection_crop` cuts
    them) -> ``descriptors [B,D]`` (a tensor), as the torch :class:`~cosy_lite.nets.appearance_scorer.AppearanceScorer`.

    Args: as :class:`OnnxPoseNet`. Attributes: obj_ids, crop_size (S), shading (how the templates
    it was trained against were rendered), iou_weight (float: the silhouette's share of the
    score), path.
    """

    def __init__(self, path: str | Path, threads: int | None = None, entry: ModelEntry | None = None,
                 name: str = SCORER_KIND, spinning: bool = False):
        self.path = Path(path)
        self.session = open_session(self.path, threads, spinning)
        meta = _metadata(self.session, self.path)
        if meta["cosy_lite.kind"] != SCORER_KIND:
            raise OnnxModelError(self.path, "metadata_props[cosy_lite.kind]",
                                 f"{meta['cosy_lite.kind']!r}, expected {SCORER_KIND!r}")
        self.obj_ids = [int(i) for i in parse_json_meta(meta, "cosy_lite.obj_ids", self.path)]
        crop = parse_json_meta(meta, "cosy_lite.crop_resolution", self.path)
        config = parse_json_meta(meta, "cosy_lite.config", self.path)
        _check_against(self.path, entry, name, {"cosy_lite.kind": SCORER_KIND, "cosy_lite.obj_ids": self.obj_ids,
                                                "cosy_lite.crop_resolution": crop})
        if not (isinstance(crop, list) and len(crop) == 2 and crop[0] == crop[1] and isinstance(crop[0], int)
                and crop[0] > 0):
            raise OnnxModelError(self.path, "metadata_props[cosy_lite.crop_resolution]",
                                 f"{crop!r}, expected [S, S] (the square crops the scorer describes)")
        weight = config.get("iou_weight") if isinstance(config, dict) else None
        if not (isinstance(config, dict) and isinstance(config.get("template_shading"), str)
                and isinstance(weight, (int, float)) and math.isfinite(weight)):
            raise OnnxModelError(self.path, "metadata_props[cosy_lite.config]", f"{str(config)[:200]}: expected "
                                 "template_shading (a string) and a finite iou_weight (not a cosy_lite scorer export?)")
        self.shading, self.iou_weight, self.crop_size = str(config["template_shading"]), float(weight), crop[0]
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        expected = [SCORER_INPUT_CHANNELS, self.crop_size, self.crop_size]
        if len(inputs) != 1 or len(outputs) != 1 or list(inputs[0].shape)[1:] != expected or len(outputs[0].shape) != 2:
            raise OnnxModelError(self.path, "graph inputs/outputs", f"{[(i.name, i.shape) for i in inputs]} -> "
                                 f"{[(o.name, o.shape) for o in outputs]}, expected crops [batch, "
                                 f"{', '.join(map(str, expected))}] -> descriptors [batch, D]")
        self.input_name = inputs[0].name

    def __call__(self, crops: Any) -> Any:
        """``crops [B,3,S,S]`` (torch tensor) -> ``descriptors [B,D]`` float32 (torch tensor, on the CPU)."""
        import torch

        x = np.ascontiguousarray(crops.detach().to("cpu", torch.float32).numpy())
        if x.ndim != 4 or list(x.shape[1:]) != [SCORER_INPUT_CHANNELS, self.crop_size, self.crop_size]:
            raise ValueError(f"{self.path.name}: crops must be [B,{SCORER_INPUT_CHANNELS},{self.crop_size},"
                             f"{self.crop_size}], got {x.shape}")
        return torch.from_numpy(self.session.run(None, {self.input_name: x})[0])

    def describe(self) -> str:
        return str(self.path)


# precision -> suffix of the manifest entry names of the pose networks
ONNX_FILE_SUFFIXES: dict[str, str] = {"fp32": "", "int8": ".int8"}


@dataclass
class OnnxModels:
    """The networks of an export folder in onnxruntime; detector/refiner None when not exported
    (or not asked for)."""

    coarse: PoseModel | None  # None: only start="templates" works
    refiner: PoseModel | None
    detector: OnnxDetector | None
    manifest: Manifest
    scorer: OnnxScorer | None = None  # None: start="appearance" describes detections with the frozen trunk


def load_onnx_models(root: str | Path, threads: int | None = None, precision: str = "fp32",
                     detector: bool = True, spinning: bool = False) -> OnnxModels:
    """The networks of the export folder ``root`` (``cosy-lite export --out root``), as the
    :class:`~cosy_lite.weights.loaders.PoseModel` the predictor takes (``net``: an
    :class:`OnnxPoseNet`) and an :class:`OnnxDetector`.

    Args:
        threads: intra-op threads of each session (None: onnxruntime's default).
        precision: "fp32", or "int8" for the quantised pose networks (``--quantize int8`` exports).
        detector: load ``detector.onnx`` when the folder has one (``scorer.onnx`` is loaded whenever
            the folder has one).
    Raises OnnxModelError naming the file and field: no manifest, a listed file missing, truncated
    or replaced, not loadable, or its metadata not matching the manifest (kind, obj_ids, crop size,
    6 input channels); no pose model at all.
    """
    from cosy_lite.weights.loaders import PoseModel  # torch behind it: not needed by the sessions

    if precision not in ONNX_FILE_SUFFIXES:
        raise ValueError(f"precision must be one of {sorted(ONNX_FILE_SUFFIXES)} for ONNX models, got {precision!r}")
    manifest = Manifest.read(root)
    pose: dict[str, PoseModel | None] = {}
    for role in POSE_KINDS:
        name = role + ONNX_FILE_SUFFIXES[precision]
        if manifest.entry(name) is None:
            if manifest.entry(role) is not None:  # fp32 exported, the asked precision not
                raise OnnxModelError(manifest.path, f"models.{name}", f"not exported (found models.{role} only): "
                                     f"export with --quantize {precision}, or use precision fp32")
            pose[role] = None
            continue
        entry = manifest.models[name]
        if entry.kind != role:
            raise OnnxModelError(manifest.path, f"models.{name}.kind", f"{entry.kind!r}, expected {role!r}")
        net = OnnxPoseNet(manifest.file(name), threads, role, entry, name, spinning)
        pose[role] = PoseModel(net, role, net.crop_resolution, net.obj_ids, net.path,
                               str(net.config.get("render_shading", "flat")),
                               "flow" if net.config.get("arch") == "flow" else "delta")
    if pose["coarse"] is None and pose["refiner"] is None:
        raise OnnxModelError(manifest.path, "models", "the export has no pose model (coarse or refiner; "
                             f"it has {sorted(manifest.models)})")
    det = None
    if detector and manifest.entry("detector") is not None:
        det = OnnxDetector(manifest.file("detector"), threads, manifest.models["detector"], "detector", spinning)
    scorer = None
    if manifest.entry(SCORER_KIND) is not None:
        scorer = OnnxScorer(manifest.file(SCORER_KIND), threads, manifest.models[SCORER_KIND], SCORER_KIND, spinning)
    return OnnxModels(pose["coarse"], pose["refiner"], det, manifest, scorer)
