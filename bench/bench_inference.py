"""Latency of the inference pipeline (``cosy_lite.inference.predictor``) on one 640x480 image.

Usage: python bench/bench_inference.py [--dataset data/ycbvsynth] [--objects 1 5] [--repeats 5]
       [--threads 2] [--detector CKPT] [--profiles effb3 demo] [--precisions fp32 bf16] [--no-icp]

The image: the first test image of ``--dataset`` with at least 5 instances >= 50 % visible; its
most visible 1 (or 5) instances, with their GT visible boxes and masks as detections (the
reference numbers exclude the detector) and the dataset's depth for ICP. Per profile (pose-net
backbone + crop size; untrained weights, which cost the same as trained ones), precision (fp32 or
bf16 autocast, ``--precisions``) and object count: the coarse model + 4 refiner iterations through
:meth:`Predictor.predict` (networks with BatchNorm folded, channels-last), torch backend,
``--threads`` CPU threads with OpenMP waiting passively unless ``OMP_WAIT_POLICY`` says otherwise
(spinning threads are many times slower on cores shared with other jobs). Warm-up calls first (GL
context, mesh uploads, oneDNN kernels for the batch shape), then ``--repeats`` calls, the variants
called in turn so that they share the machine's load; medians and the best call, broken down into
crops (boxes, roi_align, K_crop, pose updates), render, networks and ICP. The detector
(``--detector``, else the demo profile's detector untrained: ``configs/detector/demo.yaml``) is
timed separately on the same image.

Reference (issue 6): the public CosyPose implementation (happypose), EfficientNet-B3 at 240x320,
2 threads, without the detector, on the project machine: 0.74 s (1 object), 4.45 s (5 objects).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np

from cosy_lite.geometry.crops import CROP_RESOLUTION

PROFILES = {  # name -> (backbone, crop (h, w))
    "effb3": ("efficientnet_b3", CROP_RESOLUTION),  # CosyPose's
    "demo": ("resnet18", (96, 128)),  # configs/{coarse,refiner}/demo.yaml
}
REFERENCE_S = {1: 0.74, 5: 4.45}  # happypose CosyPose, EfficientNet-B3 240x320, this machine, no detector
STAGES = ("crops", "render", "networks", "icp")


def pick_image(ds, max_objects: int, min_visib: float = 0.5):
    """(record, indices of its ``max_objects`` most visible GT instances) of the first test image that has them."""
    for rec in ds.images("test"):
        infos = rec.gt_info or []
        order = sorted((i for i, g in enumerate(infos) if g.visib_fract >= min_visib),
                       key=lambda i: -infos[i].visib_fract)
        if len(order) >= max_objects and rec.depth_path is not None:
            return rec, order[:max_objects]
    raise SystemExit(f"{ds.root}: no test image with {max_objects} instances >= {min_visib:.0%} visible")


def oracle(ds, rec, keep: list[int]):
    import torch

    from cosy_lite.bop.detections import Detections
    from cosy_lite.bop.io import load_mask

    boxes = torch.tensor([[b[0], b[1], b[0] + b[2], b[1] + b[3]] for b in (rec.gt_info[i].bbox_visib for i in keep)],
                         dtype=torch.float32)
    masks = np.stack([load_mask(ds.mask_path("test", rec.scene_id, rec.im_id, i, visib=True)) for i in keep])
    masks = torch.from_numpy(masks)
    return Detections(boxes, torch.tensor([rec.gt[i].obj_id for i in keep]), torch.linspace(1.0, 0.5, len(keep)), masks)


def build_predictor(ds, renderer, objects, profile: str, icp: bool, precision: str):
    from cosy_lite.geometry.symmetries import symmetry_transforms
    from cosy_lite.inference.predictor import Predictor
    from cosy_lite.inference.settings import InferenceConfig
    from cosy_lite.weights.loaders import PoseModel
    from cosy_lite.weights.pose_nets import PoseNetConfig, build_pose_net

    backbone, crop = PROFILES[profile]
    models = []
    for kind in ("coarse", "refiner"):
        net = build_pose_net(PoseNetConfig(backbone=backbone, crop_resolution=list(crop))).eval()
        models.append(PoseModel(net, kind, crop, objects.obj_ids))
    syms = {i: symmetry_transforms(ds.models_info[i]) for i in objects.obj_ids} if icp else None
    return Predictor(models[0], models[1], objects, renderer, config=InferenceConfig(icp=icp, precision=precision),
                     icp_symmetries=syms)


def time_detector(ds, rgb: np.ndarray, ckpt: Path | None, repeats: int) -> tuple[float, float, int, str]:
    """(median s, best s, detections, what) of the detector on ``rgb``."""
    import torch

    from cosy_lite.nets.detector import Detector, LabelMap, detect

    if ckpt is not None:
        from cosy_lite.weights.loaders import load_detector

        model, what = load_detector(ckpt), str(ckpt)
    else:
        from cosy_lite.config import load_config, packaged_config
        from cosy_lite.train.detector_task import DetectorTrainConfig

        demo = packaged_config("detector", "demo.yaml")
        cfg = load_config(DetectorTrainConfig, demo)
        torch.manual_seed(0)
        model = Detector(LabelMap(tuple(ds.obj_ids)), cfg.detector).eval()
        what = f"{cfg.detector.name} (demo profile, untrained)"
    image = torch.from_numpy(rgb).permute(2, 0, 1).float() / 255.0
    times, n = [], 0
    for k in range(repeats + 2):
        t = time.perf_counter()
        n = len(detect(model, [image])[0])
        if k >= 2:
            times.append(time.perf_counter() - t)
    return float(np.median(times)), min(times), n, what


def ratio(seconds: float, n: int) -> str:
    return f"{seconds / REFERENCE_S[n]:.2f}x of {REFERENCE_S[n]} s" if n in REFERENCE_S else "-"


def main(argv: list[str] | None = None) -> None:
    from cosy_lite.render.gl import use_egl

    use_egl()
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--dataset", type=Path, default=Path("data/ycbvsynth"))
    p.add_argument("--objects", type=int, nargs="+", default=[1, 5])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--profiles", nargs="+", default=list(PROFILES), choices=list(PROFILES))
    p.add_argument("--precisions", nargs="+", default=["fp32", "bf16"], choices=["fp32", "bf16"])
    p.add_argument("--detector", type=Path, default=None, help="detector checkpoint (default: demo profile, untrained)")
    p.add_argument("--no-icp", action="store_true")
    args = p.parse_args(argv)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads OpenMP; see infer.py

    import torch

    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.inference import predictor as _  # noqa: F401  (torchvision before any rendering)
    from cosy_lite.nets.object_table import ObjectTable
    from cosy_lite.render.renderer import GlRenderer

    torch.set_num_threads(args.threads)
    ds = BopDataset(args.dataset)
    rec, keep = pick_image(ds, max(args.objects))
    rgb, depth = ds.load_rgb(rec), ds.load_depth(rec)
    renderer = GlRenderer.from_dataset(ds)
    objects = ObjectTable.from_dataset(ds, sorted({rec.gt[i].obj_id for i in keep}))
    load0 = os.getloadavg()
    print(f"# {platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, {args.threads} threads, "
          f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}; "
          f"{ds.name} test scene {rec.scene_id} image {rec.im_id} (640x480), "
          f"objects {[rec.gt[i].obj_id for i in keep]}")
    det_med, det_best, n_det, det_what = time_detector(ds, rgb, args.detector, args.repeats)
    print(f"# detector {det_what}: median {det_med * 1e3:.0f} ms, best {det_best * 1e3:.0f} ms ({n_det} detections)")
    print("| profile | precision | objects | pose s (median) | pose s (best) | vs reference | crops ms | render ms "
          "| networks ms | ICP ms | + ICP s | + detector + ICP s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    variants = [(p, q) for p in args.profiles for q in args.precisions]
    predictors = {v: build_predictor(ds, renderer, objects, v[0], not args.no_icp, v[1]) for v in variants}
    for n in args.objects:
        det = oracle(ds, rec, keep[:n])
        runs: dict[tuple[str, str], list[dict[str, float]]] = {v: [] for v in variants}
        for k in range(args.warmup + args.repeats):  # round-robin: every variant sees the same load
            for v, pred in predictors.items():
                est = pred.predict(rgb, rec.camera.K, None if args.no_icp else depth, detections=det)
                if k >= args.warmup:
                    runs[v].append(est.timings)
        for (profile, precision), rs in runs.items():
            med = {k: float(np.median([r[k] for r in rs])) for k in (*STAGES, "total")}
            pose = [r["crops"] + r["render"] + r["networks"] for r in rs]
            pose_med = float(np.median(pose))
            print(f"| {profile} ({PROFILES[profile][0]}, {PROFILES[profile][1][0]}x{PROFILES[profile][1][1]}) "
                  f"| {precision} | {n} "
                  f"| {pose_med:.3f} | {min(pose):.3f} | {ratio(pose_med, n)} "
                  f"| {med['crops'] * 1e3:.0f} | {med['render'] * 1e3:.0f} | {med['networks'] * 1e3:.0f} "
                  f"| {med['icp'] * 1e3:.0f} | {med['total']:.3f} | {med['total'] + det_med:.3f} |", flush=True)
    load1 = os.getloadavg()
    print(f"# load average (1, 5, 15 min) before {tuple(round(v, 2) for v in load0)}, "
          f"after {tuple(round(v, 2) for v in load1)}")
    renderer.close()


if __name__ == "__main__":
    main()
