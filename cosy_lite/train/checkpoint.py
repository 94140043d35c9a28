"""Self-describing checkpoints: weights + full config + version + training state, written atomically.

One file per run folder (``checkpoint.pt``) is rewritten every ``checkpoint_every`` steps: the new
file is written next to it and moved over it with :func:`os.replace`, so a run killed at any moment
(even ``kill -9``) leaves either the previous or the new checkpoint, never a truncated one.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

import cosy_lite

CHECKPOINT_FORMAT = 1
REQUIRED_KEYS = ("format", "kind", "model", "config", "step")


class CheckpointError(ValueError):
    """A checkpoint file that cannot be used; the message names the file and what is wrong."""

    def __init__(self, path: str | Path, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path = Path(path)


@dataclass
class Checkpoint:
    """Contents of a checkpoint file.

    kind: which model ("detector", "coarse", "refiner", ...); model: state_dict of the bare (not
    DDP-wrapped) module; config: the full training config as a plain dict; step: optimisation steps
    done; train_state: optimiser/scheduler/scaler states for resuming; meta: anything the model
    needs to be rebuilt and used (e.g. label map, object ids).
    """

    kind: str
    model: dict[str, torch.Tensor]
    config: dict[str, Any]
    step: int
    train_state: dict[str, Any] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)
    version: str = cosy_lite.__version__


def save_checkpoint(path: str | Path, ckpt: Checkpoint) -> None:
    """Write ``ckpt`` to ``path`` atomically (temporary file in the same folder + fsync + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    payload = {
        "format": CHECKPOINT_FORMAT,
        "kind": ckpt.kind,
        "model": ckpt.model,
        "config": ckpt.config,
        "step": ckpt.step,
        "train_state": ckpt.train_state,
        "meta": ckpt.meta,
        "version": ckpt.version,
    }
    with open(tmp, "wb") as f:
        torch.save(payload, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def load_checkpoint(path: str | Path, kind: str | tuple[str, ...] | None = None) -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint` (on CPU).

    Raises CheckpointError naming the file when it is missing, unreadable/truncated, lacks a field,
    has another format version, or holds another kind of model than ``kind``.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(path, "checkpoint file not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # truncated zip, not a torch file, ...
        raise CheckpointError(path, f"not a readable checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(payload, dict):
        raise CheckpointError(path, f"expected a dict, found {type(payload).__name__}")
    missing = [k for k in REQUIRED_KEYS if k not in payload]
    if missing:
        raise CheckpointError(path, f"missing field(s) {missing}")
    if payload["format"] != CHECKPOINT_FORMAT:
        raise CheckpointError(path, f"field 'format' is {payload['format']}, this version reads {CHECKPOINT_FORMAT}")
    kinds = (kind,) if isinstance(kind, str) else kind
    if kinds is not None and payload["kind"] not in kinds:
        raise CheckpointError(path, f"field 'kind' is {payload['kind']!r}, expected one of {list(kinds)}")
    return Checkpoint(
        kind=payload["kind"],
        model=payload["model"],
        config=payload["config"],
        step=int(payload["step"]),
        train_state=payload.get("train_state", {}),
        meta=payload.get("meta", {}),
        version=payload.get("version", "?"),
    )
