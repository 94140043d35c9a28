"""Estimate 6D poses on a BOP test split and write the BOP19 submission CSV: ``python infer.py --dataset ...``.

Thin wrapper of ``cosy-lite infer`` (:mod:`cosy_lite.inference.command_infer`: the arguments, the
predictor from checkpoints, the shipped reference models or ONNX exports, the run over the split). Examples::

    python infer.py --dataset ycbvsynth --detector runs/ycbvsynth-detector/checkpoint.pt \\
        --coarse runs/ycbvsynth-coarse/checkpoint.pt --refiner runs/ycbvsynth-refiner/checkpoint.pt \\
        --out results/ --vis 8
    python infer.py --dataset ycbvsynth --pretrained ycbvsynth --out results/   # the shipped reference models
    python infer.py --dataset ycbvsynth --onnx onnx/ --threads 2 --out results/
"""

from __future__ import annotations

import os
import sys


def main(argv: list[str] | None = None) -> int:
    # Waiting OpenMP threads sleep instead of spinning (read when torch loads, so only if it has
    # not yet): on CPUs shared with other jobs, spinning threads made the networks 3-8x slower.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from cosy_lite import cli

    return cli.main(["infer", *(sys.argv[1:] if argv is None else argv)], prog="infer.py")


if __name__ == "__main__":
    sys.exit(main())
