"""What a training run carries from one checkpoint to the next, and how it starts: afresh, from
published weights (``--init``) or resumed from its ``checkpoint.pt``."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from cosy_lite.errors import ConfigError
from cosy_lite.weights.checkpoint import Checkpoint, CheckpointError, load_checkpoint, save_checkpoint

# Config keys allowed to differ when resuming (how long to train, not what to train).
RESUMABLE_CHANGES = ("loop.steps", "loop.max_minutes", "loop.val_every", "loop.log_every",
                     "loop.checkpoint_every", "loop.num_workers", "loop.device", "loop.val_at_start")
# Settings added after checkpoints were written, with the value that behaves as before they existed: a
# checkpoint whose config lacks one resumes when the new config has that value.
ADDED_SETTINGS = {"optim.schedule": "step", "optim.cosine_floor": 0.05}


@dataclass
class RunState:
    """The run so far: its step, training time and items before this process, the log interval in
    progress, the fraction of its budget done (None: an older checkpoint, whose saved learning rate
    then stands for the first step), and where its weights started."""

    step: int = 0
    elapsed_before: float = 0.0
    items_before: int = 0
    log_interval: dict[str, Any] = field(default_factory=dict)
    done: float | None = 0.0
    init_record: dict[str, Any] | None = None
    weights_source: str | None = None  # when the task did not read its weights itself (resume, --init)
    t_start: float = field(default_factory=time.perf_counter)  # this process's start
    items: int = 0  # training items of this process's part

    def elapsed(self) -> float:
        """Seconds trained, parts before this process included."""
        return self.elapsed_before + time.perf_counter() - self.t_start


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        out.update(_flatten(v, key + ".") if isinstance(v, dict) else {key: v})
    return out


def check_same_config(path: Path, old: dict[str, Any], new: dict[str, Any]) -> None:
    a, b = _flatten(old), _flatten(new)
    a.update({k: v for k, v in ADDED_SETTINGS.items() if k not in a})
    diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k) and k not in RESUMABLE_CHANGES)
    if diff:
        details = ", ".join(f"{k}: {a.get(k)!r} -> {b.get(k)!r}" for k in diff[:8])
        raise CheckpointError(path, f"cannot resume with a different config ({details})")


def resume_run(ckpt_path: Path, kind: str, model: torch.nn.Module, optimizer: torch.optim.Optimizer,
               config: dict[str, Any], steps: int, items_per_step: int, init: str | Path | None) -> RunState:
    """The model and optimiser as the checkpoint left them, and the run's state. CheckpointError /
    ConfigError naming the file for a checkpoint of another config, kind or model, or past ``steps``."""
    ckpt = load_checkpoint(ckpt_path, kind=kind)
    check_same_config(ckpt_path, ckpt.config, config)
    init_record = ckpt.meta.get("init")
    if init is not None and (init_record or {}).get("path") != str(init):
        print(f"{ckpt_path}: resuming; --init {init} is not used (the run started from "
              f"{(init_record or {}).get('path', 'its fresh initialisation')})")
    if ckpt.step > steps:
        raise ConfigError(ckpt_path, "loop.steps", f"{steps}: the checkpoint is at step {ckpt.step} already; "
                          f"expected loop.steps >= {ckpt.step} to resume")
    if "optimizer" not in ckpt.train_state:
        raise CheckpointError(ckpt_path, "field 'train_state' lacks ['optimizer']: not a checkpoint of a run to resume")
    try:
        model.load_state_dict(ckpt.model)
        optimizer.load_state_dict(ckpt.train_state["optimizer"])
    except (RuntimeError, ValueError, KeyError, TypeError) as e:
        raise CheckpointError(ckpt_path, f"does not fit this model/optimiser ({type(e).__name__}: "
                              f"{str(e).splitlines()[0]})") from None
    state = ckpt.train_state
    return RunState(step=ckpt.step, elapsed_before=float(state.get("elapsed_s", 0.0)),
                    items_before=int(state.get("items_trained", ckpt.step * items_per_step)),
                    log_interval=state.get("log_interval", {}), done=state.get("schedule_done"),
                    init_record=init_record, weights_source=ckpt.meta.get("initialised_from"))


def save_run(ckpt_path: Path, kind: str, model: torch.nn.Module, optimizer: torch.optim.Optimizer,
             config: dict[str, Any], run: RunState, task_meta: dict[str, Any], log_interval: dict[str, Any],
             world_size: int) -> None:
    """Write the run's checkpoint (atomically): weights, optimiser, config, the run's state and meta."""
    items_trained = run.items_before + run.items
    if "initialised_from" in task_meta and task_meta["initialised_from"] is None:
        task_meta = {**task_meta, "initialised_from": run.weights_source}
    meta = {**task_meta, "items_seen": items_trained + ((run.init_record or {}).get("items_seen") or 0),
            "world_size": world_size, **({"init": run.init_record} if run.init_record else {})}
    save_checkpoint(ckpt_path, Checkpoint(
        kind=kind, model=model.state_dict(), config=config, step=run.step,
        train_state={"optimizer": optimizer.state_dict(), "log_interval": log_interval, "elapsed_s": run.elapsed(),
                     "items_trained": items_trained, "schedule_done": run.done},
        meta=meta))
