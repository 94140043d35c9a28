"""Optimiser and learning-rate schedule: Adam, linear warm-up, then step decay or a cosine decay over
the run's budget (its training minutes, or its steps without a time limit)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch


@dataclass
class OptimConfig:
    """Adam with linear warm-up from ``lr / warmup_steps`` to ``lr``, then x``decay_factor`` at each
    step of ``decay_steps``; gradients clipped to ``clip_grad_norm`` (0 = no clipping).

    ``schedule = "cosine"`` replaces the step decay (``decay_steps`` are ignored: a profile's steps
    left under the cosine held a 60-minute detector run at <= 3e-5 for most of its time) by a cosine
    from 1 to ``cosine_floor`` over the fraction of the run done: its training time over
    ``loop.max_minutes`` when that is set (so a time-capped run ends at the low rate whatever its
    speed), else its steps over ``loop.steps``.
    """

    lr: float = 3e-4
    weight_decay: float = 0.0
    warmup_steps: int = 100
    decay_steps: list[int] = field(default_factory=list)
    decay_factor: float = 0.1
    clip_grad_norm: float = 10.0
    schedule: str = "step"
    cosine_floor: float = 0.05


SCHEDULES = ("step", "cosine")


def lr_factor(step: int, cfg: OptimConfig) -> float:
    """Multiplier of ``cfg.lr`` at optimisation step ``step`` (0-based)."""
    warm = min(1.0, (step + 1) / cfg.warmup_steps) if cfg.warmup_steps > 0 else 1.0
    if cfg.schedule == "cosine":
        return warm
    n_decays = sum(step >= s for s in cfg.decay_steps)
    return warm * cfg.decay_factor**n_decays


def budget_factor(done_fraction: float, cfg: OptimConfig) -> float:
    """Multiplier from the run's schedule at ``done_fraction`` of its budget (1 for ``"step"``)."""
    if cfg.schedule != "cosine":
        return 1.0
    f = min(max(done_fraction, 0.0), 1.0)
    return cfg.cosine_floor + (1.0 - cfg.cosine_floor) * 0.5 * (1.0 + math.cos(math.pi * f))


def learning_rate(step: int, done_fraction: float, cfg: OptimConfig) -> float:
    """The learning rate of optimisation step ``step`` (0-based) when ``done_fraction`` of the run's
    budget is behind it: ``cfg.lr`` x warm-up and step decay x the cosine over the budget."""
    return cfg.lr * lr_factor(step, cfg) * budget_factor(done_fraction, cfg)


def set_learning_rate(optimizer: torch.optim.Optimizer, step: int, done_fraction: float | None,
                      cfg: OptimConfig) -> None:
    """The one place the learning rate is set, before each optimisation step. ``done_fraction`` None
    (the first step resumed from a checkpoint that did not record it): the rate the checkpoint's
    optimiser holds stands."""
    if done_fraction is None:
        return
    lr = learning_rate(step, done_fraction, cfg)
    for group in optimizer.param_groups:
        group["lr"] = lr


def build_optimizer(params, cfg: OptimConfig) -> torch.optim.Optimizer:
    """Adam over ``params`` (its rate set by :func:`set_learning_rate` before each step)."""
    return torch.optim.Adam(params, lr=cfg.lr * lr_factor(0, cfg), weight_decay=cfg.weight_decay, foreach=True)
