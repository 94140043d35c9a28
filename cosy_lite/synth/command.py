"""``cosy-lite generate``: write the embedded synthetic BOP dataset."""

from __future__ import annotations

import argparse
import os
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, default=None,
                   help="YAML with differences from the defaults (default dataset ycbv-synth); e.g. configs/synth/tiny.yaml")
    p.add_argument("--out", type=Path, default=None, help="dataset folder (default: $COSY_LITE_DATA or ./data, / NAME)")
    p.add_argument("--splits", nargs="+", default=["train_pbr", "test"], choices=["train_pbr", "test"])
    p.add_argument("--workers", type=int, default=None, help="processes rendering layouts in parallel")
    p.add_argument("overrides", nargs="*", help="config overrides key=value, e.g. train.n_images=200 seed=3")


def default_data_root() -> Path:
    return Path(os.environ.get("COSY_LITE_DATA", "data"))


def run(args: argparse.Namespace) -> int:
    from cosy_lite.config import load_config
    from cosy_lite.synth.generator import SynthConfig, generate

    cfg = load_config(SynthConfig, args.config, args.overrides)
    if args.workers is not None:
        cfg.workers = args.workers
    out = args.out or default_data_root() / cfg.name
    stats = generate(cfg, out, tuple(args.splits))
    rate = stats["images"] / stats["seconds"] if stats["images"] else 0.0
    print(f"{out}: {stats['images']} new images in {stats['seconds']:.1f} s ({rate:.2f} img/s)")
    return 0
