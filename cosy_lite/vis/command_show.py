"""``cosy-lite show DATASET --scene S --image I``: GT poses re-rendered over the image, as a PNG."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path, help="BOP dataset folder")
    p.add_argument("--name", default=None, help="dataset name in the parameter table (default: folder name)")
    p.add_argument("--split", default="train_pbr")
    p.add_argument("--scene", type=int, default=0)
    p.add_argument("--image", type=int, default=0)
    p.add_argument("--out", type=Path, default=None, help="PNG path (default: outputs/show_SPLIT_SCENE_IMAGE.png)")


def run(args: argparse.Namespace) -> int:
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.io import save_image
    from cosy_lite.vis.gt_overlay import render_gt_overlay

    ds = BopDataset(args.dataset, args.name or "")
    out = args.out or Path("outputs") / f"show_{args.split}_{args.scene:06d}_{args.image:06d}.png"
    save_image(out, render_gt_overlay(ds, ds.image(args.split, args.scene, args.image)))
    print(f"wrote {out}")
    return 0
