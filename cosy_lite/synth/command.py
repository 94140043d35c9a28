"""``cosy-lite generate``: write the embedded synthetic BOP dataset."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, default=None,
                   help="YAML with differences from the defaults (default dataset ycbvsynth); e.g. configs/synth/tiny.yaml")
    p.add_argument("--out", type=Path, default=None, help="dataset folder (default: $COSY_LITE_DATA or ./data, / NAME)")
    p.add_argument("--splits", nargs="+", default=["train_pbr", "test"], choices=["train_pbr", "test"])
    p.add_argument("--workers", type=int, default=None, help="processes rendering layouts in parallel")
    p.add_argument("--meshes", type=Path, default=None, metavar="DIR",
                   help="your own objects: a folder of meshes (PLY/OBJ/glTF/GLB/STL), one object per file (needs --units)")
    p.add_argument("--units", choices=["mm", "m"], default=None, help="unit of the --meshes files")
    p.add_argument("overrides", nargs="*", help="config overrides key=value, e.g. train.n_images=200 seed=3")


def run(args: argparse.Namespace) -> int:
    from cosy_lite.bop.folders import default_data_root
    from cosy_lite.config import load_config
    from cosy_lite.synth.generator import SynthConfig, generate

    cfg = load_config(SynthConfig, args.config, args.overrides)
    if args.workers is not None:
        cfg.workers = args.workers
    if (args.meshes is None) != (args.units is None):
        print("error: --meshes DIR and --units mm|m go together (the unit of the meshes is not guessed)", file=sys.stderr)
        return 2
    if args.meshes is not None:
        if args.out is None:
            print("error: --meshes needs --out DIR (the dataset folder; its name is the dataset's name)", file=sys.stderr)
            return 2
        cfg.models_dir, cfg.models_units, cfg.name = str(args.meshes), args.units, args.out.name
    out = args.out or default_data_root() / cfg.name
    if "-" in out.name or "_" in out.name:
        print(f"error: dataset folder name {out.name!r} contains '-' or '_': the BOP toolkit splits results file "
              f"names METHOD_DATASET-SPLIT.csv on them; name it e.g. {out.name.replace('-', '').replace('_', '')!r}",
              file=sys.stderr)
        return 2
    stats = generate(cfg, out, tuple(args.splits))
    rate = stats["images"] / stats["seconds"] if stats["images"] else 0.0
    print(f"{out}: {stats['images']} new images in {stats['seconds']:.1f} s ({rate:.2f} img/s)")
    return 0
