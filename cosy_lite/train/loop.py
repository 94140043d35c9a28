"""The one training loop of cosy_lite (detector, coarse and refiner all run through it).

A model-specific :class:`TrainTask` says how to build the model and the data and how to compute
the losses of a batch; this loop owns everything else: device and DDP, Adam and its learning-rate
schedule (:mod:`~cosy_lite.train.schedule`), gradient clipping, mixed precision on GPU, the tqdm bar
(losses, items/s), the log (:mod:`~cosy_lite.train.run_log`), validation every N steps, atomic
checkpoints and exact resume (:mod:`~cosy_lite.train.run_state`).

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

import math
import time
from collections.abc import Sized
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol, cast

import torch
from torch.utils.data import DataLoader, Dataset

from cosy_lite.errors import ConfigError, CosyLiteError
from cosy_lite.train.distributed import DistInfo, all_reduce_mean, barrier, init_distributed, shutdown_distributed
from cosy_lite.train.run_log import RunLog, plot_losses, truncate_log
from cosy_lite.train.run_state import RunState, resume_run, save_run
from cosy_lite.train.sampler import StepBatchSampler
from cosy_lite.train.schedule import SCHEDULES, OptimConfig, build_optimizer, learning_rate, set_learning_rate
from cosy_lite.weights.checkpoint import CheckpointError, remove_stale_temporaries

CHECKPOINT_NAME = "checkpoint.pt"
LOG_NAME = "log.jsonl"


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


def _start_run(task: TrainTask, model: torch.nn.Module, optimizer: torch.optim.Optimizer, ckpt_path: Path,
               loop: LoopConfig, config: dict[str, Any], resume: bool, init: str | Path | None,
               world_size: int) -> RunState:
    """The run resumed from its checkpoint, started from ``init`` weights, or afresh."""
    if ckpt_path.is_file():
        if not resume:
            raise CheckpointError(ckpt_path, "a checkpoint already exists; pass --resume to continue it or choose "
                                  "another output folder")
        return resume_run(ckpt_path, task.kind, model, optimizer, config, loop.steps, loop.batch_size * world_size,
                          init)
    if init is not None:
        from cosy_lite.train.init_weights import load_initial_weights

        net = config.get("net")
        return RunState(init_record=load_initial_weights(model, init, task.kind, net if isinstance(net, dict) else None),
                        weights_source=f"init: {init}")
    return RunState()


def _validate(task: TrainTask, model: torch.nn.Module, device: torch.device) -> dict[str, float]:
    """The task's held-out metrics, the model in eval mode meanwhile."""
    model.eval()
    with torch.no_grad():
        metrics = task.validate(model, device)
    model.train()
    return metrics


def _progress_bar(kind: str, loop: LoopConfig, run: RunState, show: bool) -> Any:
    """The bar of a run: over its time budget in seconds when ``loop.max_minutes`` is set (the ETA is the
    budget's), else over ``loop.steps``. Shown only on a terminal."""
    from tqdm import tqdm

    disable = None if show else True  # None: only on a terminal
    if loop.max_minutes > 0:
        return tqdm(total=60 * loop.max_minutes, initial=min(run.elapsed_before, 60 * loop.max_minutes),
                    desc=f"train {kind} ({loop.max_minutes:g} min)", unit="s", disable=disable, dynamic_ncols=True,
                    bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}{postfix}]")
    return tqdm(total=loop.steps, initial=run.step, desc=f"train {kind}", unit="step", disable=disable,
                dynamic_ncols=True)


def _budget_done(run: RunState, loop: LoopConfig, dist: DistInfo, reserve: float = 0.0) -> tuple[bool, float]:
    """(out of time, the fraction of the run's budget done) after ``run.step`` steps; ``reserve``: seconds
    kept for the final validation and checkpoint (the last ones' durations), so that they end inside it. The
    processes agree on both (their clocks differ slightly)."""
    elapsed = run.elapsed()
    out_of_time = loop.max_minutes > 0 and elapsed + reserve > 60 * loop.max_minutes
    done = elapsed / (60 * loop.max_minutes) if loop.max_minutes > 0 else run.step / loop.steps
    out_of_time_mean, done = all_reduce_mean(torch.tensor([float(out_of_time), done]), dist).tolist()
    return out_of_time_mean > 0, done


