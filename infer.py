"""Run the pose-estimation pipeline and write a BOP19 results CSV: ``python infer.py --dataset ...``.

Thin wrapper over ``cosy_lite.inference`` (issue #6: detector -> coarse -> refiner -> optional
ICP). Until that lands the command stops with a clear message instead of writing anything.
"""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default="ycbv-synth")
    ap.add_argument("--split", default="test")
    ap.parse_args(argv)
    print("error: the inference pipeline is not implemented yet (see the open issues); nothing written", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
