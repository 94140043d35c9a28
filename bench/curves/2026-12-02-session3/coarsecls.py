"""Scratch: coarse rotation as classification over fixed rotation anchors (soft symmetric targets).

crop (from the box's initial pose, CosyPose crop) -> pretrained Lite0 -> pooled 1280 -> FiLM(object)
-> logits over N anchor rotations (allocentric: relative to the ray through the object). Target: a
Gaussian kernel (sigma deg) of the angle to the closest symmetric GT, normalised. Held-out metric:
symmetry-aware rotation error of the best anchor; fraction under 15/30 deg; MSSD recall of
(anchor rotation, box translation) and, with --refiner, after 4 refiner iterations.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(1, str(Path(__file__).parents[1] / "2026-12-01"))  # ramdata.py (the RAM cache of train_pbr)
from ramdata import RamBatcher, load_split, make_split  # noqa: E402

from cosy_lite.geometry.crops import crop_boxes, crop_images  # noqa: E402
from cosy_lite.models.initial_pose import initial_pose_from_boxes  # noqa: E402
from cosy_lite.models.object_table import ObjectTable  # noqa: E402
from cosy_lite.models.pose_net import IMAGENET_MEAN, IMAGENET_STD  # noqa: E402
from cosy_lite.models.pretrained import lite_features  # noqa: E402
from cosy_lite.train.pose_task import pose_errors  # noqa: E402


def random_rotations(n: int, seed: int = 0) -> torch.Tensor:
    q = torch.randn(n, 4, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    q = q / q.norm(dim=1, keepdim=True)
    w, x, y, z = q.unbind(1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], 1).view(n, 3, 3).float()


def ray_rotation(t: torch.Tensor) -> torch.Tensor:
    """[B,3,3] rotation taking the camera z axis onto the ray of t [B,3] (minimal rotation)."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=t.dtype).expand_as(t)
    d = t / t.norm(dim=1, keepdim=True)
    v = torch.cross(z, d, dim=1)
    c = (z * d).sum(1)
    vx = torch.zeros(t.shape[0], 3, 3, dtype=t.dtype)
    vx[:, 0, 1], vx[:, 0, 2], vx[:, 1, 0] = -v[:, 2], v[:, 1], v[:, 2]
    vx[:, 1, 2], vx[:, 2, 0], vx[:, 2, 1] = -v[:, 0], -v[:, 1], v[:, 0]
    eye = torch.eye(3, dtype=t.dtype).expand(t.shape[0], 3, 3)
    return eye + vx + vx @ vx / (1 + c)[:, None, None]


class CoarseCls(nn.Module):
    def __init__(self, n_obj: int, n_anchors: int, width: int = 512):
        super().__init__()
        self.trunk = lite_features("efficientnet_lite0", out_indices=(4,), pretrained=True)
        self.proj = nn.Linear(320, width)
        self.film = nn.Embedding(n_obj, 2 * width)
        nn.init.zeros_(self.film.weight)
        self.hidden = nn.Linear(width, width)
        self.out = nn.Linear(width, n_anchors)
        self.trans = nn.Linear(width, 3)
        nn.init.zeros_(self.trans.weight); nn.init.zeros_(self.trans.bias)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1))

    def forward(self, x, obj_rows):
        f = self.trunk((x - self.mean) / self.std)[-1]
        f = f.mean((2, 3))
        h = self.proj(f)
        g, b = self.film(obj_rows).chunk(2, dim=1)
        h = F.relu(h * (1 + g) + b)
        h = F.relu(self.hidden(h))
        return self.out(h), self.trans(h)


def jitter_boxes(box, gen, scale=0.1, shift=0.05):
    wh = box[:, 2:] - box[:, :2]
    c = (box[:, 2:] + box[:, :2]) / 2
    c = c + (torch.rand(c.shape, generator=gen) * 2 - 1) * shift * wh
    wh = wh * (1 + (torch.rand(wh.shape, generator=gen) * 2 - 1) * scale)
    return torch.cat([c - wh / 2, c + wh / 2], 1)


def prepare(b, objects, res, gen=None):
    rows = objects.index(b["obj"])
    box = b["box"].float()
    if gen is not None:
        box = jitter_boxes(box, gen)
    diam = objects.diameters[rows].float()
    TCO0 = initial_pose_from_boxes(box, b["K"].float(), diam)
    pts = objects.points[rows].float()
    cb = crop_boxes(TCO0, b["K"].float(), pts, crop_resolution=res)
    x = crop_images(b["rgb"].float() / 255, cb, res)
    Rray = ray_rotation(TCO0[:, :3, 3].double()).float()
    return x, rows, TCO0, Rray, cb


