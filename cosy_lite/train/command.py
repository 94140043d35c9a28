"""``python train.py --model coarse|refiner|detector``: config -> task -> the training loop."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any, Callable

from cosy_lite.config import load_config, save_config
from cosy_lite.errors import ConfigError
from cosy_lite.train.loop import check_train_config, train

CONFIGS_DIR = Path(__file__).resolve().parents[2] / "configs"


def _pose_task(cfg, root: Path):
    from cosy_lite.train.pose_task import PoseTask

    return PoseTask(cfg, root)


def _detector_task(cfg, root: Path):
    from cosy_lite.train.detector_task import DetectorTask

    return DetectorTask(cfg, root)


def _pose_config():
    from cosy_lite.train.pose_task import PoseTrainConfig

    return PoseTrainConfig


def _detector_config():
    from cosy_lite.train.detector_task import DetectorTrainConfig

    return DetectorTrainConfig


# model -> (config class getter, task builder)
TASKS: dict[str, tuple[Callable[[], type], Callable[[Any, Path], Any]]] = {
    "coarse": (_pose_config, _pose_task),
    "refiner": (_pose_config, _pose_task),
    "detector": (_detector_config, _detector_task),
}


def default_config_path(model: str, profile: str = "demo") -> Path:
    return CONFIGS_DIR / model / f"{profile}.yaml"


def load_train_config(args: argparse.Namespace, dataset_name: str) -> Any:
    """The training config of ``args`` (``--config`` or ``--profile`` YAML + overrides), checked:
    ConfigError naming the file or override and the key for anything that cannot train."""
    config_cls, _ = TASKS[args.model]
    cfg_path = Path(args.config) if args.config else default_config_path(args.model, args.profile)
    if not args.config and not cfg_path.is_file():
        profiles = sorted(p.stem for p in cfg_path.parent.glob("*.yaml"))
        raise ConfigError(cfg_path, "--profile", f"no profile {args.profile!r} for the {args.model}; "
                          f"expected one of {profiles}")
    overrides = [*args.overrides, f"model={args.model}", f"dataset={dataset_name}"]
    cfg = load_config(config_cls(), cfg_path, overrides)
    check_train_config(cfg.loop, cfg.optim, " + ".join([str(cfg_path), *(f"override {o!r}" for o in args.overrides)]))
    return cfg


def run(root: Path, args: argparse.Namespace, cfg: Any | None = None) -> int:
    """Train ``args.model`` on the dataset at ``root``; the run folder is ``args.out``."""
    _, make_task = TASKS[args.model]
    cfg = cfg if cfg is not None else load_train_config(args, args.dataset_name)
    out = Path(args.out) if args.out else Path("runs") / f"{args.dataset_name}-{args.model}"
    if out.exists() and not out.is_dir():
        raise ConfigError(out, "--out", "exists and is not a folder; expected a run folder")
    task = make_task(cfg, root)
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.yaml")
    print(f"training {args.model} on {root} ({len(task.train_dataset())} training items) -> {out}")
    summary = train(task, cfg.loop, cfg.optim, out, config=dataclasses.asdict(cfg), resume=args.resume)
    print(f"done: {summary.steps_done} steps in {summary.seconds / 60:.1f} min ({summary.items_per_s:.1f} items/s); "
          f"checkpoint {summary.checkpoint}")
    for k, v in summary.last_val.items():
        print(f"  {k:32s} {v:.4f}")
    return 0
