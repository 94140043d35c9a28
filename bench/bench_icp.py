"""Benchmark of the depth ICP (``cosy_lite.inference.icp``): ms per object and accuracy.

Usage: python bench/bench_icp.py [--objects 1 5] [--repeats 10] [--dataset data/ycbvsynth --images 20]

Latency: one 640x480 image (YCB-V camera) holding 5 asymmetric YCB-V objects (mustard bottle,
power drill, banana, pitcher base, large clamp; meshes from ``cosy_lite.synth.objects``, no files
needed) at 0.7-1.1 m in front of a wall, measured depth = their rendered depth + 1 mm Gaussian
noise, masks = visible pixels; starts = GT moved by 1 cm and rotated by 5 deg (random directions).
For each N in ``--objects``: :func:`refine_poses_icp` on the first N objects (one batched render
call per image), one warm-up then ``--repeats`` calls; the table gives the median and best wall
time per image, the median per object, its breakdown (median over calls of the per-object mean;
render is the per-object share of the batched call) and the errors after ICP.

``--dataset``: the same on the test split of a BOP dataset (e.g. the synthetic ``ycbvsynth``):
every GT instance with visib_fract >= 0.1 of the first ``--images`` images, its ``mask_visib``,
the dataset's depth + 1 mm noise, starts GT + 1 cm / 5 deg; acceptance rate, MSSD (BOP's
symmetry-aware maximum surface distance) before / after and the MSSD recall (AR_MSSD) before / after.
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np

OBJECTS = [5, 15, 10, 11, 19]  # mustard bottle, power drill, banana, pitcher base, large clamp
YCBV_K = np.array([[1066.778, 0.0, 312.9869], [0.0, 1067.487, 241.3109], [0.0, 0.0, 1.0]])
SIZE = (480, 640)
WALL = 99


def perturb(TCO: np.ndarray, deg: float, metres: float, rng: np.random.Generator) -> np.ndarray:
    """TCO rotated by ``deg`` about a random axis (object centre fixed) and moved by ``metres`` in a random direction."""
    from scipy.spatial.transform import Rotation

    axis, direction = (v / np.linalg.norm(v) for v in rng.normal(size=(2, 3)))
    out = TCO.copy()
    out[:3, :3] = Rotation.from_rotvec(np.radians(deg) * axis).as_matrix() @ TCO[:3, :3]
    out[:3, 3] += metres * direction
    return out


def errors(TCO: np.ndarray, TCO_gt: np.ndarray) -> tuple[float, float]:
    """(translation error mm, rotation error deg)."""
    from cosy_lite.inference.icp import rotation_angle_deg

    return float(np.linalg.norm(TCO[:3, 3] - TCO_gt[:3, 3]) * 1000), rotation_angle_deg(TCO[:3, :3] @ TCO_gt[:3, :3].T)


def synthetic_scene(renderer, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GT poses [5,4,4], measured depth [H,W] (m, + 1 mm noise) and visible masks [5,H,W] of the bench image."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    positions = [(-0.14, -0.08, 0.8), (0.12, -0.07, 0.9), (-0.12, 0.1, 0.7), (0.15, 0.11, 1.1), (0.0, 0.0, 1.0)]
    TCO = np.tile(np.eye(4), (len(OBJECTS), 1, 1))
    TCO[:, :3, :3] = Rotation.random(len(OBJECTS), random_state=seed).as_matrix()
    TCO[:, :3, 3] = positions
    wall = np.eye(4)
    wall[2, 3] = 1.3
    d = renderer.render([*OBJECTS, WALL], np.concatenate([TCO, wall[None]]), YCBV_K, SIZE, depth_only=True).depth
    d = np.where(d > 0, d, np.inf)
    nearest, depth = d.argmin(axis=0), d.min(axis=0)
    depth[~np.isfinite(depth)] = 0.0
    depth = (depth + rng.normal(0.0, 0.001, depth.shape) * (depth > 0)).astype(np.float32)
    masks = np.stack([(nearest == k) & np.isfinite(d[k]) for k in range(len(OBJECTS))])
    return TCO, depth, masks


def bench_latency(n_objects: list[int], repeats: int) -> list[dict]:
    import trimesh

    from cosy_lite.inference.icp import refine_poses_icp
    from cosy_lite.render.renderer import GlRenderer
    from cosy_lite.synth.objects import load_ycb_mesh

    meshes = {i: load_ycb_mesh(i) for i in OBJECTS}
    meshes[WALL] = trimesh.creation.box(extents=(3.0, 3.0, 0.01))
    renderer = GlRenderer(meshes=meshes)
    TCO_gt, depth, masks = synthetic_scene(renderer)
    rng = np.random.default_rng(1)
    rows = []
    for n in n_objects:
        starts = np.stack([perturb(T, 5.0, 0.01, rng) for T in TCO_gt[:n]])
        refine_poses_icp(starts, YCBV_K, depth, masks[:n], renderer, OBJECTS[:n])  # warm-up (open3d import, GL, uploads)
        walls, parts, results = [], [], None
        for _ in range(repeats):
            t = time.perf_counter()
            results = refine_poses_icp(starts, YCBV_K, depth, masks[:n], renderer, OBJECTS[:n])
            walls.append(time.perf_counter() - t)
            parts.append({k: np.mean([r.timings[k] for r in results]) for k in ("render", "clouds", "normals", "icp")})
        errs = np.array([errors(r.TCO, T) for r, T in zip(results, TCO_gt[:n])])
        rows.append(dict(
            n=n, wall_med=np.median(walls) * 1e3, wall_best=min(walls) * 1e3, per_obj=np.median(walls) / n * 1e3,
            **{k: np.median([p[k] for p in parts]) * 1e3 for k in parts[0]},
            accepted=sum(r.accepted for r in results), t_err=errs[:, 0].max(), r_err=errs[:, 1].max(),
        ))
    renderer.close()
    return rows


def bench_dataset(root: Path, n_images: int, use_symmetries: bool, seed: int = 0) -> dict:
    """ICP from GT + 1 cm / 5 deg on the first test images of a BOP dataset: per instance MSSD (m,
    symmetry-aware, as BOP) before / after, accepted flag, seconds, rejection reasons."""
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.io import load_mask
    from cosy_lite.eval.object_errors import ObjectErrors
    from cosy_lite.geometry.symmetries import symmetry_transforms
    from cosy_lite.inference.icp import refine_poses_icp
    from cosy_lite.render.renderer import GlRenderer

    ds = BopDataset(root)
    renderer = GlRenderer.from_dataset(ds)
    rng = np.random.default_rng(seed)
    obj_errors: dict[int, ObjectErrors] = {}
    syms = {obj_id: symmetry_transforms(info) for obj_id, info in ds.models_info.items()}
    rows, reasons = [], {}
    for k, rec in enumerate(ds.images("test")):
        if k >= n_images:
            break
        keep = [i for i, info in enumerate(rec.gt_info or []) if info.visib_fract >= 0.1]
        if not keep:
            continue
        depth = ds.load_depth(rec)
        depth = (depth + rng.normal(0.0, 0.001, depth.shape) * (depth > 0)).astype(np.float32)
        masks = np.stack([load_mask(ds.mask_path("test", rec.scene_id, rec.im_id, i, visib=True)) for i in keep])
        starts = np.stack([perturb(rec.gt[i].TCO, 5.0, 0.01, rng) for i in keep])
        obj_ids = [rec.gt[i].obj_id for i in keep]
        results = refine_poses_icp(starts, rec.camera.K, depth, masks, renderer, obj_ids,
                                   symmetries=[syms[o] if use_symmetries else None for o in obj_ids])
        for i, obj_id, res, start in zip(keep, obj_ids, results, starts):
            if obj_id not in obj_errors:
                info = ds.models_info[obj_id]
                pts = np.asarray(ds.load_model(obj_id, eval=True).vertices)
                obj_errors[obj_id] = ObjectErrors.from_model(pts, symmetry_transforms(info), info.diameter)
            oe = obj_errors[obj_id]
            mssd, _ = oe.mssd_mspd(np.stack([start, res.TCO]), rec.gt[i].TCO, rec.camera.K)
            rows.append((mssd[0], mssd[1], oe.diameter, res.accepted, res.seconds, rec.gt_info[i].visib_fract))
            if not res.accepted:
                key = res.reason.split(" (")[0].split(" > ")[0].split(" < ")[0]
                key = " ".join(w for w in key.split() if not w.replace(".", "").isdigit())
                reasons[key] = reasons.get(key, 0) + 1
    renderer.close()
    before, after, diameter, acc, seconds, visib = (np.array(c) for c in zip(*rows))
    return dict(before=before, after=after, diameter=diameter, acc=acc.astype(bool), seconds=seconds,
                visib=visib, reasons=reasons)


def mssd_recall(mssd: np.ndarray, diameter: np.ndarray) -> float:
    """BOP19 MSSD recall averaged over the thresholds 0.05..0.5 x diameter."""
    return float(np.mean([(mssd < th * diameter).mean() for th in np.arange(0.05, 0.51, 0.05)]))


def main(argv: list[str] | None = None) -> None:
    from cosy_lite.render.gl import use_egl

    use_egl()
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--objects", type=int, nargs="+", default=[1, 5])
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--dataset", type=Path, default=None, help="a BOP dataset root with a test split (optional)")
    p.add_argument("--images", type=int, default=20)
    args = p.parse_args(argv)
    print(f"# {platform.processor() or platform.machine()}, {__import__('os').cpu_count()} CPUs; 640x480, YCB-V camera")
    print("| objects | ms/image (median) | ms/image (best) | ms/object | render | clouds | normals | ICP "
          "| accepted | max error after (mm / deg) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in bench_latency(args.objects, args.repeats):
        print(f"| {r['n']} | {r['wall_med']:.1f} | {r['wall_best']:.1f} | {r['per_obj']:.1f} | {r['render']:.1f} "
              f"| {r['clouds']:.1f} | {r['normals']:.1f} | {r['icp']:.1f} | {r['accepted']}/{r['n']} "
              f"| {r['t_err']:.2f} / {r['r_err']:.2f} |")
    if args.dataset is None:
        return
    print(f"\n{args.dataset} test: instances with visib_fract >= 0.1 of the first {args.images} images, "
          "start GT + 1 cm / 5 deg, depth + 1 mm noise; MSSD in mm (symmetry-aware, as BOP)")
    print("| symmetries given | instances | accepted | ms/object (median) | MSSD start (median) "
          "| MSSD after (median, 90%) | accepted only (median, 90%) | worse than start | AR_MSSD start -> after |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for use_symmetries in (False, True):
        r = bench_dataset(args.dataset, args.images, use_symmetries)
        b, a, d, acc = r["before"] * 1e3, r["after"] * 1e3, r["diameter"], r["acc"]
        print(f"| {'yes' if use_symmetries else 'no'} | {len(acc)} | {acc.mean():.1%} | {np.median(r['seconds']) * 1e3:.1f} "
              f"| {np.median(b):.1f} | {np.median(a):.2f}, {np.quantile(a, 0.9):.1f} "
              f"| {np.median(a[acc]):.2f}, {np.quantile(a[acc], 0.9):.2f} | {(a > b).sum()} "
              f"| {mssd_recall(b / 1e3, d):.3f} -> {mssd_recall(a / 1e3, d):.3f} |")
        print(f"rejections ({'with' if use_symmetries else 'without'} symmetries):", r["reasons"])


if __name__ == "__main__":
    main()
