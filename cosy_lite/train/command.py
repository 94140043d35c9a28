"""``cosy-lite train --model coarse|refiner|detector|scorer`` (also ``python train.py ...``): arguments ->
dataset (generated if a synthetic one is absent, validated) -> config -> task -> the training loop.

The config is ``configs/MODEL/PROFILE.yaml`` shipped in the package (:func:`cosy_lite.config.packaged_config`)
or ``--config FILE``, then ``key=value`` overrides. Resume an interrupted run (also after kill -9) with
``--resume`` and the same ``--out``. Multi-GPU / multi-node: ``torchrun --nproc_per_node N -m cosy_lite.cli
train ...`` (or ``torchrun ... train.py ...``).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any, Callable

from cosy_lite.config import load_config, packaged_config, save_config
from cosy_lite.errors import ConfigError

MODELS = ("detector", "coarse", "refiner", "scorer")
# synthetic datasets generated when absent: name -> the packaged YAML of its differences (None: the defaults)
SYNTH_CONFIGS: dict[str, tuple[str, ...] | None] = {"ycbvsynth": None, "tiny": ("synth", "tiny.yaml")}


def _pose_task(cfg, root: Path):
    from cosy_lite.train.pose_task import PoseTask

    return PoseTask(cfg, root)


def _detector_task(cfg, root: Path):
    from cosy_lite.train.detector_task import DetectorTask

    return DetectorTask(cfg, root)


def _scorer_task(cfg, root: Path):
    from cosy_lite.train.scorer_task import ScorerTask

    return ScorerTask(cfg, root)


def _scorer_config():
    from cosy_lite.train.scorer_task import ScorerTrainConfig

    return ScorerTrainConfig


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
    "scorer": (_scorer_config, _scorer_task),
}


def default_config_path(model: str, profile: str = "demo") -> Path:
    """The packaged profile ``configs/MODEL/PROFILE.yaml`` (may not exist: an unknown profile)."""
    return packaged_config(model, f"{profile}.yaml")


def synth_config_path(name: str) -> Path | None:
    """The packaged generator config of the synthetic dataset ``name`` (None: the defaults, ycbvsynth)."""
    parts = SYNTH_CONFIGS[name]
    return packaged_config(*parts) if parts is not None else None


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--dataset", default="ycbvsynth", help="dataset name (folder under --data-root) or path")
    ap.add_argument("--data-root", type=Path, default=None, help="default: $COSY_LITE_DATA or ./data")
    ap.add_argument("--model", choices=MODELS, required=True)
    ap.add_argument("--profile", default="demo", help="configs/MODEL/PROFILE.yaml: demo (CPU, minutes) or full (GPUs)")
    ap.add_argument("--config", default=None, help="a YAML config instead of the profile's")
    ap.add_argument("--out", default=None, help="run folder (default runs/DATASET-MODEL)")
    ap.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    ap.add_argument("--init", type=Path, default=None, metavar="WEIGHTS",
                    help="start from these weights (a reference set's KIND.safetensors or a run's checkpoint.pt "
                         "of the same network; fine-tuning: a fresh optimiser and step count), recorded in the card")
    ap.add_argument("overrides", nargs="*", help="config overrides key=value, e.g. loop.steps=200 net.backbone=resnet18")


def run(args: argparse.Namespace) -> int:
    """Load the config, find (or generate) the dataset, validate it, train."""
    from cosy_lite.bop.folders import dataset_folder, where_datasets_are
    from cosy_lite.bop.params import dataset_name_of
    from cosy_lite.bop.validate import check_dataset, report

    root = dataset_folder(args.dataset, args.data_root)
    name = dataset_name_of(root)
    cfg = load_train_config(args, name)  # a bad config fails before any data work
    if not root.is_dir():
        if args.dataset not in SYNTH_CONFIGS:
            print(f"error: dataset folder {root} not found ({where_datasets_are()}; BOP datasets are not downloaded "
                  f"here; synthetic ones are generated: {sorted(SYNTH_CONFIGS)})", file=sys.stderr)
            return 2
        from cosy_lite.synth.generator import SynthConfig, generate

        generate(load_config(SynthConfig, synth_config_path(args.dataset)), root)
    if report(check_dataset(root, splits=["train_pbr"]), str(root)):
        return 1
    args.dataset_name = name
    return train_on(root, args, cfg)


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
    cfg: Any = load_config(config_cls(), cfg_path, overrides)  # one of the tasks' config dataclasses
    from cosy_lite.train.loop import check_train_config

    check_train_config(cfg.loop, cfg.optim, " + ".join([str(cfg_path), *(f"override {o!r}" for o in args.overrides)]))
    return cfg


def train_on(root: Path, args: argparse.Namespace, cfg: Any | None = None) -> int:
    """Train ``args.model`` on the dataset at ``root``; the run folder is ``args.out``."""
    from cosy_lite.train.loop import train

    _, make_task = TASKS[args.model]
    cfg = cfg if cfg is not None else load_train_config(args, args.dataset_name)
    out = Path(args.out) if args.out else Path("runs") / f"{args.dataset_name}-{args.model}"
    if out.exists() and not out.is_dir():
        raise ConfigError(out, "--out", "exists and is not a folder; expected a run folder")
    task = make_task(cfg, root)
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.yaml")
    print(f"training {args.model} on {root} ({len(task.train_dataset())} training items) -> {out}")
    summary = train(task, cfg.loop, cfg.optim, out, config=dataclasses.asdict(cfg), resume=args.resume,
                    init=getattr(args, "init", None))
    print(f"done: {summary.steps_done} steps in {summary.seconds / 60:.1f} min ({summary.items_per_s:.1f} items/s); "
          f"checkpoint {summary.checkpoint}")
    for k, v in summary.last_val.items():
        print(f"  {k:32s} {v:.4f}")
    return 0
