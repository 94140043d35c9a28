"""Trained models from checkpoint files, ready for inference (eval mode, on a device).

Pose networks: :func:`load_pose_model` (``kind`` "coarse" or "refiner", written by
:class:`cosy_lite.train.pose_task.PoseTask`: ``meta = {"obj_ids", "net", "dataset", "model"}``;
older files keep ``net`` and ``obj_ids`` in their training config, and are read from there).
Detector: :func:`load_detector` (``kind`` "detector", written by
:class:`cosy_lite.train.detector_task.DetectorTask`: ``meta = {"detector_config", "label_map", ...}``).
Coarse scorer: :func:`load_scorer` (``kind`` "scorer", written by
:class:`cosy_lite.train.scorer_task.ScorerTask`: ``meta = {"obj_ids", "trunk", "templates", ...}``).
Every problem raises :class:`~cosy_lite.weights.checkpoint.CheckpointError` naming the file.
Exported networks (onnxruntime) are read by :func:`cosy_lite.inference.onnx_runtime.load_onnx_models`
into the same :class:`PoseModel`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from cosy_lite.weights.checkpoint import Checkpoint, CheckpointError, describe_value, is_id_list, load_checkpoint

if TYPE_CHECKING:
    import torch
    from torch import nn

    from cosy_lite.nets.detector import Detector

Size = tuple[int, int]
DETECTOR_KIND = "detector"
SCORER_KIND = "scorer"
# the fields of a file's ``meta`` the loaders read: name -> (check, what is expected)
META_FIELDS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "obj_ids": (is_id_list, "a list of positive integers"),
    "net": (lambda v: isinstance(v, dict), "a JSON object (the PoseNetConfig)"),
    "detector_config": (lambda v: isinstance(v, dict), "a JSON object (the DetectorConfig)"),
    "label_map": (lambda v: isinstance(v, dict) and is_id_list(v.get("obj_ids")),
                  "a JSON object {'obj_ids': a list of positive integers}"),
    "trunk": (lambda v: isinstance(v, str), "a trunk name (a string)"),
    "templates": (lambda v: isinstance(v, dict) and isinstance(v.get("shading"), str),
                  "a JSON object {'shading': how the templates were rendered, ...}"),
}


@dataclass
class PoseModel:
    """A pose network (coarse or refiner) and what it was trained for.

    net: the :class:`~cosy_lite.nets.pose_net.PoseNet` (eval mode), or any callable
    ``[B,6,h,w] -> [B,9]`` (or flow) tensor function such as an
    :class:`~cosy_lite.inference.onnx_runtime.OnnxPoseNet` (called inside the same loop,
    :func:`~cosy_lite.nets.render_and_compare.iterate_poses`); crop_resolution: (h, w) px of its input
    crops; obj_ids: objects it was trained on; path: the checkpoint or ``.onnx`` file (None if
    built in code).
    """

    net: nn.Module | Callable[[torch.Tensor], torch.Tensor]
    kind: str
    crop_resolution: Size
    obj_ids: list[int]
    path: Path | None = None
    render_shading: str = "flat"  # how its renderings were made in training (PoseNetConfig.render_shading)
    output: str = "delta"  # what the net returns: 9-number updates, or a "flow" field (render_and_compare)

    def describe(self) -> str:
        return str(self.path) if self.path is not None else f"{self.kind} model (built in code)"


def _meta_field(ckpt: Checkpoint, path: Path, name: str, from_config: bool = True) -> Any:
    """``ckpt.meta[name]`` checked as :data:`META_FIELDS` says; ``from_config``: for older pose
    files, ``ckpt.config[name]`` when the meta lacks it."""
    source, where = ckpt.meta, "meta"
    if name not in ckpt.meta and from_config and name in ckpt.config:  # older files: the training config holds it
        source, where = ckpt.config, "config"
    if name not in source:
        raise CheckpointError(path, f"field 'meta.{name}' missing (needed to rebuild the {ckpt.kind} model)")
    check, expected = META_FIELDS[name]
    if not check(source[name]):
        raise CheckpointError(path, f"field '{where}.{name}': expected {expected}, got {describe_value(source[name])}")
    return source[name]


def load_pose_model(path: str | Path, kind: str, device: str | torch.device = "cpu") -> PoseModel:
    """The ``kind`` ("coarse" | "refiner") network of the checkpoint at ``path``, in eval mode on ``device``."""
    from cosy_lite.nets.render_and_compare import network_output
    from cosy_lite.weights.pose_nets import PoseNetConfig, build_pose_net

    path = Path(path)
    ckpt = load_checkpoint(path, kind=kind)
    net_cfg = _meta_field(ckpt, path, "net")
    obj_ids = _meta_field(ckpt, path, "obj_ids")
    try:
        cfg = PoseNetConfig(**net_cfg)
        net = build_pose_net(cfg, kind, load_weights=False)
        net.load_state_dict(ckpt.model)
    except (TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(path, f"weights do not fit the network of meta.net {net_cfg} "
                                    f"({type(e).__name__}: {e})") from None
    h, w = (int(v) for v in cfg.crop_resolution)
    shading = str(net_cfg.get("render_shading", "flat"))  # files from before shading existed: flat renderings
    return PoseModel(net.to(device).eval(), kind, (h, w), sorted(int(i) for i in obj_ids), path, shading,
                     network_output(net))


def load_detector(path: str | Path, device: str | torch.device = "cpu") -> Detector:
    """The trained :class:`~cosy_lite.nets.detector.Detector` of the checkpoint at ``path`` (eval
    mode, on ``device``); its obj_id label map is ``.label_map``.

    Raises CheckpointError naming the file when it is not a detector checkpoint, lacks the
    detector config / label map, or its weights do not fit the architecture they describe.
    """
    from cosy_lite.nets.detector import Detector

    ckpt = load_checkpoint(path, kind=DETECTOR_KIND)
    missing = [k for k in ("detector_config", "label_map") if k not in ckpt.meta]
    if missing:
        raise CheckpointError(path, f"field 'meta' lacks {missing} (needed to rebuild the detector)")
    for name in ("detector_config", "label_map"):
        _meta_field(ckpt, Path(path), name, from_config=False)
    try:
        model = Detector.from_meta(ckpt.meta)
    except (TypeError, ValueError) as e:
        raise CheckpointError(path, f"field 'meta' does not describe a detector ({e})") from None
    try:
        model.load_state_dict(ckpt.model)
    except RuntimeError as e:
        raise CheckpointError(path, f"field 'model' does not fit the detector of 'meta' ({str(e).splitlines()[0]})") from None
    return model.to(device).eval()


@dataclass
class ScorerModel:
    """The coarse scorer (:class:`~cosy_lite.nets.appearance_scorer.AppearanceScorer`, eval mode),
    the objects it was trained on, and how the templates it was trained against were rendered
    (``shading``: its templates must be rendered the same way)."""

    net: nn.Module
    obj_ids: list[int]
    shading: str
    path: Path | None = None


def load_scorer(path: str | Path, device: str | torch.device = "cpu") -> ScorerModel:
    """The coarse scorer of the checkpoint or weights file at ``path``, in eval mode on ``device``."""
    from cosy_lite.nets.appearance_scorer import AppearanceScorer
    from cosy_lite.nets.pretrained import WEIGHTS

    path = Path(path)
    ckpt = load_checkpoint(path, kind=SCORER_KIND)
    trunk = _meta_field(ckpt, path, "trunk", from_config=False)
    obj_ids = _meta_field(ckpt, path, "obj_ids", from_config=False)
    templates = _meta_field(ckpt, path, "templates", from_config=False)
    if trunk not in WEIGHTS:
        raise CheckpointError(path, f"field 'meta.trunk': {trunk!r} is not one of {sorted(WEIGHTS)}")
    try:
        net = AppearanceScorer(trunk, load_pretrained=False)
        net.load_state_dict(ckpt.model)
    except (TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(path, f"weights do not fit the scorer of meta.trunk {trunk!r} "
                                    f"({type(e).__name__}: {e})") from None
    return ScorerModel(net.to(device).eval(), sorted(int(i) for i in obj_ids), str(templates["shading"]), path)
