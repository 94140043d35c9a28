"""The refiner/coarse learning-curve harness of 2026-12-01, kept as it ran (paths of the development
machine: data/ycbv-synth under /work/main, an image cache in /work/cache). It uses the package's
crops, renderer, loss and validation errors; images held in memory (ramdata.py); network variants in
nets.py (the one kept is cosy_lite.models.siamese_pose_net.SiamesePoseNet). The args.json of each
run folder is its command line: python train_exp.py --out RUN [--shading headlight] [--noise-mix] ...
The package's own training path for the recipe is `python train.py --model refiner` (demo profile)."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from ramdata import RamBatcher, load_split, make_split  # noqa: E402

from cosy_lite.data.augmentation import AugmentationConfig, StrongAugmentation  # noqa: E402
from cosy_lite.geometry.crops import crop_images  # noqa: E402
from cosy_lite.models.initial_pose import add_pose_noise, initial_pose_from_boxes  # noqa: E402
from cosy_lite.models.losses import disentangled_loss  # noqa: E402
from cosy_lite.models.object_table import ObjectTable  # noqa: E402
from cosy_lite.models.render_and_compare import iterate_poses, make_inputs  # noqa: E402
from cosy_lite.render.renderer import PyrenderRenderer  # noqa: E402
from cosy_lite.train.pose_task import pose_errors  # noqa: E402


def flow_targets(renderer, obj_ids, TCO_in, TCO_gt, K_crop, res, size):
    """GT 2D displacement [B,2,h,w] (crop px) of each rendered pixel (at stride) and its mask [B,h,w]."""
    _, depth = renderer.render_tensors(obj_ids, TCO_in.double().numpy(), K_crop.double().numpy(), res, depth_only=True)
    h, w = size
    s = res[0] // h
    d = depth[:, 0, s // 2::s, s // 2::s][:, :h, :w].double()  # [B,h,w] sample at cell centres
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64) * s + s / 2, torch.arange(w, dtype=torch.float64) * s + s / 2,
                          indexing="ij")
    uv1 = torch.stack([u, v, torch.ones_like(u)], -1)  # [h,w,3]
    Kinv = torch.linalg.inv(K_crop.double())
    X = torch.einsum("bij,hwj->bhwi", Kinv, uv1) * d[..., None]  # camera (input pose)
    T = TCO_gt.double() @ torch.linalg.inv(TCO_in.double())
    Y = torch.einsum("bij,bhwj->bhwi", T[:, :3, :3], X) + T[:, None, None, :3, 3]
    p = torch.einsum("bij,bhwj->bhwi", K_crop.double(), Y)
    uv2 = p[..., :2] / p[..., 2:3].clamp(min=1e-6)
    flow = (uv2 - uv1[..., :2]).permute(0, 3, 1, 2).float()
    return flow, (d > 0).float()


def build(args, width):
    if args.net == "r18":
        from cosy_lite.models.pose_net import PoseNet
        return PoseNet("resnet18", 6, output_scale=tuple(args.scale), crop_width=width)
    from nets import SiamLite
    return SiamLite(width, tuple(args.scale), pretrained=not args.scratch, corr_r=args.corr, keypoints=not args.nokp,
                    freeze_trunk=args.freeze, width=args.width, flat=args.flat, res=tuple(args.res))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--net", default="siam")
    ap.add_argument("--model", default="refiner")
    ap.add_argument("--out", required=True)
    ap.add_argument("--res", type=int, nargs=2, default=[96, 128])
    ap.add_argument("--bs", type=int, default=16)
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--trunk-lr", type=float, default=None)
    ap.add_argument("--minutes", type=float, default=20)
    ap.add_argument("--val-every", type=int, default=100)
    ap.add_argument("--aug", action="store_true")
    ap.add_argument("--scratch", action="store_true")
    ap.add_argument("--freeze", action="store_true")
    ap.add_argument("--nokp", action="store_true")
    ap.add_argument("--corr", type=int, default=3)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--flat", type=int, default=0)
    ap.add_argument("--shading", default="flat")
    ap.add_argument("--loss-weights", type=float, nargs=3, default=[1.0, 1.0, 1.0], help="rotation, xy, depth")
    ap.add_argument("--flow-weight", type=float, default=0.0, help="auxiliary dense-flow loss weight (m per px)")
    ap.add_argument("--noise-mix", action="store_true", help="per-sample noise scale ~ U(0,1) (training only)")
    ap.add_argument("--rot", type=float, default=15.0)
    ap.add_argument("--trans", type=float, nargs=3, default=[0.01, 0.01, 0.05])
    ap.add_argument("--scale", type=float, nargs=3, default=[0.25, 0.04, 0.06])
    ap.add_argument("--n-val", type=int, default=128)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--train-images", type=int, default=0, help="0: all")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.set_flush_denormal(True)
    torch.manual_seed(0)
    out = Path(args.out); out.mkdir(parents=True, exist_ok=True)
    root = Path("/work/main/data/ycbv-synth")
    ds, full, rgb, lab = load_split(root, "train_pbr", Path("/work/cache"))
    tr_rows, va_rows = make_split(full)
    if args.train_images:
        imgs = np.unique(full.table.image_idx[tr_rows])[: args.train_images]
        tr_rows = tr_rows[np.isin(full.table.image_idx[tr_rows], imgs)]
    train, val = RamBatcher(full, tr_rows, rgb, lab), RamBatcher(full, va_rows, rgb, lab)
    objects = ObjectTable.from_dataset(ds, None, 2000, 64)
    renderer = PyrenderRenderer.from_dataset(ds, shading=args.shading)
    res = tuple(args.res)
    aug = StrongAugmentation(AugmentationConfig()) if args.aug else None
    net = build(args, res[1])
    if args.trunk_lr is not None and hasattr(net, "trunk"):
        tp = [p for p in net.trunk.parameters() if p.requires_grad]
        ids = {id(p) for p in tp}
        rest = [p for p in net.parameters() if id(p) not in ids and p.requires_grad]
        opt = torch.optim.Adam([{"params": tp, "lr": args.trunk_lr}, {"params": rest, "lr": args.lr}])
    else:
        opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=args.lr)
    warm = 100
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: min(1.0, (s + 1) / warm))

    g = torch.Generator().manual_seed(12345)
    vidx = torch.randperm(len(val), generator=g)[: args.n_val].numpy()
    vb = val.get(vidx)
    vrows = objects.index(vb["obj"])
    vpoints = objects.points[vrows]

    def init(b, rows, gen=None, train=False):
        if args.model == "refiner":
            if train and args.noise_mix:
                out = []
                for k in range(len(b["TCO"])):
                    u = float(torch.rand(()))
                    out.append(add_pose_noise(b["TCO"][k:k+1].double(), args.rot * u, tuple(x * u for x in args.trans)))
                return torch.cat(out).float()
            return add_pose_noise(b["TCO"].double(), args.rot, tuple(args.trans), generator=gen).float()
        return initial_pose_from_boxes(b["box"].double(), b["K"].double(), objects.diameters[rows].double()).float()

    vTCO_in = init(vb, vrows, g)
    vimages = vb["rgb"].float() / 255

    def validate():
        net.eval()
        with torch.no_grad():
            poses = iterate_poses(net, vimages, vb["K"], vTCO_in, vb["obj"].tolist(), vpoints, renderer,
                                  4 if args.model == "refiner" else 1, res, batch_size=32)
        net.train()
        syms, m = objects.symmetries[vrows], objects.sym_mask[vrows]
        d = objects.diameters[vrows]
        o = pose_errors(vTCO_in, vb["TCO"], vpoints, syms, m).summary(d, "init/")
        o.update(pose_errors(poses[0], vb["TCO"], vpoints, syms, m).summary(d, "it1/"))
        o.update(pose_errors(poses[-1], vb["TCO"], vpoints, syms, m).summary(d, "itN/"))
        return o

    log = open(out / "log.jsonl", "w")
    json.dump(vars(args), open(out / "args.json", "w"))
    step, crops = 0, 0
    tval = 0.0
    tt = {"data": 0.0, "render+crop": 0.0, "net": 0.0}
    rng = np.random.default_rng(0)
    v = validate()
    print(f"step 0 crops 0 " + " ".join(f"{k}={x:.3g}" for k, x in v.items() if "median" in k or "mssd" in k), flush=True)
    log.write(json.dumps({"type": "val", "step": 0, "crops": 0, "t": 0, **v}) + "\n")
    sums = {}
    t0 = time.perf_counter()
    while time.perf_counter() - t0 - tval < 60 * args.minutes:
        ta = time.perf_counter()
        idx = rng.integers(0, len(train), args.bs)
        b = train.get(idx)
        rows = objects.index(b["obj"])
        pts, syms, sm = objects.points[rows], objects.symmetries[rows], objects.sym_mask[rows]
        images = b["rgb"].float() / 255
        masks_any = b["lab"] > 0
        TCO_in = init(b, rows, train=True)
        tb = time.perf_counter()

        def ct(crops, boxes):
            if aug is None:
                return crops
            m = crop_images(masks_any[:, None], boxes, res, mode="nearest")[:, 0]
            return aug(crops, m)

        inp = make_inputs(images, b["K"], TCO_in, b["obj"].tolist(), pts, renderer, res, crop_transform=ct)
        tc = time.perf_counter()
        if args.flow_weight > 0:
            delta, flow = net(inp.images, return_flow=True)
            ft, fm = flow_targets(renderer, b["obj"].tolist(), TCO_in, b["TCO"], inp.K_crop, res, flow.shape[-2:])
            flow_loss = ((flow - ft).abs().sum(1) * fm).sum() / fm.sum().clamp(min=1)
        else:
            delta = net(inp.images)
            flow_loss = torch.zeros(())
        terms = disentangled_loss(TCO_in, inp.K_crop, delta.float(), b["TCO"], pts, syms, sm)
        opt.zero_grad(set_to_none=True)
        wr, wx, wd = args.loss_weights
        main_loss = (wr * terms.rotation + wx * terms.xy + wd * terms.depth) if args.loss_weights != [1.0, 1.0, 1.0] else terms.total
        (main_loss + args.flow_weight * flow_loss).backward()
        sums["flow_px"] = sums.get("flow_px", 0) + float(flow_loss.detach())
        torch.nn.utils.clip_grad_norm_(net.parameters(), 10.0)
        opt.step(); sched.step()
        td = time.perf_counter()
        tt["data"] += tb - ta; tt["render+crop"] += tc - tb; tt["net"] += td - tc
        step += 1; crops += args.bs
        for k in ("total", "rotation", "xy", "depth"):
            sums[k] = sums.get(k, 0) + float(getattr(terms, k).detach())
        if step % 20 == 0:
            el = time.perf_counter() - t0 - tval
            rec = {"type": "train", "step": step, "crops": crops, "t": el, "crops_per_s": crops / el,
                   **{k: x / 20 for k, x in sums.items()}, **{f"time/{k}": x for k, x in tt.items()}}
            log.write(json.dumps(rec) + "\n"); log.flush()
            sums = {}
        if step % args.val_every == 0:
            tv = time.perf_counter()
            v = validate()
            tval += time.perf_counter() - tv
            el = time.perf_counter() - t0 - tval
            log.write(json.dumps({"type": "val", "step": step, "crops": crops, "t": el, **v}) + "\n"); log.flush()
            torch.save({"net": net.state_dict(), "opt": opt.state_dict(), "step": step}, out / "state.pt")
            print(f"step {step} crops {crops} t {el:.0f}s {crops/el:.1f}c/s loss {rec['total']:.4f} xy {rec['xy']:.4f} "
                  + " ".join(f"{k}={x:.3g}" for k, x in v.items() if k.startswith("itN") or k.startswith("it1/rot")), flush=True)
    v = validate()
    el = time.perf_counter() - t0
    log.write(json.dumps({"type": "val", "step": step, "crops": crops, "t": el, "final": True, **v}) + "\n")
    print("final", step, crops, json.dumps(v), json.dumps(tt), flush=True)
    torch.save(net.state_dict(), out / "net.pt")


if __name__ == "__main__":
    main()
