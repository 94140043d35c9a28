"""A training run's log: ``log.jsonl`` (one JSON record per log interval and per validation) and its
loss-curve PNG.

A killed run leaves at most a half-written last line (dropped when read); a resumed run cuts the log
back to its checkpoint's step and carries the loss sums of the interval in progress in the
checkpoint, so the log reads as one uninterrupted run.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from cosy_lite.train.distributed import DistInfo, all_reduce_mean
from cosy_lite.weights.checkpoint import CheckpointError


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


def truncate_log(log_path: Path, step: int) -> None:
    """Keep the log records up to ``step`` (the checkpoint's; 0: none): later ones will be produced again."""
    if not log_path.is_file():
        return
    keep = [r for r in read_log(log_path) if r["step"] <= step]
    tmp = log_path.with_name(f".{log_path.name}.tmp")
    tmp.write_text("".join(json.dumps(r) + "\n" for r in keep))
    os.replace(tmp, log_path)


def plot_losses(log_path: Path, png_path: Path) -> None:
    """Loss curves (every ``loss/*`` term, log scale) and validation metrics from ``log.jsonl`` (none
    without a log yet)."""
    if not log_path.is_file():
        return
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


@dataclass
class RunLog:
    """Writes the records of one process's part of a run (the main process writes, the others only
    average their losses into it) and sums the losses of the log interval in progress."""

    path: Path
    dist: DistInfo
    sums: dict[str, float] = field(default_factory=dict)  # loss sums of the interval in progress
    n: int = 0  # steps in them
    items: int = 0  # training items of the interval (for items/s)

    def write(self, record: dict[str, Any]) -> None:
        if self.dist.is_main:
            with open(self.path, "a") as f:
                f.write(json.dumps(record) + "\n")

    def add(self, losses: dict[str, torch.Tensor], items: int) -> None:
        """One step's losses, averaged over the processes."""
        values = all_reduce_mean(torch.stack([v.detach().float() for v in losses.values()]), self.dist)
        for k, v in zip(losses, values.tolist()):
            self.sums[k] = self.sums.get(k, 0.0) + v
        self.n += 1
        self.items += items

    def close_interval(self, step: int, lr: float, elapsed_s: float, seconds: float) -> tuple[dict[str, float], float]:
        """Write the interval's mean losses as a ``train`` record; returns them and the items per second."""
        means = {k: v / self.n for k, v in self.sums.items()}
        rate = self.items / max(seconds, 1e-9)
        self.write({"type": "train", "step": step, "lr": lr, "items_per_s": rate, "elapsed_s": elapsed_s,
                    **{f"loss/{k}": v for k, v in means.items()}})
        self.sums, self.n, self.items = {}, 0, 0
        return means, rate

    def validation(self, step: int, metrics: dict[str, float]) -> None:
        self.write({"type": "val", "step": step, **{f"val/{k}": v for k, v in metrics.items()}})

    def state(self) -> dict[str, Any]:
        """The interval in progress, for the checkpoint."""
        return {"sums": dict(self.sums), "n": self.n}

    def restore(self, state: dict[str, Any]) -> None:
        self.sums, self.n = dict(state.get("sums", {})), int(state.get("n", 0))