def _prepare_folder(out_dir: Path, ckpt_path: Path) -> None:
    """The run folder, without the temporary checkpoint files of an interrupted write."""
    out_dir.mkdir(parents=True, exist_ok=True)
    if stale := remove_stale_temporaries(ckpt_path):
        print(f"removed {len(stale)} temporary checkpoint file(s) of an interrupted run: {[p.name for p in stale]}")


def _loader(task: TrainTask, loop: LoopConfig, start_step: int, dist: DistInfo, out_dir: Path) -> DataLoader:
    """The task's training items in the order of (seed, step) from ``start_step`` on, this process's share."""
    dataset = task.train_dataset()
    sized = cast(Sized, dataset)  # map-style: every task's training set has a length
    if len(sized) == 0:
        raise CosyLiteError(f"{out_dir}: the {task.kind} training set is empty (no training items in the dataset)")
    sampler = StepBatchSampler(len(sized), loop.batch_size, loop.seed, start_step, loop.steps, dist.rank,
                               dist.world_size)
    return DataLoader(dataset, batch_sampler=sampler, num_workers=loop.num_workers, collate_fn=task.collate,
                      persistent_workers=False, pin_memory=dist.device.type == "cuda")


def _step(task: TrainTask, train_model: torch.nn.Module, model: torch.nn.Module, optimizer: torch.optim.Optimizer,
          batch: Any, run: RunState, loop: LoopConfig, optim: OptimConfig, dist: DistInfo,
          out_dir: Path) -> dict[str, torch.Tensor]:
    """One optimisation step (the random state a function of (seed, step, rank)); returns the losses."""
    torch.manual_seed(loop.seed * 1_000_003 + run.step * dist.world_size + dist.rank)
    autocast = (torch.autocast("cuda", dtype=torch.bfloat16) if loop.amp and dist.device.type == "cuda"
                else nullcontext())
    with autocast:
        losses = task.compute_losses(train_model, batch, run.step, dist.device)
    if not torch.isfinite(losses["total"]):
        raise DivergedError(f"{out_dir}: step {run.step}: non-finite loss "
                            f"{({k: float(v.detach()) for k, v in losses.items()})}; "
                            "expected finite losses (lower optim.lr, check the data)")
    optimizer.zero_grad(set_to_none=True)
    losses["total"].backward()
    if optim.clip_grad_norm > 0:
        torch.nn.utils.clip_grad_norm_(model.parameters(), optim.clip_grad_norm)
    set_learning_rate(optimizer, run.step, run.done, optim)
    optimizer.step()
    return losses


def _validate_and_log(task: TrainTask, model: torch.nn.Module, device: torch.device, log: RunLog, step: int,
                      write: Callable[[str], None]) -> tuple[dict[str, float], float]:
    """Validate ``model``, log and write the metrics; returns them and the seconds this took (the
    validation and its log line: kept free at the end of a time budget)."""
    t_val = time.perf_counter()
    metrics = _validate(task, model, device)
    log.validation(step, metrics)
    write(f"step {step}: " + ", ".join(f"{k} {v:.4g}" for k, v in metrics.items()))
    return metrics, time.perf_counter() - t_val


