"""Scratch: training-free coarse pose by silhouette templates, then the flow refiner.

Per object, N allocentric rotations rendered (depth only) on the optical axis; each silhouette
normalised to a SxS occupancy grid over the square around its box. A test instance's visible mask is
normalised the same way over its visible box; the best template (soft IoU) gives R_allo, its box
gives depth and the origin offset; R = R_ray(t) R_allo. Then 4 refiner iterations (a checkpoint).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(1, str(Path(__file__).parents[1] / "2026-12-01"))  # ramdata.py (the RAM cache of train_pbr)
from ramdata import RamBatcher, load_split, make_split  # noqa: E402
from coarsecls import random_rotations, ray_rotation  # noqa: E402

from cosy_lite.models.object_table import ObjectTable  # noqa: E402
from cosy_lite.render.renderer import PyrenderRenderer  # noqa: E402
from cosy_lite.train.pose_task import pose_errors  # noqa: E402

TF, TRES = 300.0, 128  # template focal (px), template image side


def norm_grid(masks: torch.Tensor, boxes: torch.Tensor, S: int) -> torch.Tensor:
    """masks [B,H,W] bool, boxes [B,4] xyxy -> occupancy [B,S,S] over the square around each box."""
    B, H, W = masks.shape
    c = (boxes[:, :2] + boxes[:, 2:]) / 2
    half = (boxes[:, 2:] - boxes[:, :2]).amax(1) / 2 * 1.05 + 1
    lin = (torch.arange(S, dtype=torch.float32) + 0.5) / S * 2 - 1
    gy, gx = torch.meshgrid(lin, lin, indexing="ij")
    x = c[:, 0, None, None] + gx[None] * half[:, None, None]
    y = c[:, 1, None, None] + gy[None] * half[:, None, None]
    grid = torch.stack([(x + 0.5) / W * 2 - 1, (y + 0.5) / H * 2 - 1], -1)  # align_corners=False pixel centres
    m = masks.float()[:, None]
    # area-like sampling: supersample 4x4 then average
    up = F.grid_sample(m, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return up[:, 0]


def mask_boxes(masks: torch.Tensor) -> torch.Tensor:
    B = masks.shape[0]
    out = torch.zeros(B, 4)
    for i in range(B):
        ys, xs = torch.nonzero(masks[i], as_tuple=True)
        if len(xs):
            out[i] = torch.tensor([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=torch.float32)
    return out


def build_templates(renderer, obj_id, diameter, anchors, S):
    z0 = TF * diameter / (0.6 * TRES)
    K = torch.tensor([[TF, 0, TRES / 2], [0, TF, TRES / 2], [0, 0, 1]], dtype=torch.float64)
    n = len(anchors)
    TCO = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    TCO[:, :3, :3] = anchors.double()
    TCO[:, 2, 3] = z0
    grids, boxes = [], []
    for s in range(0, n, 256):
        r = renderer.render([obj_id] * len(TCO[s:s + 256]), TCO[s:s + 256].numpy(), K.numpy(), (TRES, TRES), depth_only=True)
        m = torch.from_numpy(r.mask)
        b = mask_boxes(m)
        grids.append(norm_grid(m, b, S)); boxes.append(b)
    return torch.cat(grids), torch.cat(boxes), z0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--anchors", type=int, default=2048)
    ap.add_argument("--grid", type=int, default=32)
    ap.add_argument("--n-val", type=int, default=128)
    ap.add_argument("--topk", type=int, default=5)
    ap.add_argument("--refiner", default=None)
    ap.add_argument("--baseline-coarse", default=None, help="coarse checkpoint: also box init -> coarse -> 4 refiner its")
    args = ap.parse_args()
    torch.set_num_threads(1)
    out = Path(args.out); out.mkdir(parents=True, exist_ok=True)
    root = Path("/work/main/data/ycbvsynth")
    ds, full, rgb, lab = load_split(root, "train_pbr", Path("/work/cache"))
    _, va_rows = make_split(full)
    val = RamBatcher(full, va_rows, rgb, lab)
    objects = ObjectTable.from_dataset(ds, None, 2000, 64)
    g = torch.Generator().manual_seed(12345)
    vidx = torch.randperm(len(val), generator=g)[: args.n_val].numpy()
    vb = val.get(vidx)
    rows = objects.index(vb["obj"])
    pts, syms, smask, diam = objects.points[rows], objects.symmetries[rows], objects.sym_mask[rows], objects.diameters[rows]
    gt = vb["TCO"]
    renderer = PyrenderRenderer.from_dataset(ds, shading="headlight")
    anchors = random_rotations(args.anchors)
    t0 = time.perf_counter()
    tmpl = {}
    for o in sorted(set(vb["obj"].tolist())):
        tmpl[o] = build_templates(renderer, o, float(objects.diameters[objects.index([o])][0]), anchors, args.grid)
    t_tmpl = time.perf_counter() - t0
    print(f"templates: {len(tmpl)} objects x {args.anchors} in {t_tmpl:.1f} s", flush=True)

    masks = (vb["lab"] == (vb["gt"][:, None, None] + 1))
    boxes = mask_boxes(masks)
    obs = norm_grid(masks, boxes, args.grid)
    B = len(vidx)
    TCO = torch.eye(4, dtype=torch.float64).repeat(B, 1, 1)
    cand_rot_err = []
    t1 = time.perf_counter()
    top_all = []
    for i in range(B):
        o = int(vb["obj"][i])
        grids, tboxes, z0 = tmpl[o]
        inter = torch.minimum(grids, obs[i][None]).sum((1, 2))
        union = torch.maximum(grids, obs[i][None]).sum((1, 2)).clamp(min=1e-6)
        score = inter / union
        top = score.topk(args.topk).indices
        top_all.append(top)
        j = int(top[0])
        tb = tboxes[j]
        s_t = float((tb[2:] - tb[:2]).max())
        s_o = float((boxes[i, 2:] - boxes[i, :2]).max())
        K = vb["K"][i].double()
        f_o = float(K[0, 0])
        z = z0 * (s_t / TF) / (s_o / f_o)
        ct = (tb[:2] + tb[2:]) / 2 - TRES / 2  # template box centre - origin projection (px)
        co = (boxes[i, :2] + boxes[i, 2:]) / 2 - ct * (s_o / s_t)
        xy = (co.double() - K[:2, 2]) / torch.stack([K[0, 0], K[1, 1]]) * z
        t = torch.tensor([float(xy[0]), float(xy[1]), z], dtype=torch.float64)
        TCO[i, :3, 3] = t
        Rr = ray_rotation(t[None])[0]
        TCO[i, :3, :3] = Rr @ anchors[j].double()
        # oracle over top-k
        errs = []
        for jj in top.tolist():
            T = TCO[i:i + 1].clone()
            T[0, :3, :3] = Rr @ anchors[jj].double()
            errs.append(float(pose_errors(T, gt[i:i + 1], pts[i:i + 1], syms[i:i + 1], smask[i:i + 1]).rot_deg[0]))
        cand_rot_err.append(min(errs))
    t_match = time.perf_counter() - t1
    e = pose_errors(TCO, gt, pts, syms, smask)
    rep = e.summary(diam, "coarse/")
    rep["coarse/rot_lt15"] = float((e.rot_deg < 15).float().mean())
    rep["coarse/rot_lt30"] = float((e.rot_deg < 30).float().mean())
    ce = torch.tensor(cand_rot_err)
    rep[f"coarse/best_of_top{args.topk}_rot_median"] = float(ce.median())
    rep[f"coarse/best_of_top{args.topk}_lt30"] = float((ce < 30).float().mean())
    dz = (TCO[:, 2, 3] - gt[:, 2, 3]) * 100
    rep["coarse/dz_cm_median_signed"] = float(dz.median())
    rep["templates_s"], rep["match_s_per_instance"] = t_tmpl, t_match / B
    print({k: round(v, 3) for k, v in rep.items()}, flush=True)
    if args.refiner:
        from cosy_lite.model_files.loaders import load_pose_model
        from cosy_lite.models.render_and_compare import iterate_poses

        model = load_pose_model(args.refiner, "refiner")
        with torch.no_grad():
            poses = iterate_poses(model.net, vb["rgb"].float() / 255, vb["K"].float(), TCO.float(), vb["obj"].tolist(),
                                  pts.float(), renderer, 4, model.crop_resolution, output=model.output)
        for k in (0, 3):
            e2 = pose_errors(poses[k], gt, pts, syms, smask)
            rep.update(e2.summary(diam, f"refined_it{k + 1}/"))
        print({k: round(v, 3) for k, v in rep.items() if "refined" in k}, flush=True)
        if args.baseline_coarse:
            from cosy_lite.models.initial_pose import initial_pose_from_boxes
            coarse = load_pose_model(args.baseline_coarse, "coarse")
            T0 = initial_pose_from_boxes(boxes.double(), vb["K"].double(), diam.double()).float()
            with torch.no_grad():
                Tc = iterate_poses(coarse.net, vb["rgb"].float() / 255, vb["K"].float(), T0, vb["obj"].tolist(),
                                   pts.float(), renderer, 1, coarse.crop_resolution, output=coarse.output)[-1]
            for name, start in (("box_canonical", T0), ("box_trained_coarse", Tc)):
                with torch.no_grad():
                    pp = iterate_poses(model.net, vb["rgb"].float() / 255, vb["K"].float(), start, vb["obj"].tolist(),
                                       pts.float(), renderer, 4, model.crop_resolution, output=model.output)
                rep.update(pose_errors(start, gt, pts, syms, smask).summary(diam, f"{name}/start/"))
                rep.update(pose_errors(pp[-1], gt, pts, syms, smask).summary(diam, f"{name}/it4/"))
            print({k: round(v, 3) for k, v in rep.items() if k.startswith("box")}, flush=True)
        # top-k candidates: 2 refiner iterations each, choose by the flow confidence, 2 more on the choice
        from cosy_lite.models.render_and_compare import make_inputs, updated_poses

        Kk = args.topk
        cand = TCO[:, None].repeat(1, Kk, 1, 1).clone()
        for i in range(B):
            Rr = ray_rotation(TCO[i:i + 1, :3, 3])[0]
            for a, jj in enumerate(top_all[i].tolist()):
                cand[i, a, :3, :3] = Rr @ anchors[jj].double()
        C = cand.reshape(B * Kk, 4, 4).float()
        imgs = (vb["rgb"].float() / 255).repeat_interleave(Kk, 0)
        Kc = vb["K"].float().repeat_interleave(Kk, 0)
        oids = vb["obj"].repeat_interleave(Kk, 0).tolist()
        P = pts.float().repeat_interleave(Kk, 0)
        confs = []
        with torch.no_grad():
            for it in range(2):
                new, cf = [], []
                for s0 in range(0, len(C), 32):
                    sl = slice(s0, s0 + 32)
                    inp = make_inputs(imgs[sl], Kc[sl], C[sl], oids[sl], P[sl], renderer, model.crop_resolution)
                    o = model.net(inp.images)
                    d = F.adaptive_avg_pool2d((inp.depth > 0).float(), o.shape[-2:]) > 0.5
                    cf.append((o[:, 2:3] * d).sum((1, 2, 3)) / d.sum((1, 2, 3)).clamp(min=1))
                    new.append(updated_poses(C[sl], inp, o, model.output))
                C = torch.cat(new)
                confs.append(torch.cat(cf))
        for name, sc in (("conf_it1", confs[0]), ("conf_it2", confs[1])):
            pick = sc.view(B, Kk).argmax(1)
            chosen = C.view(B, Kk, 4, 4)[torch.arange(B), pick]
            with torch.no_grad():
                poses = iterate_poses(model.net, vb["rgb"].float() / 255, vb["K"].float(), chosen, vb["obj"].tolist(),
                                      pts.float(), renderer, 2, model.crop_resolution, output=model.output)
            e3 = pose_errors(poses[-1], gt, pts, syms, smask)
            rep.update(e3.summary(diam, f"top{Kk}_{name}_it4/"))
            ec = pose_errors(cand[torch.arange(B), pick], gt, pts, syms, smask)
            rep[f"top{Kk}_{name}/chosen_coarse_rot_median"] = float(ec.rot_deg.median())
        print({k: round(v, 3) for k, v in rep.items() if k.startswith("top")}, flush=True)
    (out / "report.json").write_text(json.dumps(rep, indent=1))


if __name__ == "__main__":
    main()
