"""``cosy-lite export``: checkpoints -> ONNX files + ``manifest.json``
(:func:`~cosy_lite.export.onnx_export.export_models`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--pretrained", default=None, metavar="NAME",
                   help="the shipped reference models NAME (e.g. ycbvsynth); --detector/--coarse/--refiner/--scorer "
                        "given as well win")
    p.add_argument("--detector", type=Path, default=None, metavar="CKPT", help="detector checkpoint -> detector.onnx")
    p.add_argument("--coarse", type=Path, default=None, metavar="CKPT", help="coarse checkpoint -> coarse.onnx")
    p.add_argument("--refiner", type=Path, default=None, metavar="CKPT", help="refiner checkpoint -> refiner.onnx")
    p.add_argument("--scorer", type=Path, default=None, metavar="CKPT",
                   help="coarse scorer checkpoint (train.py --model scorer) -> scorer.onnx, for start=appearance")
    p.add_argument("--out", type=Path, default=Path("onnx"), metavar="DIR",
                   help="export folder (default onnx/; models/ holds the reference models)")
    p.add_argument("--quantize", default=None, choices=["int8"],
                   help="also write dynamically quantised pose networks (coarse.int8.onnx, refiner.int8.onnx)")
    p.add_argument("--opset", type=int, default=17, help="ONNX opset (>= 11; default 17)")


def run(args: argparse.Namespace) -> int:
    from cosy_lite.export.onnx_export import describe, export_models
    from cosy_lite.weights.reference_models import fill_networks, reference_models

    inference = None
    if args.pretrained is not None:
        ref = reference_models(args.pretrained)
        fill_networks(args, ref)
        inference = ref.inference  # the export runs as the set does
    if args.detector is None and args.coarse is None and args.refiner is None:
        print("error: give --pretrained NAME or at least one of --detector, --coarse, --refiner", file=sys.stderr)
        return 2
    if args.opset < 11:
        print(f"error: --opset {args.opset}: Mask R-CNN needs >= 11", file=sys.stderr)
        return 2
    # A bad checkpoint raises CheckpointError naming it: one message, exit 2 (cosy_lite.cli).
    manifest = export_models(args.out, args.detector, args.coarse, args.refiner, args.quantize, args.opset,
                             inference, args.scorer)
    for line in describe(manifest):
        print(line)
    print(f"manifest: {manifest.path}")
    return 0
