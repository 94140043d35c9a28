"""Scratch: refiner = dense flow (feature correlation) + Gauss-Newton PnP, held-out measure and training."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

sys.path.insert(0, str(Path(__file__).parent))
from ramdata import RamBatcher, load_split, make_split  # noqa: E402
from nets import lite0_trunk  # noqa: E402

from cosy_lite.geometry.crops import crop_boxes, crop_images, crop_intrinsics  # noqa: E402
from cosy_lite.models.initial_pose import add_pose_noise  # noqa: E402
from cosy_lite.models.object_table import ObjectTable  # noqa: E402
from cosy_lite.models.pose_net import IMAGENET_MEAN, IMAGENET_STD  # noqa: E402
from cosy_lite.render.renderer import PyrenderRenderer  # noqa: E402
from cosy_lite.train.pose_task import pose_errors  # noqa: E402


def local_corr(a, b, r):
    """a, b [B,C,H,W] -> [B,(2r+1)^2,H,W] dot a(p).b(p+d), row-major (dy, dx)."""
    B, C, H, W = a.shape
    bp = F.pad(b, (r, r, r, r))
    n = 2 * r + 1
    return torch.stack([(a * bp[:, :, dy:dy + H, dx:dx + W]).sum(1) for dy in range(n) for dx in range(n)], 1)


class FlowNet(nn.Module):
    """crop + rendering -> descriptors (stride s) -> correlation over +-r cells -> (flow px [B,2,h,w], cost logits)."""

    def __init__(self, radius=4, level=2, adapter=0, temp=0.05, pretrained=True, glob=False):
        super().__init__()
        self.trunk = lite0_trunk(pretrained, out_indices=(level, level + 1) if adapter else (level,))
        self.stride = self.trunk.feature_info.reduction()[0]
        c = sum(self.trunk.feature_info.channels())
        self.adapter = None
        if adapter:
            self.adapter = nn.Sequential(nn.Conv2d(c, 2 * adapter, 3, 1, 1), nn.BatchNorm2d(2 * adapter), nn.ReLU(inplace=True),
                                         nn.Conv2d(2 * adapter, adapter, 3, 1, 1), nn.BatchNorm2d(adapter), nn.ReLU(inplace=True),
                                         nn.Conv2d(adapter, adapter, 1))
        self.glob = glob
        self.radius = radius
        self.dustbin = None
        self.log_temp = nn.Parameter(torch.tensor(float(np.log(temp))))
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, images):
        B = images.shape[0]
        x = (torch.cat([images[:, :3], images[:, 3:]], 0) - self.mean) / self.std
        fs = self.trunk(x)
        f = fs[0]
        if self.adapter is not None:
            f = self.adapter(torch.cat([f, F.interpolate(fs[1], size=f.shape[-2:], mode="bilinear", align_corners=False)], 1))
        f = F.normalize(f, dim=1)
        if self.glob:
            a, b = f[B:], f[:B]
            C, h, w = a.shape[1:]
            logits = torch.einsum("bcn,bcm->bmn", b.flatten(2), a.flatten(2)).reshape(B, h * w, h, w) / self.log_temp.exp()
            p = logits.softmax(1)
            ys, xs = torch.meshgrid(torch.arange(h, dtype=p.dtype), torch.arange(w, dtype=p.dtype), indexing="ij")
            ex = (p * xs.reshape(1, -1, 1, 1)).sum(1); ey = (p * ys.reshape(1, -1, 1, 1)).sum(1)
            flow = torch.stack([ex - xs, ey - ys], 1) * self.stride
            return flow, p.max(1).values, logits
        logits = local_corr(f[B:], f[:B], self.radius) / self.log_temp.exp()  # rendering cell -> image cells
        n = 2 * self.radius + 1
        if self.dustbin is not None:
            logits = torch.cat([logits, self.dustbin.expand(B, 1, *logits.shape[2:])], 1)
            pf = logits.softmax(1)
            conf = pf[:, :-1].max(1).values
            p = pf[:, :-1] / pf[:, :-1].sum(1, keepdim=True)
            d = torch.arange(n, dtype=p.dtype) - self.radius
            dy = (p.view(B, n, n, *p.shape[2:]).sum(2) * d.view(1, n, 1, 1)).sum(1)
            dx = (p.view(B, n, n, *p.shape[2:]).sum(1) * d.view(1, n, 1, 1)).sum(1)
            return torch.stack([dx, dy], 1) * self.stride, conf, logits
        p = logits.softmax(1)
        d = torch.arange(n, dtype=p.dtype) - self.radius
        k = getattr(self, "local_k", 0)
        if k:
            conf = p.max(1).values
            am = p.argmax(1)
            ay, ax = am // n, am % n
            yy = torch.arange(n).view(1, n, 1, 1, 1); xx = torch.arange(n).view(1, 1, n, 1, 1)
            win = ((yy - ay[:, None, None]).abs() <= k) & ((xx - ax[:, None, None]).abs() <= k)
            q = p.view(B, n, n, *p.shape[2:]) * win
            q = q / q.sum((1, 2), keepdim=True)
            dy = (q.sum(2) * d.view(1, n, 1, 1)).sum(1); dx = (q.sum(1) * d.view(1, n, 1, 1)).sum(1)
            return torch.stack([dx, dy], 1) * self.stride, conf, logits
        dy = (p.view(B, n, n, *p.shape[2:]).sum(2) * d.view(1, n, 1, 1)).sum(1)
        dx = (p.view(B, n, n, *p.shape[2:]).sum(1) * d.view(1, n, 1, 1)).sum(1)
        flow = torch.stack([dx, dy], 1) * self.stride
        conf = p.max(1).values
        return flow, conf, logits


def cell_points(depth, K_crop, s):
    """depth [B,1,H,W] -> cell centres uv [h,w,2] and depth at them [B,h,w]."""
    d = depth[:, 0, s // 2::s, s // 2::s].double()
    h, w = d.shape[1:]
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64) * s + s / 2, torch.arange(w, dtype=torch.float64) * s + s / 2, indexing="ij")
    return torch.stack([u, v], -1), d


def backproject(uv, d, K_crop):
    uv1 = torch.cat([uv, torch.ones_like(uv[..., :1])], -1)
    Kinv = torch.linalg.inv(K_crop.double())
    return torch.einsum("bij,hwj->bhwi", Kinv, uv1) * d[..., None]


def gt_flow(uv, X, TCO_in, TCO_gt, K_crop):
    T = TCO_gt.double() @ torch.linalg.inv(TCO_in.double())
    Y = torch.einsum("bij,bhwj->bhwi", T[:, :3, :3], X) + T[:, None, None, :3, 3]
    p = torch.einsum("bij,bhwj->bhwi", K_crop.double(), Y)
    return p[..., :2] / p[..., 2:3].clamp(min=1e-6) - uv


def skew(w):
    O = torch.zeros_like(w[..., 0])
    return torch.stack([torch.stack([O, -w[..., 2], w[..., 1]], -1), torch.stack([w[..., 2], O, -w[..., 0]], -1),
                        torch.stack([-w[..., 1], w[..., 0], O], -1)], -2)


def so3_exp(w):
    th = w.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    k = skew(w / th)
    th = th[..., None]
    I = torch.eye(3, dtype=w.dtype).expand(k.shape)
    return I + th.sin() * k + (1 - th.cos()) * (k @ k)


def solve_pose(TCO, K_crop, X_cam, target, w, iters=10, huber=2.0, damping=1e-3):
    """Weighted Gauss-Newton: T = [exp(w_r) | t + dt] about object origin; X_cam [B,N,3] points at TCO, target [B,N,2] px."""
    TCO = TCO.double()
    R0, t0 = TCO[:, :3, :3], TCO[:, :3, 3]
    Xo = X_cam - t0[:, None]  # object-origin-centred, camera-aligned
    B = TCO.shape[0]
    dR = torch.eye(3, dtype=torch.float64).repeat(B, 1, 1)
    t = t0.clone()
    fx, fy, cx, cy = K_crop[:, 0, 0, None].double(), K_crop[:, 1, 1, None].double(), K_crop[:, 0, 2, None].double(), K_crop[:, 1, 2, None].double()
    for _ in range(iters):
        Y = torch.einsum("bij,bnj->bni", dR, Xo) + t[:, None]
        z = Y[..., 2].clamp(min=1e-3)
        u = fx * Y[..., 0] / z + cx
        v = fy * Y[..., 1] / z + cy
        r = torch.stack([u, v], -1) - target  # [B,N,2]
        # Jacobian of (u,v) wrt Y
        Ju = torch.stack([fx / z, torch.zeros_like(z), -fx * Y[..., 0] / z ** 2], -1)
        Jv = torch.stack([torch.zeros_like(z), fy / z, -fy * Y[..., 1] / z ** 2], -1)
        JY = torch.stack([Ju, Jv], -2)  # [B,N,2,3]
        P = Y - t[:, None]  # rotated centred point; dY/dw = -[P]x ; dY/dt = I
        J = torch.cat([-JY @ skew(P), JY], -1)  # [B,N,2,6]
        e = r.norm(dim=-1)
        hw = torch.where(e < huber, torch.ones_like(e), huber / e.clamp(min=1e-9)) * w
        H = torch.einsum("bnki,bn,bnkj->bij", J, hw, J)
        g = torch.einsum("bnki,bn,bnk->bi", J, hw, r)
        H = H + damping * torch.diag_embed(H.diagonal(dim1=1, dim2=2)) + 1e-9 * torch.eye(6, dtype=H.dtype)
        dx = -torch.linalg.solve(H, g)
        dR = so3_exp(dx[:, :3]) @ dR
        t = t + dx[:, 3:]
    top = torch.cat([dR @ R0, t[:, :, None]], 2)
    bottom = torch.tensor([0, 0, 0, 1.0], dtype=top.dtype).expand(len(top), 1, 4)
    return torch.cat([top, bottom], 1)


def refine_step(net, images, K, TCO, obj_ids, points, renderer, res, min_conf=0.0):
    boxes = crop_boxes(TCO, K, points, crop_resolution=res)
    crops = crop_images(images, boxes, res)
    K_crop = crop_intrinsics(K, boxes, res)
    rgb, depth = renderer.render_tensors(obj_ids, TCO.double().numpy(), K_crop.double().numpy(), res)
    flow, conf, _ = net(torch.cat([crops, rgb.float()], 1))
    uv, d = cell_points(depth, K_crop, net.stride)
    X = backproject(uv, d, K_crop)
    valid = (d > 0) & (conf.double() > min_conf)
    k = getattr(net, "erode", 0)
    if k:
        occ = (d > 0).double()[:, None]
        valid = valid & ((-F.max_pool2d(-F.pad(occ, (k, k, k, k), value=0.0), 2 * k + 1, 1))[:, 0] > 0.5)
    w = valid.double() * conf.double()
    target = uv[None] + flow.permute(0, 2, 3, 1).double()
    B = len(TCO)
    new = solve_pose(TCO, K_crop, X.reshape(B, -1, 3), target.reshape(B, -1, 2), w.reshape(B, -1))
    ok = valid.reshape(B, -1).sum(1) >= 6
    return torch.where(ok[:, None, None], new, TCO.double()).float()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--res", type=int, nargs=2, default=[192, 256])
    ap.add_argument("--radius", type=int, default=4)
    ap.add_argument("--level", type=int, default=2)
    ap.add_argument("--adapter", type=int, default=0)
    ap.add_argument("--temp", type=float, default=0.05)
    ap.add_argument("--minutes", type=float, default=0)
    ap.add_argument("--bs", type=int, default=8)
    ap.add_argument("--lr", type=float, default=1e-4)
    ap.add_argument("--val-every", type=int, default=100)
    ap.add_argument("--n-val", type=int, default=128)
    ap.add_argument("--iters", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rot", type=float, default=15.0)
    ap.add_argument("--trans", type=float, nargs=3, default=[0.01, 0.01, 0.05])
    ap.add_argument("--noise-mix", action="store_true")
    ap.add_argument("--aug", action="store_true")
    ap.add_argument("--glob", action="store_true")
    ap.add_argument("--dustbin", action="store_true")
    ap.add_argument("--pose-weight", type=float, default=0.0)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.set_flush_denormal(True)
    torch.manual_seed(0)
    out = Path(args.out); out.mkdir(parents=True, exist_ok=True)
    root = Path("/work/main/data/ycbv-synth")
    ds, full, rgb, lab = load_split(root, "train_pbr", Path("/work/cache"))
    tr_rows, va_rows = make_split(full)
    train, val = RamBatcher(full, tr_rows, rgb, lab), RamBatcher(full, va_rows, rgb, lab)
    objects = ObjectTable.from_dataset(ds, None, 2000, 64)
    renderer = PyrenderRenderer.from_dataset(ds, shading="headlight")
    res = tuple(args.res)
    net = FlowNet(args.radius, args.level, args.adapter, args.temp, glob=args.glob)
    if args.dustbin:
        net.dustbin = nn.Parameter(torch.tensor(0.0))
    g = torch.Generator().manual_seed(12345)
    vidx = torch.randperm(len(val), generator=g)[: args.n_val].numpy()
    vb = val.get(vidx)
    vrows = objects.index(vb["obj"])
    vpoints = objects.points[vrows]
    vTCO_in = add_pose_noise(vb["TCO"].double(), args.rot, tuple(args.trans), generator=g).float()
    vimages = vb["rgb"].float() / 255

    def validate():
        net.eval()
        syms, m = objects.symmetries[vrows], objects.sym_mask[vrows]
        dd = objects.diameters[vrows]
        o = pose_errors(vTCO_in, vb["TCO"], vpoints, syms, m).summary(dd, "init/")
        TCO = vTCO_in
        with torch.no_grad():
            for k in range(args.iters):
                parts = []
                for s in range(0, len(TCO), 32):
                    sl = slice(s, s + 32)
                    parts.append(refine_step(net, vimages[sl], vb["K"][sl], TCO[sl], vb["obj"][sl].tolist(), vpoints[sl], renderer, res))
                TCO = torch.cat(parts)
                if k == 0:
                    o.update(pose_errors(TCO, vb["TCO"], vpoints, syms, m).summary(dd, "it1/"))
        o.update(pose_errors(TCO, vb["TCO"], vpoints, syms, m).summary(dd, "itN/"))
        net.train()
        return o

    log = open(out / "log.jsonl", "w")
    json.dump(vars(args), open(out / "args.json", "w"))
    t0 = time.perf_counter()
    v = validate()
    tv0 = time.perf_counter() - t0
    keys = [k for k in v if "median" in k or "mssd" in k]
    print(f"step 0 val {tv0:.0f}s " + " ".join(f"{k}={v[k]:.3g}" for k in keys), flush=True)
    log.write(json.dumps({"type": "val", "step": 0, "crops": 0, "t": 0, **v}) + "\n"); log.flush()
    if args.minutes <= 0:
        return
    params = [p for p in net.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=args.lr)
    rng = np.random.default_rng(0)
    step, crops, tval, sums = 0, 0, 0.0, {}
    t0 = time.perf_counter()
    n = 2 * args.radius + 1
    while time.perf_counter() - t0 - tval < 60 * args.minutes:
        idx = rng.integers(0, len(train), args.bs)
        b = train.get(idx)
        rows = objects.index(b["obj"])
        pts = objects.points[rows]
        images = b["rgb"].float() / 255
        scale = torch.rand(args.bs, dtype=torch.float64) if args.noise_mix else None
        TCO_in = add_pose_noise(b["TCO"].double(), args.rot, tuple(args.trans), scale=scale).float()
        boxes = crop_boxes(TCO_in, b["K"], pts, crop_resolution=res)
        crop_rgb = crop_images(images, boxes, res)
        labc = crop_images(b["lab"][:, None].float(), boxes, res, mode="nearest")[:, 0]
        K_crop = crop_intrinsics(b["K"], boxes, res)
        rr, depth = renderer.render_tensors(b["obj"].tolist(), TCO_in.double().numpy(), K_crop.double().numpy(), res)
        flow, conf, logits = net(torch.cat([crop_rgb, rr.float()], 1))
        uv, d = cell_points(depth, K_crop, net.stride)
        X = backproject(uv, d, K_crop)
        fgt = gt_flow(uv, X, TCO_in, b["TCO"], K_crop)  # [B,h,w,2] px
        # visible in the real crop: label at the target location is this instance
        tgt = uv[None] + fgt
        ui = tgt[..., 0].floor().long().clamp(0, res[1] - 1); vi = tgt[..., 1].floor().long().clamp(0, res[0] - 1)
        inside = (tgt[..., 0] >= 0) & (tgt[..., 0] < res[1]) & (tgt[..., 1] >= 0) & (tgt[..., 1] < res[0])
        labv = torch.gather(labc.flatten(1), 1, (vi * res[1] + ui).flatten(1)).view_as(ui)
        vis = (d > 0) & inside & (labv == (b["gt"][:, None, None] + 1).float())
        # soft target over the cost volume: bilinear weights at the GT displacement (cells)
        hh, ww = d.shape[1:]
        if args.glob:
            c = (uv[None] + fgt) / net.stride - 0.5  # image cell coords
            n = ww
            inwin = (c[..., 0] >= 0) & (c[..., 0] <= ww - 1) & (c[..., 1] >= 0) & (c[..., 1] <= hh - 1)
            xmax, ymax = ww - 2, hh - 2
        else:
            c = fgt / net.stride + args.radius  # [B,h,w,2] in window coords
            inwin = (c >= 0).all(-1) & (c <= 2 * args.radius).all(-1)
            xmax = ymax = 2 * args.radius - 1
        m = (vis & inwin).float()
        x0 = c[..., 0].floor().clamp(0, xmax); y0 = c[..., 1].floor().clamp(0, ymax)
        fx_, fy_ = (c[..., 0] - x0).clamp(0, 1), (c[..., 1] - y0).clamp(0, 1)
        logp = logits.log_softmax(1).double()  # [B,n*n,h,w]
        def lp(yy, xx):
            k = (yy * n + xx).long()
            return torch.gather(logp, 1, k[:, None]).squeeze(1)
        ce = -((1 - fx_) * (1 - fy_) * lp(y0, x0) + fx_ * (1 - fy_) * lp(y0, x0 + 1) + (1 - fx_) * fy_ * lp(y0 + 1, x0) + fx_ * fy_ * lp(y0 + 1, x0 + 1))
        if args.dustbin:
            occ = ((d > 0) & ~(vis & inwin)).double()
            ce_dust = -logp[:, -1]
            loss = ((ce * m).sum() + (ce_dust * occ).sum()) / (m.sum() + occ.sum()).clamp(min=1)
        else:
            loss = (ce * m).sum() / m.sum().clamp(min=1)
        epe = ((flow.permute(0, 2, 3, 1).double() - fgt).norm(dim=-1) * m).sum() / m.sum().clamp(min=1)
        if args.pose_weight > 0:
            from cosy_lite.models.losses import disentangled_loss
            from cosy_lite.models.pose_update import pose_update_targets
            Bq = len(TCO_in)
            wq = ((d > 0).double() * conf.double()).reshape(Bq, -1)
            tq = (uv[None] + flow.permute(0, 2, 3, 1).double()).reshape(Bq, -1, 2)
            newp = solve_pose(TCO_in.double(), K_crop, X.reshape(Bq, -1, 3), tq, wq, iters=5)
            delta = pose_update_targets(TCO_in.double(), newp, K_crop.double())
            syms, sm = objects.symmetries[rows], objects.sym_mask[rows]
            terms = disentangled_loss(TCO_in, K_crop, delta.float(), b["TCO"], pts, syms, sm)
            ptot = terms.total
            if torch.isfinite(ptot):
                loss = loss + args.pose_weight * ptot.double()
            sums["pose"] = sums.get("pose", 0) + float(ptot.detach())
        opt.zero_grad(set_to_none=True)
        loss.float().backward()
        opt.step()
        step += 1; crops += args.bs
        sums["ce"] = sums.get("ce", 0) + float(loss.detach()); sums["epe"] = sums.get("epe", 0) + float(epe); sums["frac"] = sums.get("frac", 0) + float(m.sum() / (d > 0).sum().clamp(min=1))
        sums["epe0"] = sums.get("epe0", 0) + float((fgt.norm(dim=-1) * m).sum() / m.sum().clamp(min=1))
        if step % 20 == 0:
            el = time.perf_counter() - t0 - tval
            rec = {"type": "train", "step": step, "crops": crops, "t": el, **{k: x / 20 for k, x in sums.items()}, "temp": float(net.log_temp.exp())}
            log.write(json.dumps(rec) + "\n"); log.flush(); sums = {}
        if step % args.val_every == 0:
            tv = time.perf_counter()
            v = validate()
            tval += time.perf_counter() - tv
            el = time.perf_counter() - t0 - tval
            log.write(json.dumps({"type": "val", "step": step, "crops": crops, "t": el, **v}) + "\n"); log.flush()
            torch.save(net.state_dict(), out / "net.pt")
            print(f"step {step} crops {crops} t {el:.0f}s {crops/el:.1f}c/s ce {rec['ce']:.3f} epe {rec['epe']:.2f} " + " ".join(f"{k}={v[k]:.3g}" for k in keys), flush=True)
    v = validate()
    log.write(json.dumps({"type": "val", "step": step, "crops": crops, "t": time.perf_counter() - t0 - tval, "final": True, **v}) + "\n")
    print("final", step, crops, json.dumps(v), flush=True)
    torch.save(net.state_dict(), out / "net.pt")


if __name__ == "__main__":
    main()
