"""Trained models from checkpoint files, ready for inference (eval mode, on a device).

Pose networks: :func:`load_pose_model` (``kind`` "coarse" or "refiner", written by
:class:`cosy_lite.train.pose_task.PoseTask`: ``meta = {"obj_ids", "net", "dataset", "model"}``).
Detector: :func:`load_detector` (``kind`` "detector", read by
:func:`cosy_lite.train.detector_task.load_detector`). Every problem raises
:class:`~cosy_lite.train.checkpoint.CheckpointError` naming the file.

Exported networks (``cosy-lite export``): :func:`load_onnx_models` reads an export folder
(``manifest.json`` + ``.onnx`` files) into onnxruntime sessions with the same interfaces
(:class:`PoseModel` whose ``net`` is an :class:`~cosy_lite.export.onnx_models.OnnxPoseNet`); its
problems raise :class:`~cosy_lite.export.manifest.OnnxModelError` naming the file and the field.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch
from torch import nn

from cosy_lite.train.checkpoint import Checkpoint, CheckpointError, load_checkpoint

Size = tuple[int, int]


@dataclass
class PoseModel:
    """A pose network (coarse or refiner) and what it was trained for.

    net: the :class:`~cosy_lite.models.pose_net.PoseNet` (eval mode), or any callable
    ``[B,6,h,w] -> [B,9]`` tensor function such as an
    :class:`~cosy_lite.export.onnx_models.OnnxPoseNet` (nets with a numpy ``run``, as that one, make
    the Predictor iterate in numpy: :mod:`~cosy_lite.inference.iterate_np`); crop_resolution: (h, w) px of its input
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


def _meta_field(ckpt: Checkpoint, path: Path, name: str) -> Any:
    if name in ckpt.meta:
        return ckpt.meta[name]
    if name in ckpt.config:  # older files: the training config holds it
        return ckpt.config[name]
    raise CheckpointError(path, f"field 'meta.{name}' missing (needed to rebuild the {ckpt.kind} model)")


def load_pose_model(path: str | Path, kind: str, device: str | torch.device = "cpu") -> PoseModel:
    """The ``kind`` ("coarse" | "refiner") network of the checkpoint at ``path``, in eval mode on ``device``."""
    from cosy_lite.models.render_and_compare import network_output
    from cosy_lite.train.pose_task import PoseNetConfig, build_pose_net

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
    if not obj_ids:
        raise CheckpointError(path, "field 'meta.obj_ids' is empty")
    shading = str(net_cfg.get("render_shading", "flat"))  # files from before shading existed: flat renderings
    return PoseModel(net.to(device).eval(), kind, (h, w), sorted(int(i) for i in obj_ids), path, shading,
                     network_output(net))


def load_detector(path: str | Path, device: str | torch.device = "cpu") -> nn.Module:
    """The :class:`~cosy_lite.models.detector.Detector` of the checkpoint at ``path`` (eval mode),
    as the detector training task loads it."""
    from cosy_lite.train.detector_task import load_detector as load

    model, _ = load(path, device)
    return model


# precision -> suffix of the manifest entry names of the pose networks
ONNX_PRECISIONS: dict[str, str] = {"fp32": "", "int8": ".int8"}


@dataclass
class OnnxModels:
    """The networks of an export folder in onnxruntime; detector/refiner None when not exported
    (or not asked for)."""

    coarse: PoseModel | None  # None: only start="templates" works
    refiner: PoseModel | None
    detector: Any  # OnnxDetector | None
    manifest: Any  # cosy_lite.export.manifest.Manifest


def load_onnx_models(root: str | Path, threads: int | None = None, precision: str = "fp32",
                     detector: bool = True, spinning: bool = False) -> OnnxModels:
    """The networks of the export folder ``root`` (``cosy-lite export --out root``).

    Args:
        threads: intra-op threads of each session (None: onnxruntime's default).
        precision: "fp32", or "int8" for the quantised pose networks (``--quantize int8`` exports).
        detector: load ``detector.onnx`` when the folder has one.
    Raises OnnxModelError naming the file and field: no manifest, a listed file missing, truncated
    or replaced, not loadable, or its metadata not matching the manifest (kind, obj_ids, crop size,
    6 input channels); no pose model at all.
    """
    from cosy_lite.export.manifest import Manifest, OnnxModelError
    from cosy_lite.export.onnx_models import OnnxDetector, OnnxPoseNet

    if precision not in ONNX_PRECISIONS:
        raise ValueError(f"precision must be one of {sorted(ONNX_PRECISIONS)} for ONNX models, got {precision!r}")
    manifest = Manifest.read(root)
    pose: dict[str, PoseModel | None] = {}
    for role in ("coarse", "refiner"):
        name = role + ONNX_PRECISIONS[precision]
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
    return OnnxModels(pose["coarse"], pose["refiner"], det, manifest)  # type: ignore[arg-type]
