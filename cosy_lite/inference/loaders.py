"""Trained models from checkpoint files, ready for inference (eval mode, on a device).

Pose networks: :func:`load_pose_model` (``kind`` "coarse" or "refiner", written by
:class:`cosy_lite.train.pose_task.PoseTask`: ``meta = {"obj_ids", "net", "dataset", "model"}``).
Detector: :func:`load_detector` (``kind`` "detector", read by
:func:`cosy_lite.train.detector_task.load_detector`). Every problem raises
:class:`~cosy_lite.train.checkpoint.CheckpointError` naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from cosy_lite.train.checkpoint import Checkpoint, CheckpointError, load_checkpoint

Size = tuple[int, int]


@dataclass
class PoseModel:
    """A pose network (coarse or refiner) and what it was trained for.

    net: the :class:`~cosy_lite.models.pose_net.PoseNet` (eval mode); crop_resolution: (h, w) px of
    its input crops; obj_ids: objects it was trained on; path: the checkpoint (None if built in code).
    """

    net: nn.Module
    kind: str
    crop_resolution: Size
    obj_ids: list[int]
    path: Path | None = None

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
    from cosy_lite.train.pose_task import PoseNetConfig, build_pose_net

    path = Path(path)
    ckpt = load_checkpoint(path, kind=kind)
    net_cfg = _meta_field(ckpt, path, "net")
    obj_ids = _meta_field(ckpt, path, "obj_ids")
    try:
        cfg = PoseNetConfig(**net_cfg)
        net = build_pose_net(cfg)
        net.load_state_dict(ckpt.model)
    except (TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(path, f"weights do not fit the network of meta.net {net_cfg} "
                                    f"({type(e).__name__}: {e})") from None
    h, w = (int(v) for v in cfg.crop_resolution)
    if not obj_ids:
        raise CheckpointError(path, "field 'meta.obj_ids' is empty")
    return PoseModel(net.to(device).eval(), kind, (h, w), sorted(int(i) for i in obj_ids), path)


def load_detector(path: str | Path, device: str | torch.device = "cpu") -> nn.Module:
    """The :class:`~cosy_lite.models.detector.Detector` of the checkpoint at ``path`` (eval mode),
    as the detector training task loads it."""
    from cosy_lite.train.detector_task import load_detector as load

    model, _ = load(path, device)
    return model
