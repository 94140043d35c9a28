"""Train a cosy_lite model: ``python train.py --dataset ycbvsynth --model detector|coarse|refiner``.

Thin wrapper of ``cosy-lite train`` (:mod:`cosy_lite.train.command`: the arguments, the dataset,
the config ``configs/MODEL/PROFILE.yaml`` shipped in the package + ``key=value`` overrides).
Resume an interrupted run (also after kill -9) with ``--resume`` and the same ``--out``.
Multi-GPU / multi-node: ``torchrun --nproc_per_node N train.py ...`` (the same script).
"""

from __future__ import annotations

import os
import sys


def main(argv: list[str] | None = None) -> int:
    # Waiting OpenMP threads sleep instead of spinning (read when torch loads): on CPUs shared with
    # other jobs spinning threads made the networks 3-8x slower (measured for infer.py).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from cosy_lite import cli

    return cli.main(["train", *(sys.argv[1:] if argv is None else argv)], prog="train.py")


if __name__ == "__main__":
    sys.exit(main())
