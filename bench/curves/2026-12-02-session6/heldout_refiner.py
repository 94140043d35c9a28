"""Scratch: a refiner checkpoint on the 256 held-out instances of session 3's diag_refiner.py (same
images, instances and noise: GT + 15 deg / (1, 1, 5) cm, seed 12345), loading only the 20 held-out
images instead of caching all of train_pbr. Prints and writes medians after 1..4 iterations."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(1, str(Path(__file__).parents[1] / "2026-12-01"))  # ramdata.py: RamBatcher, make_split
from ramdata import RamBatcher, make_split  # noqa: E402

from cosy_lite.bop.dataset import BopDataset  # noqa: E402
from cosy_lite.data.instances import load_rgb  # noqa: E402
from cosy_lite.data.pose_dataset import PoseDataset  # noqa: E402
from cosy_lite.model_files.checkpoint import load_checkpoint  # noqa: E402
from cosy_lite.model_files.loaders import load_pose_model  # noqa: E402
from cosy_lite.models.initial_pose import add_pose_noise  # noqa: E402
from cosy_lite.models.object_table import ObjectTable  # noqa: E402
from cosy_lite.models.render_and_compare import iterate_poses  # noqa: E402
from cosy_lite.render.renderer import PyrenderRenderer  # noqa: E402
from cosy_lite.train.pose_task import pose_errors  # noqa: E402


class LazyImages:
    """``rgb[image_rows]`` like the RAM cache, reading only the images asked for."""

    def __init__(self, ds, full):
        self.ds, self.t, self.cache = ds, full.table, {}

    def __getitem__(self, rows):
        out = []
        for r in np.asarray(rows).tolist():
            if r not in self.cache:
                self.cache[r] = load_rgb(self.ds, "train_pbr", int(self.t.scene_ids[r]), int(self.t.im_ids[r]))
            out.append(self.cache[r])
        return np.stack(out)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("ckpt")
    ap.add_argument("--n-val", type=int, default=256)
    ap.add_argument("--iters", type=int, default=4)
    ap.add_argument("--out", default=None)
    ap.add_argument("--root", default="data/ycbvsynth")
    ap.add_argument("--from-gt", action="store_true", help="start at the GT pose (the refiner's drift at its fixed point)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    root = Path(args.root)
    ds = BopDataset(root, root.name)
    full = PoseDataset(ds, "train_pbr", min_visib_fract=0.1)
    _, va_rows = make_split(full)
    val = RamBatcher(full, va_rows, LazyImages(ds, full), None)
    objects = ObjectTable.from_dataset(ds, None, 2000, 64)
    model = load_pose_model(args.ckpt, "refiner")
    renderer = PyrenderRenderer.from_dataset(ds, shading=model.render_shading)
    g = torch.Generator().manual_seed(12345)
    vidx = torch.randperm(len(val), generator=g)[: args.n_val].numpy()
    im = val.img[vidx]
    rgb = torch.from_numpy(val.rgb[im]).permute(0, 3, 1, 2)
    rows = objects.index(val.obj[vidx])
    pts, syms, mask, diam = objects.points[rows], objects.symmetries[rows], objects.sym_mask[rows], objects.diameters[rows]
    gt = val.TCO[vidx]
    T0 = add_pose_noise(gt.double(), 15.0, (0.01, 0.01, 0.05), generator=g).float()
    if args.from_gt:
        T0 = gt.float().clone()
    with torch.no_grad():
        poses = iterate_poses(model.net, rgb.float() / 255, val.K[vidx].float(), T0, val.obj[vidx].tolist(), pts.float(),
                              renderer, args.iters, model.crop_resolution, output=model.output)
    report = {"step": load_checkpoint(Path(args.ckpt), kind="refiner").step}
    for k, T in [("init", T0)] + [(f"it{i + 1}", p) for i, p in enumerate(poses)]:
        d = pose_errors(T, gt, pts, syms, mask).summary(diam, "")
        dz = (T[:, 2, 3] - gt[:, 2, 3].float()) * 100
        d.update({"abs_dz_cm_median": float(dz.abs().median()), "dz_cm_median_signed": float(dz.median()),
                  "xy_cm_median": float((T[:, :2, 3] - gt[:, :2, 3].float()).norm(dim=1).median() * 100)})
        report[k] = d
        print(k, {a: round(b, 3) for a, b in d.items()}, flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
