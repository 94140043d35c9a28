"""Train a cosy_lite model: ``python train.py --dataset ycbvsynth --model detector|coarse|refiner``.

Thin wrapper: parse, find (or generate) the dataset, validate it, hand over to
:func:`cosy_lite.train.command.run` (config: ``configs/MODEL/PROFILE.yaml`` + ``key=value`` overrides).
Resume an interrupted run (also after kill -9) with ``--resume`` and the same ``--out``.
Multi-GPU / multi-node: ``torchrun --nproc_per_node N train.py ...`` (the same script).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

MODELS = ("detector", "coarse", "refiner")
SYNTH_CONFIGS = {"ycbvsynth": None, "tiny": Path(__file__).parent / "configs" / "synth" / "tiny.yaml"}


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default="ycbvsynth", help="dataset name (folder under --data-root) or path")
    ap.add_argument("--data-root", type=Path, default=None, help="default: $COSY_LITE_DATA or ./data")
    ap.add_argument("--model", choices=MODELS, required=True)
    ap.add_argument("--profile", default="demo", help="configs/MODEL/PROFILE.yaml: demo (CPU, minutes) or full (GPUs)")
    ap.add_argument("--config", default=None, help="a YAML config instead of the profile's")
    ap.add_argument("--out", default=None, help="run folder (default runs/DATASET-MODEL)")
    ap.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    ap.add_argument("overrides", nargs="*", help="config overrides key=value, e.g. loop.steps=200 net.backbone=resnet18")
    return ap


def run(args: argparse.Namespace) -> int:
    """Load the config, find (or generate) the dataset, validate it, train."""
    from cosy_lite.bop.params import dataset_name_of
    from cosy_lite.bop.validate import check_dataset, report
    from cosy_lite.synth.command import dataset_folder
    from cosy_lite.train.command import load_train_config, run as train

    root = dataset_folder(args.dataset, args.data_root)
    name = dataset_name_of(root)
    cfg = load_train_config(args, name)  # a bad config fails before any data work
    if not root.is_dir():
        if args.dataset not in SYNTH_CONFIGS:
            print(f"error: dataset folder {root} not found (BOP datasets cannot be downloaded here; "
                  f"synthetic ones are generated: {sorted(SYNTH_CONFIGS)})", file=sys.stderr)
            return 2
        from cosy_lite.config import load_config
        from cosy_lite.synth.generator import SynthConfig, generate

        generate(load_config(SynthConfig, SYNTH_CONFIGS[args.dataset]), root)
    if report(check_dataset(root, splits=["train_pbr"]), str(root)):
        return 1
    args.dataset_name = name
    return train(root, args, cfg)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # Waiting OpenMP threads sleep instead of spinning (read when torch loads): on CPUs shared with
    # other jobs spinning threads made the networks 3-8x slower (measured for infer.py).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from cosy_lite.errors import run_reporting_errors

    return run_reporting_errors(lambda: run(args), "train.py")


if __name__ == "__main__":
    sys.exit(main())
