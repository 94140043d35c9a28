"""Train a cosy_lite model: ``python train.py --dataset ycbv-synth --model detector|coarse|refiner``.

Thin wrapper: parse, find (or generate) the dataset, validate it, hand over to the trainer of the
model from the TRAINERS table. The trainers arrive with their issues (detector: #5, coarse and
refiner: #4); until then the command stops with a clear message after preparing the data.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

# model -> "module:function" taking (dataset_root, args); filled as the trainers land.
TRAINERS: dict[str, str] = {}
MODELS = ("detector", "coarse", "refiner")
SYNTH_CONFIGS = {"ycbv-synth": None, "tiny": Path(__file__).parent / "configs" / "synth" / "tiny.yaml"}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default="ycbv-synth", help="dataset name (folder under --data-root) or path")
    ap.add_argument("--data-root", type=Path, default=None, help="default: $COSY_LITE_DATA or ./data")
    ap.add_argument("--model", choices=MODELS, required=True)
    args = ap.parse_args(argv)

    from cosy_lite.bop.validate import check_dataset, report
    from cosy_lite.synth.command import default_data_root

    root = Path(args.dataset) if Path(args.dataset).is_dir() else (args.data_root or default_data_root()) / args.dataset
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
    if args.model not in TRAINERS:
        print(f"error: training the {args.model!r} model is not implemented yet (see the open issues); "
              f"the dataset {root} is ready", file=sys.stderr)
        return 2
    module, fn = TRAINERS[args.model].split(":")
    import importlib

    return int(getattr(importlib.import_module(module), fn)(root, args) or 0)


if __name__ == "__main__":
    sys.exit(main())
