"""Estimate 6D poses on a BOP test split and write the BOP19 submission CSV: ``python infer.py --dataset ...``.

Thin wrapper: parse, load the checkpoints (:meth:`cosy_lite.inference.predictor.Predictor.from_checkpoints`),
hand over to :func:`cosy_lite.inference.bop_run.run_on_split` (ViVo targets, CSV
``METHOD_DATASET-SPLIT.csv``, overlays, results checker). Example::

    python infer.py --dataset ycbv-synth --detector runs/ycbv-synth-detector/checkpoint.pt \\
        --coarse runs/ycbv-synth-coarse/checkpoint.pt --refiner runs/ycbv-synth-refiner/checkpoint.pt \\
        --out results/ --vis 8
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default="ycbv-synth", help="dataset name (folder under --data-root) or path")
    ap.add_argument("--data-root", type=Path, default=None, help="default: $COSY_LITE_DATA or ./data")
    ap.add_argument("--split", default="test", help="test split (default: test)")
    ap.add_argument("--detector", type=Path, default=None, metavar="CKPT", help="detector checkpoint")
    ap.add_argument("--coarse", type=Path, required=True, metavar="CKPT", help="coarse pose checkpoint")
    ap.add_argument("--refiner", type=Path, default=None, metavar="CKPT", help="refiner checkpoint (none: coarse only)")
    ap.add_argument("--n-refiner-iters", type=int, default=4, help="refiner iterations (default 4)")
    ap.add_argument("--icp", action="store_true", help="refine with the depth images (point-to-plane ICP)")
    ap.add_argument("--detections", default=None, metavar="oracle|FILE.json",
                    help="instead of the detector: 'oracle' (ground-truth boxes and masks) or a BOP22 detections JSON")
    ap.add_argument("--out", type=Path, default=Path("results"), help="output folder (default results/)")
    ap.add_argument("--method", default="cosylite", help="method name of the CSV file (no '_')")
    ap.add_argument("--vis", type=int, default=0, metavar="N", help="write overlay PNGs for the first N images")
    ap.add_argument("--limit-images", type=int, default=None, metavar="N", help="only the first N target images")
    ap.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    ap.add_argument("--precision", default="fp32", choices=["fp32", "bf16"],
                    help="pose networks' arithmetic: fp32, or bf16 autocast (faster on CPUs with AVX512-BF16)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # Waiting OpenMP threads sleep instead of spinning (read when torch loads, so only if it has
    # not yet): on CPUs shared with other jobs, spinning threads made the networks 3-8x slower.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.results import results_filename
    from cosy_lite.errors import BopFormatError
    from cosy_lite.inference.bop_run import run_on_split
    from cosy_lite.inference.predictor import Predictor, SetupError
    from cosy_lite.render.gl import use_egl
    from cosy_lite.synth.command import default_data_root
    from cosy_lite.train.checkpoint import CheckpointError

    use_egl()
    if args.detector is None and args.detections is None:
        print("error: give --detector CKPT or --detections oracle|FILE.json", file=sys.stderr)
        return 2
    method = args.method.replace("_", "")
    if method != args.method:
        print(f"note: method name {args.method!r} written as {method!r} (BOP file names have one '_')")
    try:
        results_filename(method, "dataset", args.split)
    except ValueError as e:
        print(f"error: --method / --split: {e}", file=sys.stderr)
        return 2
    root = Path(args.dataset) if Path(args.dataset).is_dir() else (args.data_root or default_data_root()) / args.dataset
    try:
        import torch

        device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
        dataset = BopDataset(root)
        predictor = Predictor.from_checkpoints(
            detector=args.detector if args.detections is None else None, coarse=args.coarse, refiner=args.refiner,
            dataset=dataset, device=device, n_refiner_iterations=args.n_refiner_iters if args.refiner else 0,
            icp=args.icp, precision=args.precision)
        summary = run_on_split(predictor, dataset, args.out, args.split, method, args.detections, args.vis,
                               args.limit_images, progress=not args.no_progress,
                               detector_path=args.detector if args.detections is None else None)
    except (CheckpointError, BopFormatError, FileNotFoundError, SetupError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for p in summary.problems:
        print(p)
    for line in summary.lines():
        print(line)
    return 0 if summary.ok else 1


if __name__ == "__main__":
    sys.exit(main())