def train(task: TrainTask, loop: LoopConfig, optim: OptimConfig, out_dir: str | Path, config: dict[str, Any],
          resume: bool = False, progress: bool = True, init: str | Path | None = None) -> TrainSummary:
    """Train ``task``'s model; ``config`` is the full config (stored in checkpoints, checked on resume).

    Without ``resume`` an existing checkpoint in ``out_dir`` is an error (nothing is overwritten by
    accident); with ``resume`` training continues from it (or starts if there is none). ``init``: a
    weights file whose network the run starts from instead of its fresh initialisation
    (:func:`~cosy_lite.train.init_weights.load_initial_weights`; a resumed run keeps its own record of it).
    """

    check_train_config(loop, optim)
    out_dir = Path(out_dir)
    ckpt_path, log_path = out_dir / CHECKPOINT_NAME, out_dir / LOG_NAME
    dist = init_distributed(loop.device)
    device = dist.device
    if dist.is_main:
        _prepare_folder(out_dir, ckpt_path)
    torch.set_flush_denormal(True)  # CPU: denormal floats (tiny Adam moments, activations) are very slow
    torch.manual_seed(loop.seed)  # the initial weights are a function of the seed (same on every rank)
    # resumed or --init: every weight is overwritten, so no pretrained (ImageNet) file is read
    model = task.build_model(load_pretrained=init is None and not ckpt_path.is_file()).to(device)
    optimizer = build_optimizer(model.parameters(), optim)
    run = _start_run(task, model, optimizer, ckpt_path, loop, config, resume, init, dist.world_size)
    log = RunLog(log_path, dist)
    log.restore(run.log_interval)
    if dist.is_main:  # records after the checkpoint (all, without one) come again
        truncate_log(log_path, run.step)
    barrier(dist)

    ddp_model = (torch.nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda"
                                                           else None) if dist.distributed else None)
    train_model = ddp_model if ddp_model is not None else model
    loader: Any = _loader(task, loop, run.step, dist, out_dir)

    last_losses: dict[str, float] = {}
    last_val: dict[str, float] = {}
    val_seconds = save_seconds = 0.0  # the last validation's and checkpoint's: kept free at the end of a budget
    if loop.val_at_start and loop.val_every > 0 and run.step == 0 and dist.is_main:
        _, val_seconds = _validate_and_log(task, train_model, device, log, 0, lambda text: print(text, flush=True))
    bar = _progress_bar(task.kind, loop, run, progress and dist.is_main)
    run.t_start = t_interval = time.perf_counter()
    train_model.train()
    if loop.max_minutes > 0 and run.elapsed_before >= 60 * loop.max_minutes:
        bar.write(f"{ckpt_path}: the run has trained {run.elapsed_before / 60:.1f} min of its loop.max_minutes="
                  f"{loop.max_minutes:g} already; nothing to do (raise loop.max_minutes to train on)")
        loader = []
    for batch in loader:
        losses = _step(task, train_model, model, optimizer, batch, run, loop, optim, dist, out_dir)
        run.step += 1
        stop, run.done = _budget_done(run, loop, dist, (val_seconds if loop.val_every > 0 else 0.0) + save_seconds)
        run.items += loop.batch_size * dist.world_size
        log.add(losses, loop.batch_size * dist.world_size)
        bar.update(min(run.elapsed(), bar.total) - bar.n if loop.max_minutes > 0 else 1)
        if run.step % loop.log_every == 0 or run.step == loop.steps:
            next_lr = learning_rate(run.step, run.done, optim)  # the rate of the coming step
            last_losses, rate = log.close_interval(run.step, next_lr, run.elapsed(), time.perf_counter() - t_interval)
            bar.set_postfix(step=run.step, loss=f"{last_losses['total']:.4g}", items_s=f"{rate:.1f}")
            t_interval = time.perf_counter()
        if loop.val_every > 0 and (run.step % loop.val_every == 0 or run.step == loop.steps or stop) and dist.is_main:
            last_val, val_seconds = _validate_and_log(task, model, device, log, run.step, bar.write)
        if (run.step % loop.checkpoint_every == 0 or run.step == loop.steps or stop) and dist.is_main:
            t_save = time.perf_counter()
            save_run(ckpt_path, task.kind, model, optimizer, config, run, task.checkpoint_meta(), log.state(),
                     dist.world_size)
            plot_losses(log_path, out_dir / "loss.png")
            save_seconds = time.perf_counter() - t_save
        if stop:
            bar.write(f"stopping at step {run.step}: time budget of {loop.max_minutes} min reached (checkpoint saved)")
            break
    bar.close()
    seconds = time.perf_counter() - run.t_start
    del train_model, ddp_model, loader  # before destroy_process_group (gloo aborts otherwise)
    barrier(dist)
    shutdown_distributed(dist)
    return TrainSummary(steps_done=run.step, seconds=seconds, items_per_s=run.items / max(seconds, 1e-9),
                        last_losses=last_losses, last_val=last_val,
                        checkpoint=ckpt_path if ckpt_path.is_file() else None)
