"""``cosy-lite contact-sheet DATASET``: a grid of N random images with their GT mask contours."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path, help="BOP dataset folder")
    p.add_argument("--name", default=None, help="dataset name in the parameter table (default: folder name)")
    p.add_argument("--split", default="train_pbr")
    p.add_argument("-n", type=int, default=16, help="number of images")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None, help="PNG path (default: outputs/contact_sheet_SPLIT.png)")


def run(args: argparse.Namespace) -> int:
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.io import save_image
    from cosy_lite.vis.gt_overlay import contact_sheet

    ds = BopDataset(args.dataset, args.name or "")
    out = args.out or Path("outputs") / f"contact_sheet_{args.split}.png"
    save_image(out, contact_sheet(ds, args.split, args.n, args.seed))
    print(f"wrote {out}")
    return 0
