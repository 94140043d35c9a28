"""Pose networks on held-out images (the test split, never trained on): what issue 4 asks.

1. Refiner from GT + noise (15 deg per axis, (1, 1, 5) cm; seeded): median rotation / translation
   error before and after 1..N iterations, and the ratio.
2. Coarse from the GT visible boxes (what a perfect detector gives) -> N refiner iterations:
   MSSD recall at 10% of the diameter (BOP's MSSD: models_eval vertices, the toolkit's symmetry set).
Also crops/s of the render-and-compare iteration (crop + render + network forward).

    python bench/bench_pose.py --coarse runs/ycbvsynth-coarse/checkpoint.pt \
        --refiner runs/ycbvsynth-refiner/checkpoint.pt [--dataset data/ycbvsynth] [--max-instances 400]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from cosy_lite.inference.settings import InferenceConfig


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, default=Path("data/ycbvsynth"))
    ap.add_argument("--split", default="test")
    ap.add_argument("--coarse", type=Path, default=None)
    ap.add_argument("--refiner", type=Path, required=True)
    ap.add_argument("--iterations", type=int, default=InferenceConfig.n_refiner_iterations)
    ap.add_argument("--max-instances", type=int, default=400)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.data.pose_dataset import PoseDataset
    from cosy_lite.eval.pose_errors import mssd
    from cosy_lite.geometry.symmetries import symmetry_transforms
    from cosy_lite.nets.initial_pose import add_pose_noise, initial_pose_from_boxes
    from cosy_lite.nets.object_table import ObjectTable
    from cosy_lite.nets.render_and_compare import iterate_poses
    from cosy_lite.render.renderer import GlRenderer
    from cosy_lite.structures import PoseBatch
    from cosy_lite.train.pose_task import pose_errors
    from cosy_lite.weights.checkpoint import load_checkpoint
    from cosy_lite.weights.pose_nets import build_pose_net

    ds = BopDataset(args.dataset)
    def load(path, kind):
        ck = load_checkpoint(path, kind=kind)
        net = build_pose_net(ck.meta["net"], kind, load_weights=False)
        net.load_state_dict(ck.model)
        return net.eval(), ck

    refiner, ck_ref = load(args.refiner, "refiner")
    res = tuple(ck_ref.meta["net"]["crop_resolution"])
    objects = ObjectTable.from_dataset(ds, sorted(set(ck_ref.meta["obj_ids"]) & set(ds.models_info)))  # those the dataset has
    items = PoseDataset(ds, args.split, obj_ids=objects.obj_ids, min_visib_fract=0.1)
    g = torch.Generator().manual_seed(args.seed)
    idx = torch.randperm(len(items), generator=g)[: args.max_instances].tolist()
    batch = PoseBatch.collate([items[i] for i in idx])
    rows = objects.index(batch.obj_ids)
    points, syms, mask, diam = objects.points[rows], objects.symmetries[rows], objects.sym_mask[rows], objects.diameters[rows]
    images = batch.rgb.float() / 255.0
    obj_ids = batch.obj_ids.tolist()
    renderer = GlRenderer.from_dataset(ds)
    print(f"{len(idx)} instances of {args.split} ({len(set(zip(batch.scene_ids.tolist(), batch.im_ids.tolist())))} images), "
          f"crops {res}, backbone {ck_ref.meta['net']['backbone']}, refiner step {ck_ref.step}")

    def run(net, TCO_init, n):
        t = time.perf_counter()
        with torch.no_grad():
            poses = iterate_poses(net, images, batch.K, TCO_init, obj_ids, points, renderer, n, res)
        return poses, len(idx) * n / (time.perf_counter() - t)

    TCO_noisy = add_pose_noise(batch.TCO.double(), generator=g).float()
    poses, crops_per_s = run(refiner, TCO_noisy, args.iterations)
    rows_out = [("GT+noise", pose_errors(TCO_noisy, batch.TCO, points, syms, mask))]
    rows_out += [(f"refiner x{i + 1}", pose_errors(p, batch.TCO, points, syms, mask)) for i, p in enumerate(poses)]
    print(f"\n1. refiner from GT + noise ({crops_per_s:.1f} crops/s)")
    print(f"{'poses':14s} {'rot err median (deg)':>22s} {'trans err median (cm)':>22s}")
    for name, e in rows_out:
        print(f"{name:14s} {float(e.rot_deg.median()):22.2f} {100 * float(e.trans_m.median()):22.2f}")
    r0, rN = rows_out[0][1], rows_out[-1][1]
    print(f"ratio after {args.iterations}: rotation {float(rN.rot_deg.median() / r0.rot_deg.median()):.3f}, "
          f"translation {float(rN.trans_m.median() / r0.trans_m.median()):.3f}")

    if args.coarse is not None:
        coarse, ck_c = load(args.coarse, "coarse")
        res_c = tuple(ck_c.meta["net"]["crop_resolution"])
        TCO_box = initial_pose_from_boxes(batch.bboxes.double(), batch.K.double(), diam.double()).float()
        with torch.no_grad():
            TCO_coarse = iterate_poses(coarse, images, batch.K, TCO_box, obj_ids, points, renderer, 1, res_c)[0]
        refined, _ = run(refiner, TCO_coarse, args.iterations)
        infos = ds.models_info
        eval_pts, eval_syms = {}, {}
        for o in set(obj_ids):
            eval_pts[o] = np.asarray(ds.load_model(o, eval=True).vertices)
            eval_syms[o] = symmetry_transforms(infos[o])

        def recall(TCO):
            errs = [mssd(TCO[i].double().numpy(), batch.TCO[i].double().numpy(), eval_pts[o], eval_syms[o])
                    for i, o in enumerate(obj_ids)]
            return float(np.mean(np.array(errs) < 0.1 * diam.numpy()))

        print("\n2. coarse from GT visible boxes, then the refiner: MSSD recall at 0.1 diameter")
        stages = [("box init", TCO_box), ("coarse", TCO_coarse)] + [(f"+ refiner x{i + 1}", p) for i, p in enumerate(refined)]
        for name, T in stages:
            print(f"{name:16s} {recall(T):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