def trans_targets(TCO0, TCO, K, cb):
    t0, t = TCO0[:, :3, 3], TCO[:, :3, 3].float()
    f = K[:, 0, 0].float()
    size = (cb[:, 2] - cb[:, 0])
    dxy = (t[:, :2] / t[:, 2:] - t0[:, :2] / t0[:, 2:]) * f[:, None] / size[:, None]
    dz = torch.log(t[:, 2] / t0[:, 2])
    return torch.cat([dxy, dz[:, None]], 1)


def apply_trans(TCO0, v, K, cb):
    t0 = TCO0[:, :3, 3]
    f = K[:, 0, 0].float()
    size = (cb[:, 2] - cb[:, 0])
    xy = t0[:, :2] / t0[:, 2:] + v[:, :2] * size[:, None] / f[:, None]
    z = t0[:, 2] * torch.exp(v[:, 2])
    return torch.cat([xy * z[:, None], z[:, None]], 1)


def targets(anchors, R_allo, syms, mask, sigma):
    """soft targets [B,N]: exp(-theta^2 / 2 sigma^2), theta = angle to the closest symmetric GT."""
    cand = R_allo[:, None] @ syms[..., :3, :3]  # [B,S,3,3]
    tr = torch.einsum("nij,bsij->bns", anchors, cand)  # trace(A^T C)
    cos = ((tr - 1) / 2).clamp(-1, 1).masked_fill(~mask[:, None, :], -1.0).amax(2)
    theta = torch.arccos(cos)
    logq = -(theta ** 2) / (2 * sigma ** 2)
    return torch.softmax(logq, dim=1), theta


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--res", type=int, nargs=2, default=[144, 192])
    ap.add_argument("--anchors", type=int, default=4096)
    ap.add_argument("--sigma", type=float, default=10.0)
    ap.add_argument("--minutes", type=float, default=20)
    ap.add_argument("--bs", type=int, default=16)
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--val-every", type=int, default=150)
    ap.add_argument("--n-val", type=int, default=128)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--trans-weight", type=float, default=1.0)
    ap.add_argument("--refiner", default=None, help="refiner checkpoint: also measure coarse + 4 refiner iterations")
    ap.add_argument("--eval-only", default=None, help="net.pt to evaluate (no training)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.set_flush_denormal(True)
    torch.manual_seed(0)
    out = Path(args.out); out.mkdir(parents=True, exist_ok=True)
    root = Path("/work/main/data/ycbvsynth")
    ds, full, rgb, lab = load_split(root, "train_pbr", Path("/work/cache"))
    tr_rows, va_rows = make_split(full)
    train, val = RamBatcher(full, tr_rows, rgb, lab), RamBatcher(full, va_rows, rgb, lab)
    objects = ObjectTable.from_dataset(ds, None, 2000, 64)
    res = tuple(args.res)
    anchors = random_rotations(args.anchors)
    sigma = math.radians(args.sigma)
    net = CoarseCls(len(objects.obj_ids), args.anchors)
    g = torch.Generator().manual_seed(12345)
    vidx = torch.randperm(len(val), generator=g)[: args.n_val].numpy()
    vb = val.get(vidx)
    vx, vrows, vTCO0, vRray, vcb = prepare(vb, objects, res)

    def validate():
        net.eval()
        with torch.no_grad():
            outs = [net(vx[s:s + 32], vrows[s:s + 32]) for s in range(0, len(vx), 32)]
        logits = torch.cat([o[0] for o in outs]); tv = torch.cat([o[1] for o in outs])
        net.train()
        t_new = apply_trans(vTCO0, tv, vb["K"], vcb)
        Rray = ray_rotation(t_new.double()).float()
        R = Rray @ anchors[logits.argmax(1)]
        TCO = vTCO0.clone()
        TCO[:, :3, :3] = R
        TCO[:, :3, 3] = t_new
        e = pose_errors(TCO, vb["TCO"], objects.points[vrows], objects.symmetries[vrows], objects.sym_mask[vrows])
        dd = objects.diameters[vrows]
        rot = e.rot_deg if hasattr(e, "rot_deg") else e[0]
        o = e.summary(dd, "coarse/")
        o["coarse/rot_lt15"] = float((rot < 15).float().mean())
        o["coarse/rot_lt30"] = float((rot < 30).float().mean())
        return o, TCO

    def refine(TCO):
        from cosy_lite.model_files.loaders import load_pose_model
        from cosy_lite.models.render_and_compare import iterate_poses
        from cosy_lite.render.renderer import PyrenderRenderer

        model = load_pose_model(args.refiner, "refiner")
        renderer = PyrenderRenderer.from_dataset(ds, shading=model.render_shading)
        with torch.no_grad():
            poses = iterate_poses(model.net, vb["rgb"].float() / 255, vb["K"].float(), TCO.float(), vb["obj"].tolist(),
                                  objects.points[vrows].float(), renderer, 4, model.crop_resolution, output=model.output)
        o = {}
        for k in (0, 3):
            e = pose_errors(poses[k], vb["TCO"], objects.points[vrows], objects.symmetries[vrows], objects.sym_mask[vrows])
            o.update(e.summary(objects.diameters[vrows], f"refined_it{k + 1}/"))
        return o

    if args.eval_only:
        net.load_state_dict(torch.load(args.eval_only, weights_only=True))
        v, TCO = validate()
        if args.refiner:
            v.update(refine(TCO))
        print(json.dumps(v, indent=1))
        (out / "eval.json").write_text(json.dumps(v, indent=1))
        return

    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    log = open(out / "log.jsonl", "w")
    json.dump(vars(args), open(out / "args.json", "w"))
    t0 = time.perf_counter()
    v, _ = validate()
    log.write(json.dumps({"type": "val", "step": 0, "crops": 0, "t": 0, **v}) + "\n"); log.flush()
    print(0, {k: round(x, 3) for k, x in v.items() if "median" in k or "lt" in k or "mssd" in k}, flush=True)
    step, crops, sums = 0, 0, {"loss": 0.0, "theta_top": 0.0}
    gen = torch.Generator().manual_seed(1)
    t_train = 0.0
    while t_train < args.minutes * 60:
        ts = time.perf_counter()
        idx = torch.randint(len(train), (args.bs,), generator=gen).numpy()
        b = train.get(idx)
        x, rows, TCO0, Rray, cb = prepare(b, objects, res, gen)
        Rray = ray_rotation(b["TCO"][:, :3, 3].double()).float()  # allocentric about the GT ray
        R_allo = Rray.transpose(1, 2) @ b["TCO"][:, :3, :3].float()
        vt = trans_targets(TCO0, b["TCO"], b["K"], cb)
        q, theta = targets(anchors, R_allo, objects.symmetries[rows].float(), objects.sym_mask[rows], sigma)
        warm = min(1.0, (step + 1) / 50)
        for pg in opt.param_groups:
            pg["lr"] = args.lr * warm
        logits, tv = net(x, rows)
        l_rot = -(q * F.log_softmax(logits, 1)).sum(1).mean()
        l_t = (tv - vt).abs().sum(1).mean()
        loss = l_rot + args.trans_weight * l_t
        sums["l_t"] = sums.get("l_t", 0.0) + float(l_t)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1; crops += args.bs
        t_train += time.perf_counter() - ts
        sums["loss"] += float(loss.detach())
        sums["theta_top"] += float(theta.gather(1, logits.argmax(1, keepdim=True)).mean())
        if step % 20 == 0:
            rec = {"type": "train", "step": step, "crops": crops, "t": t_train, **{k: x / 20 for k, x in sums.items()}}
            log.write(json.dumps(rec) + "\n"); log.flush()
            sums = {k: 0.0 for k in sums}
        if step % args.val_every == 0:
            v, _ = validate()
            log.write(json.dumps({"type": "val", "step": step, "crops": crops, "t": t_train, **v}) + "\n"); log.flush()
            print(step, crops, round(t_train), {k: round(x, 3) for k, x in v.items() if "median" in k or "lt" in k or "mssd" in k}, flush=True)
            torch.save(net.state_dict(), out / "net.pt")
    v, TCO = validate()
    if args.refiner:
        v.update(refine(TCO))
    log.write(json.dumps({"type": "val", "step": step, "crops": crops, "t": t_train, "final": True, **v}) + "\n")
    print("final", step, crops, {k: round(x, 3) for k, x in v.items() if "median" in k or "lt" in k or "mssd" in k}, flush=True)
    torch.save(net.state_dict(), out / "net.pt")


if __name__ == "__main__":
    main()
