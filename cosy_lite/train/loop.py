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
Interrupted runs (also ``kill -9``): on start the log is cut back to the checkpoint's step (all of
it when there is no checkpoint yet; a half-written last line is dropped), temporary checkpoint
files of killed writes are deleted, and the checkpoint carries the partial loss sums of the current
log interval and the elapsed time, so the resumed log reads as one uninterrupted run.
"""

from __future__ import annotations

import json
import math
import os
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

import torch
from torch.utils.data import DataLoader, Dataset

from cosy_lite.errors import ConfigError, CosyLiteError
from cosy_lite.model_files.checkpoint import (Checkpoint, CheckpointError, load_checkpoint, remove_stale_temporaries,
                                        save_checkpoint)
from cosy_lite.train.distributed import DistInfo, all_reduce_mean, barrier, init_distributed, shutdown_distributed
from cosy_lite.train.sampler import StepBatchSampler
from cosy_lite.train.schedule import SCHEDULES, OptimConfig, budget_factor, build_optimizer

CHECKPOINT_NAME = "checkpoint.pt"
LOG_NAME = "log.jsonl"
# Config keys allowed to differ when resuming (how long to train, not what to train).
RESUMABLE_CHANGES = ("loop.steps", "loop.max_minutes", "loop.val_every", "loop.log_every",
                     "loop.checkpoint_every", "loop.num_workers", "loop.device", "loop.val_at_start")
# Settings added after checkpoints were written, with the value that behaves as before they existed: a
# checkpoint whose config lacks one resumes when the new config has that value.
ADDED_SETTINGS = {"optim.schedule": "step", "optim.cosine_floor": 0.05}


@dataclass
class LoopConfig:
    """How long and how to train (per-process batch size; ``max_minutes``: training minutes of the whole
    run, resumed parts included; 0 = no time limit)."""

    steps: int = 2000
    batch_size: int = 16
    num_workers: int = 2
    log_every: int = 20
    val_every: int = 500
    val_at_start: bool = False  # also validate the untrained model (step 0; not counted in max_minutes)
    checkpoint_every: int = 100
    max_minutes: float = 0.0
    seed: int = 0
    device: str = "auto"
    amp: bool = True


class TrainTask(Protocol):
    """What a model brings to the loop."""

    kind: str

    def build_model(self, load_pretrained: bool = True) -> torch.nn.Module:
        """The network; ``load_pretrained=False``: the same network without reading pretrained weights
        (a checkpoint or ``--init`` overwrites them)."""
        ...

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
    a.update({k: v for k, v in ADDED_SETTINGS.items() if k not in a})
    diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k) and k not in RESUMABLE_CHANGES)
    if diff:
        details = ", ".join(f"{k}: {a.get(k)!r} -> {b.get(k)!r}" for k in diff[:8])
        raise CheckpointError(path, f"cannot resume with a different config ({details})")


class DivergedError(CosyLiteError, FloatingPointError):
    """Training produced a non-finite loss (learning rate too high, broken data ...)."""


def check_train_config(loop: LoopConfig, optim: OptimConfig, where: str | Path = "config") -> None:
    """ConfigError naming ``where`` and the key for a loop/optimiser setting that cannot work.

    Nothing is clamped or defaulted: ``loop.steps = 0`` would train nothing and report success.
    """
    def need(ok: bool, key: str, expected: str, value: Any) -> None:
        if not ok:
            raise ConfigError(where, key, f"{value!r}: expected {expected}")

    need(loop.steps >= 1, "loop.steps", "at least 1 optimisation step", loop.steps)
    need(loop.batch_size >= 1, "loop.batch_size", "at least 1 item per process", loop.batch_size)
    need(loop.num_workers >= 0, "loop.num_workers", ">= 0 (0: load data in the main process)", loop.num_workers)
    need(loop.log_every >= 1, "loop.log_every", "at least 1 step", loop.log_every)
    need(loop.val_every >= 0, "loop.val_every", ">= 0 (0: no validation)", loop.val_every)
    need(loop.checkpoint_every >= 1, "loop.checkpoint_every", "at least 1 step", loop.checkpoint_every)
    need(math.isfinite(loop.max_minutes) and loop.max_minutes >= 0, "loop.max_minutes",
         "a finite number >= 0 (0: no time limit)", loop.max_minutes)
    if loop.device != "auto":
        try:
            device = torch.device(loop.device)
        except (RuntimeError, ValueError):
            raise ConfigError(where, "loop.device", f"{loop.device!r}: expected auto, cpu, cuda or cuda:N") from None
        need(device.type != "cuda" or torch.cuda.is_available(), "loop.device",
             "a device this machine has (no GPU found)", loop.device)
    need(math.isfinite(optim.lr) and optim.lr > 0, "optim.lr", "a finite learning rate > 0", optim.lr)
    need(math.isfinite(optim.weight_decay) and optim.weight_decay >= 0, "optim.weight_decay", "a finite number >= 0",
         optim.weight_decay)
    need(optim.warmup_steps >= 0, "optim.warmup_steps", ">= 0", optim.warmup_steps)
    need(all(s >= 0 for s in optim.decay_steps), "optim.decay_steps", "steps >= 0", optim.decay_steps)
    need(math.isfinite(optim.decay_factor) and optim.decay_factor > 0, "optim.decay_factor", "a finite factor > 0",
         optim.decay_factor)
    need(math.isfinite(optim.clip_grad_norm) and optim.clip_grad_norm >= 0, "optim.clip_grad_norm",
         "a finite norm >= 0 (0: no clipping)", optim.clip_grad_norm)
    need(optim.schedule in SCHEDULES, "optim.schedule", f"one of {SCHEDULES}", optim.schedule)
    need(math.isfinite(optim.cosine_floor) and 0 <= optim.cosine_floor <= 1, "optim.cosine_floor",
         "a factor in [0, 1]", optim.cosine_floor)


def read_log(log_path: Path) -> list[dict[str, Any]]:
    """The records of ``log.jsonl``; a half-written last line (a killed run) is left out.

    CheckpointError naming the file and line for a broken line elsewhere or a record without an
    integer ``step``.
    """
    if not log_path.is_file():
        return []
    text = log_path.read_text(encoding="utf-8", errors="replace")
    lines = text.split("\n")
    records = []
    for n, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError as e:
            if n == len(lines):  # no newline after it: the write was cut short
                continue
            raise CheckpointError(log_path, f"line {n}: not a JSON record ({e.msg}); "
                                  "expected one JSON object per line") from None
        step = record.get("step") if isinstance(record, dict) else None
        if isinstance(step, bool) or not isinstance(step, int):
            raise CheckpointError(log_path, f"line {n}: record without an integer 'step': {line[:80]!r}")
        records.append(record)
    return records


def _truncate_log(log_path: Path, step: int) -> None:
    """Keep the log records up to ``step`` (the checkpoint's; 0: none): later ones will be produced again."""
    if not log_path.is_file():
        return
    keep = [r for r in read_log(log_path) if r["step"] <= step]
    tmp = log_path.with_name(f".{log_path.name}.tmp")
    tmp.write_text("".join(json.dumps(r) + "\n" for r in keep))
    os.replace(tmp, log_path)


def plot_losses(log_path: Path, png_path: Path) -> None:
    """Loss curves (every ``loss/*`` term, log scale) and validation metrics from ``log.jsonl``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    records = read_log(log_path)
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
          resume: bool = False, progress: bool = True, init: str | Path | None = None) -> TrainSummary:
    """Train ``task``'s model; ``config`` is the full config (stored in checkpoints, checked on resume).

    Without ``resume`` an existing checkpoint in ``out_dir`` is an error (nothing is overwritten by
    accident); with ``resume`` training continues from it (or starts if there is none). ``init``: a
    weights file whose network the run starts from instead of its fresh initialisation
    (:func:`~cosy_lite.train.init_weights.load_initial_weights`; a resumed run keeps its own record of it).
    """
    from tqdm import tqdm

    check_train_config(loop, optim)
    out_dir = Path(out_dir)
    ckpt_path, log_path = out_dir / CHECKPOINT_NAME, out_dir / LOG_NAME
    dist_info = init_distributed(loop.device)
    device = dist_info.device
    if dist_info.is_main:
        out_dir.mkdir(parents=True, exist_ok=True)
        if stale := remove_stale_temporaries(ckpt_path):
            print(f"removed {len(stale)} temporary checkpoint file(s) of an interrupted run: {[p.name for p in stale]}")

    torch.set_flush_denormal(True)  # CPU: denormal floats (tiny Adam moments, activations) are very slow
    torch.manual_seed(loop.seed)  # the initial weights are a function of the seed (same on every rank)
    # resumed or --init: every weight is overwritten below, so no pretrained (ImageNet) file is read
    model = task.build_model(load_pretrained=init is None and not ckpt_path.is_file()).to(device)
    optimizer, scheduler = build_optimizer(model.parameters(), optim)
    start_step = 0
    interval: dict[str, Any] = {"sums": {}, "n": 0}  # loss sums of the log interval in progress
    elapsed_before = 0.0  # seconds trained before this process (resumed runs)
    items_before = 0  # training items (crops, images) of the run before this process
    init_record: dict[str, Any] | None = None
    # what the weights started from, when the task did not read it itself (resume, --init)
    weights_source: str | None = None
    if ckpt_path.is_file():
        if not resume:
            raise CheckpointError(ckpt_path, "a checkpoint already exists; pass --resume to continue it or choose another output folder")
        ckpt = load_checkpoint(ckpt_path, kind=task.kind)
        _check_same_config(ckpt_path, ckpt.config, config)
        init_record = ckpt.meta.get("init")
        weights_source = ckpt.meta.get("initialised_from")
        if init is not None and (init_record or {}).get("path") != str(init):
            print(f"{ckpt_path}: resuming; --init {init} is not used (the run started from "
                  f"{(init_record or {}).get('path', 'its fresh initialisation')})")
        if ckpt.step > loop.steps:
            raise ConfigError(ckpt_path, "loop.steps", f"{loop.steps}: the checkpoint is at step {ckpt.step} already; "
                              f"expected loop.steps >= {ckpt.step} to resume")
        missing = [k for k in ("optimizer", "scheduler") if k not in ckpt.train_state]
        if missing:
            raise CheckpointError(ckpt_path, f"field 'train_state' lacks {missing}: not a checkpoint of a run to resume")
        try:
            model.load_state_dict(ckpt.model)
            optimizer.load_state_dict(ckpt.train_state["optimizer"])
            scheduler.load_state_dict(ckpt.train_state["scheduler"])
        except (RuntimeError, ValueError, KeyError, TypeError) as e:
            raise CheckpointError(ckpt_path, f"does not fit this model/optimiser ({type(e).__name__}: "
                                  f"{str(e).splitlines()[0]})") from None
        start_step = ckpt.step
        interval = ckpt.train_state.get("log_interval", interval)
        elapsed_before = float(ckpt.train_state.get("elapsed_s", 0.0))
        items_before = int(ckpt.train_state.get("items_trained", start_step * loop.batch_size * dist_info.world_size))
    elif init is not None:
        from cosy_lite.train.init_weights import load_initial_weights

        init_record = load_initial_weights(model, init, task.kind)
        weights_source = f"init: {init}"
    if dist_info.is_main:  # records after the checkpoint (all, without one) come again
        _truncate_log(log_path, start_step)
    barrier(dist_info)

    ddp_model: torch.nn.Module | None = None
    if dist_info.distributed:
        ddp_model = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None)
    train_model = ddp_model if ddp_model is not None else model

    dataset = task.train_dataset()
    if len(dataset) == 0:
        raise CosyLiteError(f"{out_dir}: the {task.kind} training set is empty (no training items in the dataset)")
    sampler = StepBatchSampler(len(dataset), loop.batch_size, loop.seed, start_step, loop.steps,
                               dist_info.rank, dist_info.world_size)
    loader = DataLoader(dataset, batch_sampler=sampler, num_workers=loop.num_workers, collate_fn=task.collate,
                        persistent_workers=False, pin_memory=device.type == "cuda")
    use_amp = loop.amp and device.type == "cuda"
    autocast = (lambda: torch.autocast("cuda", dtype=torch.bfloat16)) if use_amp else nullcontext

    def checkpoint(step: int) -> None:
        if not dist_info.is_main:
            return
        items_trained = items_before + total_items
        before = (init_record or {}).get("items_seen") or 0
        task_meta = task.checkpoint_meta()
        if "initialised_from" in task_meta and task_meta["initialised_from"] is None:
            task_meta["initialised_from"] = weights_source
        meta = {**task_meta, "items_seen": items_trained + before, "world_size": dist_info.world_size,
                **({"init": init_record} if init_record else {})}
        save_checkpoint(ckpt_path, Checkpoint(
            kind=task.kind, model=model.state_dict(), config=config, step=step,
            train_state={"optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
                         "log_interval": {"sums": dict(sums), "n": n_sum},
                         "elapsed_s": elapsed_before + time.perf_counter() - t_start,
                         "items_trained": items_trained},
            meta=meta))
        if log_path.is_file():
            plot_losses(log_path, out_dir / "loss.png")

    def log(record: dict[str, Any]) -> None:
        if dist_info.is_main:
            with open(log_path, "a") as f:
                f.write(json.dumps(record) + "\n")

    if loop.val_at_start and loop.val_every > 0 and start_step == 0 and dist_info.is_main:
        train_model.eval()
        with torch.no_grad():
            first_val = task.validate(model, device)
        log({"type": "val", "step": 0, **{f"val/{k}": v for k, v in first_val.items()}})
        print("step 0: " + ", ".join(f"{k} {v:.4g}" for k, v in first_val.items()), flush=True)
    bar = tqdm(total=loop.steps, initial=start_step, desc=f"train {task.kind}", unit="step",
               disable=None if (progress and dist_info.is_main) else True, dynamic_ncols=True)  # None: only on a terminal
    t_start = time.perf_counter()
    t_interval, items_interval = time.perf_counter(), 0
    sums: dict[str, float] = dict(interval["sums"])
    n_sum = int(interval["n"])
    step = start_step
    last_losses: dict[str, float] = {}
    last_val: dict[str, float] = {}
    total_items = 0
    train_model.train()
    if loop.max_minutes > 0 and elapsed_before >= 60 * loop.max_minutes:
        bar.write(f"{ckpt_path}: the run has trained {elapsed_before / 60:.1f} min of its loop.max_minutes="
                  f"{loop.max_minutes:g} already; nothing to do (raise loop.max_minutes to train on)")
        loader = []
    for batch in loader:
        torch.manual_seed(loop.seed * 1_000_003 + step * dist_info.world_size + dist_info.rank)
        with autocast():
            losses = task.compute_losses(train_model, batch, step, device)
        total = losses["total"]
        if not torch.isfinite(total):
            raise DivergedError(f"{out_dir}: step {step}: non-finite loss {({k: float(v.detach()) for k, v in losses.items()})}; "
                                "expected finite losses (lower optim.lr, check the data)")
        optimizer.zero_grad(set_to_none=True)
        total.backward()
        if optim.clip_grad_norm > 0:
            torch.nn.utils.clip_grad_norm_(model.parameters(), optim.clip_grad_norm)
        optimizer.step()
        scheduler.step()
        elapsed = elapsed_before + time.perf_counter() - t_start
        out_of_time = loop.max_minutes > 0 and elapsed > 60 * loop.max_minutes
        done = elapsed / (60 * loop.max_minutes) if loop.max_minutes > 0 else (step + 1) / loop.steps
        # ranks agree on stopping and on the learning rate (their clocks differ slightly)
        out_of_time, done = all_reduce_mean(torch.tensor([float(out_of_time), done]), dist_info).tolist()
        stop = out_of_time > 0
        for group in optimizer.param_groups:  # LambdaLR sets the lr from scratch at each of its steps
            group["lr"] *= budget_factor(done, optim)
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
            log({"type": "train", "step": step, "lr": optimizer.param_groups[0]["lr"], "items_per_s": rate,
                 "elapsed_s": elapsed_before + time.perf_counter() - t_start,
                 **{f"loss/{k}": v for k, v in last_losses.items()}})
            bar.set_postfix(loss=f"{last_losses['total']:.4g}", items_s=f"{rate:.1f}")
            sums, n_sum, items_interval, t_interval = {}, 0, 0, time.perf_counter()
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
