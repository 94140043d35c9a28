"""The one training loop of cosy_lite (detector, coarse and refiner all run through it).

A model-specific :class:`TrainTask` says how to build the model and the data and how to compute
the losses of a batch; this loop owns everything else: device and DDP, Adam with warm-up and step
decay, gradient clipping, mixed precision on GPU, the tqdm bar (losses, items/s), JSON-lines logs,
the loss-curve PNG, validation every N steps, atomic checkpoints and exact resume.

Run folder (``out_dir``): ``checkpoint.pt`` (latest; also the final model), ``log.jsonl`` (one
record per log interval / validation), ``loss.png``, ``config.yaml``.
Determinism: the data order is a function of (seed, step) (:mod:`cosy_lite.train.sampler`) and the
global RNG is re-seeded from (seed, step, rank) before each step, so a resumed run repeats exactly
what the uninterrupted run would have done from the checkpoint on (on the same device type).
"""

from __future__ import annotations

import json
import math
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

import torch
from torch.utils.data import DataLoader, Dataset

from cosy_lite.train.checkpoint import Checkpoint, CheckpointError, load_checkpoint, save_checkpoint
from cosy_lite.train.distributed import DistInfo, all_reduce_mean, barrier, init_distributed, shutdown_distributed
from cosy_lite.train.sampler import StepBatchSampler
from cosy_lite.train.schedule import OptimConfig, build_optimizer

CHECKPOINT_NAME = "checkpoint.pt"
LOG_NAME = "log.jsonl"
# Config keys allowed to differ when resuming (how long to train, not what to train).
RESUMABLE_CHANGES = ("loop.steps", "loop.max_minutes", "loop.val_every", "loop.log_every",
                     "loop.checkpoint_every", "loop.num_workers", "loop.device")


@dataclass
class LoopConfig:
    """How long and how to train (per-process batch size; ``max_minutes`` = 0: no time limit)."""

    steps: int = 2000
    batch_size: int = 16
    num_workers: int = 2
    log_every: int = 20
    val_every: int = 500
    checkpoint_every: int = 100
    max_minutes: float = 0.0
    seed: int = 0
    device: str = "auto"
    amp: bool = True


class TrainTask(Protocol):
    """What a model brings to the loop."""

    kind: str

    def build_model(self) -> torch.nn.Module: ...

    def train_dataset(self) -> Dataset: ...

    def collate(self, items: list) -> Any: ...

    def compute_losses(self, model: torch.nn.Module, batch: Any, step: int, device: torch.device) -> dict[str, torch.Tensor]:
        """Named loss terms of one batch; ``"total"`` is the one optimised."""
        ...

    def validate(self, model: torch.nn.Module, device: torch.device) -> dict[str, float]: ...

    def checkpoint_meta(self) -> dict[str, Any]: ...


@dataclass
class TrainSummary:
    steps_done: int
    seconds: float
    items_per_s: float
    last_losses: dict[str, float] = field(default_factory=dict)
    last_val: dict[str, float] = field(default_factory=dict)
    checkpoint: Path | None = None


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        out.update(_flatten(v, key + ".") if isinstance(v, dict) else {key: v})
    return out


def _check_same_config(path: Path, old: dict[str, Any], new: dict[str, Any]) -> None:
    a, b = _flatten(old), _flatten(new)
    diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k) and k not in RESUMABLE_CHANGES)
    if diff:
        details = ", ".join(f"{k}: {a.get(k)!r} -> {b.get(k)!r}" for k in diff[:8])
        raise CheckpointError(path, f"cannot resume with a different config ({details})")


def _truncate_log(log_path: Path, step: int) -> None:
    """Drop log records written after the checkpoint (they will be produced again)."""
    if not log_path.is_file():
        return
    keep = [line for line in log_path.read_text().splitlines() if line.strip() and json.loads(line)["step"] <= step]
    log_path.write_text("".join(line + "\n" for line in keep))


