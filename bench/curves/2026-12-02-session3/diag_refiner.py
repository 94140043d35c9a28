"""Scratch: a refiner checkpoint on N held-out instances: per-iteration errors, signed depth error,
xy error; starts: GT + noise (the training noise) and GT rotation + box translation."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(1, str(Path(__file__).parents[1] / "2026-12-01"))  # ramdata.py (the RAM cache of train_pbr)
from ramdata import RamBatcher, load_split, make_split  # noqa: E402

from cosy_lite.model_files.loaders import load_pose_model  # noqa: E402
from cosy_lite.models.initial_pose import add_pose_noise, initial_pose_from_boxes  # noqa: E402
from cosy_lite.models.object_table import ObjectTable  # noqa: E402
from cosy_lite.models.render_and_compare import iterate_poses  # noqa: E402
from cosy_lite.render.renderer import PyrenderRenderer  # noqa: E402
from cosy_lite.train.pose_task import pose_errors  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("ckpt")
    ap.add_argument("--n-val", type=int, default=256)
    ap.add_argument("--iters", type=int, default=4)
    ap.add_argument("--out", default=None)
    ap.add_argument("--only-noise", action="store_true", help="only the GT + noise start")
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    root = Path("/work/main/data/ycbvsynth")
    ds, full, rgb, lab = load_split(root, "train_pbr", Path("/work/cache"))
    _, va_rows = make_split(full)
    val = RamBatcher(full, va_rows, rgb, lab)
    objects = ObjectTable.from_dataset(ds, None, 2000, 64)
    model = load_pose_model(args.ckpt, "refiner")
    renderer = PyrenderRenderer.from_dataset(ds, shading=model.render_shading)
    g = torch.Generator().manual_seed(12345)
    vidx = torch.randperm(len(val), generator=g)[: args.n_val].numpy()
    vb = val.get(vidx)
    rows = objects.index(vb["obj"])
    pts, syms, mask, diam = objects.points[rows], objects.symmetries[rows], objects.sym_mask[rows], objects.diameters[rows]
    gt = vb["TCO"]
    starts = {"gt_noise": add_pose_noise(gt.double(), 15.0, (0.01, 0.01, 0.05), generator=g).float()}
    box = initial_pose_from_boxes(vb["box"].float(), vb["K"].float(), diam.float())
    box[:, :3, :3] = gt[:, :3, :3].float()
    if not args.only_noise:
        starts["gt_rot_box_trans"] = box
    report = {}
    for name, T0 in starts.items():
        with torch.no_grad():
            poses = iterate_poses(model.net, vb["rgb"].float() / 255, vb["K"].float(), T0, vb["obj"].tolist(), pts.float(),
                                  renderer, args.iters, model.crop_resolution, output=model.output)
        for k, T in [("init", T0)] + [(f"it{i + 1}", p) for i, p in enumerate(poses)]:
            e = pose_errors(T, gt, pts, syms, mask)
            d = e.summary(diam, "")
            dz = (T[:, 2, 3] - gt[:, 2, 3].float()) * 100
            dxy = (T[:, :2, 3] - gt[:, :2, 3].float()).norm(dim=1) * 100
            d.update({"dz_cm_median_signed": float(dz.median()), "abs_dz_cm_median": float(dz.abs().median()),
                      "xy_cm_median": float(dxy.median())})
            report[f"{name}/{k}"] = d
            print(name, k, {a: round(b, 3) for a, b in d.items()}, flush=True)
            for n_sub in (64, 128):
                if len(T) > n_sub:
                    sub = type(e)(*(x[:n_sub] for x in (e.rot_deg, e.trans_m, e.adds_m, e.mssd_m)))
                    report[f"{name}/{k}/first{n_sub}"] = sub.summary(diam[:n_sub], "")
                    print("   first", n_sub, {a: round(b, 3) for a, b in report[f"{name}/{k}/first{n_sub}"].items()})
    from cosy_lite.model_files.checkpoint import load_checkpoint
    report["step"] = load_checkpoint(Path(args.ckpt), kind="refiner").step
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