def plot_losses(log_path: Path, png_path: Path) -> None:
    """Loss curves (every ``loss/*`` term, log scale) and validation metrics from ``log.jsonl``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    records = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()]
    train = [r for r in records if r.get("type") == "train"]
    val = [r for r in records if r.get("type") == "val"]
    fig, axes = plt.subplots(1, 2 if val else 1, figsize=(12 if val else 7, 4), squeeze=False)
    ax = axes[0, 0]
    for key in sorted({k for r in train for k in r if k.startswith("loss/")}):
        ax.plot([r["step"] for r in train if key in r], [r[key] for r in train if key in r], label=key[5:])
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_title("training losses")
    if ax.get_lines():
        ax.legend()
    if val:
        ax = axes[0, 1]
        for key in sorted({k for r in val for k in r if k.startswith("val/")}):
            ax.plot([r["step"] for r in val], [r.get(key, math.nan) for r in val], marker="o", label=key[4:])
        ax.set_xlabel("step")
        ax.set_title("validation")
        ax.legend()
    fig.tight_layout()
    fig.savefig(png_path, dpi=90)
    plt.close(fig)


def train(task: TrainTask, loop: LoopConfig, optim: OptimConfig, out_dir: str | Path, config: dict[str, Any],
          resume: bool = False, progress: bool = True) -> TrainSummary:
    """Train ``task``'s model; ``config`` is the full config (stored in checkpoints, checked on resume).

    Without ``resume`` an existing checkpoint in ``out_dir`` is an error (nothing is overwritten by
    accident); with ``resume`` training continues from it (or starts if there is none).
    """
    from tqdm import tqdm

    out_dir = Path(out_dir)
    ckpt_path, log_path = out_dir / CHECKPOINT_NAME, out_dir / LOG_NAME
    dist_info = init_distributed(loop.device)
    device = dist_info.device
    if dist_info.is_main:
        out_dir.mkdir(parents=True, exist_ok=True)

    torch.set_flush_denormal(True)  # CPU: denormal floats (tiny Adam moments, activations) are very slow
    torch.manual_seed(loop.seed)  # the initial weights are a function of the seed (same on every rank)
    model = task.build_model().to(device)
    optimizer, scheduler = build_optimizer(model.parameters(), optim)
    start_step = 0
    if ckpt_path.is_file():
        if not resume:
            raise CheckpointError(ckpt_path, "a checkpoint already exists; pass --resume to continue it or choose another output folder")
        ckpt = load_checkpoint(ckpt_path, kind=task.kind)
        _check_same_config(ckpt_path, ckpt.config, config)
        model.load_state_dict(ckpt.model)
        optimizer.load_state_dict(ckpt.train_state["optimizer"])
        scheduler.load_state_dict(ckpt.train_state["scheduler"])
        start_step = ckpt.step
        if dist_info.is_main:
            _truncate_log(log_path, start_step)
    barrier(dist_info)

    ddp_model: torch.nn.Module | None = None
    if dist_info.distributed:
        ddp_model = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None)
    train_model = ddp_model if ddp_model is not None else model

    dataset = task.train_dataset()
    sampler = StepBatchSampler(len(dataset), loop.batch_size, loop.seed, start_step, loop.steps,
                               dist_info.rank, dist_info.world_size)
    loader = DataLoader(dataset, batch_sampler=sampler, num_workers=loop.num_workers, collate_fn=task.collate,
                        persistent_workers=False, pin_memory=device.type == "cuda")
    use_amp = loop.amp and device.type == "cuda"
    autocast = (lambda: torch.autocast("cuda", dtype=torch.bfloat16)) if use_amp else nullcontext

    def checkpoint(step: int) -> None:
        if not dist_info.is_main:
            return
        save_checkpoint(ckpt_path, Checkpoint(
            kind=task.kind, model=model.state_dict(), config=config, step=step,
            train_state={"optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict()},
            meta=task.checkpoint_meta()))
        if log_path.is_file():
            plot_losses(log_path, out_dir / "loss.png")

    def log(record: dict[str, Any]) -> None:
        if dist_info.is_main:
            with open(log_path, "a") as f:
                f.write(json.dumps(record) + "\n")

    bar = tqdm(total=loop.steps, initial=start_step, desc=f"train {task.kind}", unit="step",
               disable=not (progress and dist_info.is_main), dynamic_ncols=True)
    t_start = time.perf_counter()
    t_interval, items_interval = time.perf_counter(), 0
    sums: dict[str, float] = {}
    n_sum = 0
    step = start_step
    last_losses: dict[str, float] = {}
    last_val: dict[str, float] = {}
    total_items = 0
    train_model.train()
    for batch in loader:
        torch.manual_seed(loop.seed * 1_000_003 + step * dist_info.world_size + dist_info.rank)
        with autocast():
            losses = task.compute_losses(train_model, batch, step, device)
        total = losses["total"]
        if not torch.isfinite(total):
            raise FloatingPointError(f"step {step}: non-finite loss {({k: float(v) for k, v in losses.items()})}")
        optimizer.zero_grad(set_to_none=True)
        total.backward()
        if optim.clip_grad_norm > 0:
            torch.nn.utils.clip_grad_norm_(model.parameters(), optim.clip_grad_norm)
        optimizer.step()
        scheduler.step()
        step += 1
        items_interval += loop.batch_size * dist_info.world_size
        total_items += loop.batch_size * dist_info.world_size
        values = all_reduce_mean(torch.stack([v.detach().float() for v in losses.values()]), dist_info)
        for k, v in zip(losses, values.tolist()):
            sums[k] = sums.get(k, 0.0) + v
        n_sum += 1
        bar.update(1)

        if step % loop.log_every == 0 or step == loop.steps:
            dt = time.perf_counter() - t_interval
            last_losses = {k: v / n_sum for k, v in sums.items()}
            rate = items_interval / max(dt, 1e-9)
            log({"type": "train", "step": step, "lr": scheduler.get_last_lr()[0], "items_per_s": rate,
                 "elapsed_s": time.perf_counter() - t_start, **{f"loss/{k}": v for k, v in last_losses.items()}})
            bar.set_postfix(loss=f"{last_losses['total']:.4g}", items_s=f"{rate:.1f}")
            sums, n_sum, items_interval, t_interval = {}, 0, 0, time.perf_counter()
        out_of_time = loop.max_minutes > 0 and (time.perf_counter() - t_start) > 60 * loop.max_minutes
        stop = all_reduce_mean(torch.tensor([float(out_of_time)]), dist_info).item() > 0
        if loop.val_every > 0 and (step % loop.val_every == 0 or step == loop.steps or stop):
            if dist_info.is_main:
                model.eval()
                with torch.no_grad():
                    last_val = task.validate(model, device)
                model.train()
                log({"type": "val", "step": step, **{f"val/{k}": v for k, v in last_val.items()}})
                bar.write(f"step {step}: " + ", ".join(f"{k} {v:.4g}" for k, v in last_val.items()))
        if step % loop.checkpoint_every == 0 or step == loop.steps or stop:
            checkpoint(step)
        if stop:
            bar.write(f"stopping at step {step}: time budget of {loop.max_minutes} min reached (checkpoint saved)")
            break
    bar.close()
    seconds = time.perf_counter() - t_start
    del train_model, ddp_model, loader  # before destroy_process_group (gloo aborts otherwise)
    barrier(dist_info)
    shutdown_distributed(dist_info)
    return TrainSummary(steps_done=step, seconds=seconds, items_per_s=total_items / max(seconds, 1e-9),
                        last_losses=last_losses, last_val=last_val,
                        checkpoint=ckpt_path if ckpt_path.is_file() else None)
