"""onnxruntime vs torch on the CPU: pose-network forward passes and end-to-end pose latency.

Usage: python bench/bench_onnx.py [--dataset data/ycbvsynth] [--threads 2] [--repeat 10]
       [--profiles effb3 demo] [--batches 1 8] [--objects 1 5] [--no-int8] [--no-detector] [--write]

1. Pose-network forward, per profile (backbone + crop size; untrained weights, which cost the same
   as trained ones) and batch: torch eager (the plain eval module), torch as the pipeline runs it
   (BatchNorm folded, channels-last: :func:`~cosy_lite.inference.predictor.inference_net`),
   onnxruntime fp32 and, unless ``--no-int8``, the dynamically quantised int8 graph (its max
   |int8 - fp32| on the same random input is printed). Random crops in [0, 1]; denormals flushed in
   torch (as the pipeline does) and in onnxruntime (session option).
2. End to end, per profile and object count: one 640x480 image of ``--dataset`` (as
   ``bench_inference.py``: its most visible 1 or 5 objects, GT visible boxes as detections, no
   detector, no ICP), coarse + 4 refiner iterations through ``Predictor.predict`` with the torch
   networks and with the onnxruntime sessions; rendering, crops and pose updates are the same loop
   (torch) for both backends.
3. The detector (demo profile, untrained; ``--no-detector`` skips it): torch vs onnxruntime on the image.

Every variant runs ``--threads`` threads (torch: ``set_num_threads``, OpenMP waiting passively;
onnxruntime: intra-op threads, idle threads not spinning); variants are called in turn so that
they share the machine's load; medians of ``--repeat`` calls after ``--warmup``. ``--write``
appends the tables to ``bench/RESULTS.md`` with the machine, date and command.

Reference (issue 6/7): the public CosyPose implementation (happypose), EfficientNet-B3 at 240x320,
2 threads, without detection, on the project machine: 0.74 s (1 object), 4.45 s (5 objects).
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_inference (image choice, oracle detections)

from bench_inference import PROFILES, REFERENCE_S  # noqa: E402  (the same networks and reference times)

TARGET_FRACTION = 1 / 3  # issue 7: end to end at most a third of the reference
RESULTS = Path(__file__).resolve().parent / "RESULTS.md"


def _median_ms(times: list[float]) -> float:
    return 1e3 * float(np.median(times))


def _round_robin(calls: dict[str, Callable[[], object]], warmup: int, repeat: int) -> dict[str, list[float]]:
    """Seconds of each call, ``repeat`` times after ``warmup``, the calls taking turns."""
    times: dict[str, list[float]] = {k: [] for k in calls}
    for k in range(warmup + repeat):
        for name, call in calls.items():
            t0 = time.perf_counter()
            call()
            if k >= warmup:
                times[name].append(time.perf_counter() - t0)
    return times


def build_nets(profile: str, tmp: Path, threads: int, int8: bool, random_head: bool):
    """(torch eval net, pipeline copy, {"fp32": OnnxPoseNet, "int8": ...}) of one untrained profile;
    ``random_head``: head weights drawn (std 0.01) so that outputs are not all zero (a fresh head
    is zero: identity updates, which keep every pose valid in the end-to-end runs)."""
    import torch

    from cosy_lite.export.onnx_export import export_pose_net
    from cosy_lite.export.quantize import quantize_pose_net_int8
    from cosy_lite.inference.onnx_runtime import OnnxPoseNet
    from cosy_lite.inference.predictor import inference_net
    from cosy_lite.weights.pose_nets import PoseNetConfig, build_pose_net

    backbone, crop = PROFILES[profile]
    torch.manual_seed(0)
    net = build_pose_net(PoseNetConfig(backbone=backbone, crop_resolution=list(crop))).eval()
    if random_head:
        torch.nn.init.normal_(net.head.weight, std=0.01)
    name = f"{profile}{'-random-head' if random_head else ''}"
    path = tmp / f"{name}.onnx"
    entry = export_pose_net(net, path, "refiner", crop, [1], {"backbone": backbone})
    sessions = {"fp32": OnnxPoseNet(path, threads)}
    if int8:
        quantize_pose_net_int8(path, tmp / f"{name}.int8.onnx", entry, {"backbone": backbone})
        sessions["int8"] = OnnxPoseNet(tmp / f"{name}.int8.onnx", threads)
    return net, inference_net(net, torch.device("cpu")), sessions


def forward_table(nets, batches: list[int], warmup: int, repeat: int) -> list[str]:
    import torch

    lines = ["| profile | batch | torch eager ms | torch pipeline ms (BN folded, channels-last) | onnxruntime fp32 ms "
             "| onnxruntime int8 ms | fp32 speed-up vs eager | vs pipeline | int8 speed-up vs eager "
             "| int8 max abs diff (of max abs output) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    torch.set_flush_denormal(True)
    for profile, (net, fast, sessions) in nets.items():
        crop = PROFILES[profile][1]
        for b in batches:
            x = torch.rand(b, 6, *crop, generator=torch.Generator().manual_seed(b))
            x_cl = x.contiguous(memory_format=torch.channels_last)
            x_np = x.numpy()
            calls = {"eager": lambda net=net, x=x: net(x), "pipeline": lambda fast=fast, x_cl=x_cl: fast(x_cl)}
            calls.update({name: (lambda s=s, x_np=x_np: s.run(x_np)) for name, s in sessions.items()})
            with torch.inference_mode():
                t = {k: _median_ms(v) for k, v in _round_robin(calls, warmup, repeat).items()}
            diff = "-"
            if "int8" in sessions:
                ref = sessions["fp32"].run(x_np)
                diff = f"{np.abs(sessions['int8'].run(x_np) - ref).max():.3f} (of {np.abs(ref).max():.3f})"
            int8 = f"{t['int8']:.1f}" if "int8" in t else "-"
            int8_up = f"{t['eager'] / t['int8']:.2f}x" if "int8" in t else "-"
            lines.append(f"| {profile} ({PROFILES[profile][0]}, {crop[0]}x{crop[1]}) | {b} | {t['eager']:.1f} "
                         f"| {t['pipeline']:.1f} | {t['fp32']:.1f} | {int8} | {t['eager'] / t['fp32']:.2f}x "
                         f"| {t['pipeline'] / t['fp32']:.2f}x | {int8_up} | {diff} |")
            print(lines[-1], flush=True)
    torch.set_flush_denormal(False)
    return lines


def end_to_end_table(ds, nets, objects_counts: list[int], warmup: int, repeat: int) -> list[str]:
    from bench_inference import oracle, pick_image

    from cosy_lite.inference.predictor import Predictor
    from cosy_lite.nets.object_table import ObjectTable
    from cosy_lite.render.renderer import GlRenderer
    from cosy_lite.weights.loaders import PoseModel

    rec, keep = pick_image(ds, max(objects_counts))
    rgb = ds.load_rgb(rec)
    renderer = GlRenderer.from_dataset(ds)
    objects = ObjectTable.from_dataset(ds, sorted({rec.gt[i].obj_id for i in keep}))
    ids = objects.obj_ids
    predictors = {}
    for profile, (net, _, sessions) in nets.items():
        crop = PROFILES[profile][1]
        predictors[(profile, "torch")] = Predictor(PoseModel(net, "coarse", crop, ids),
                                                   PoseModel(net, "refiner", crop, ids), objects, renderer)
        for name, s in sessions.items():
            predictors[(profile, f"onnx {name}")] = Predictor(PoseModel(s, "coarse", crop, ids),
                                                              PoseModel(s, "refiner", crop, ids), objects, renderer)
    lines = [f"Image: {ds.name} test scene {rec.scene_id} image {rec.im_id}, "
             f"objects {[rec.gt[i].obj_id for i in keep]}.",
             "",
             "| profile | backend | objects | pose s (median) | pose s (best) | vs reference | crops ms | render ms "
             "| networks ms | onnx speed-up |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for n in objects_counts:
        det = oracle(ds, rec, keep[:n])
        runs: dict = {v: [] for v in predictors}
        for k in range(warmup + repeat):
            for v, pred in predictors.items():
                est = pred.predict(rgb, rec.camera.K, detections=det)
                if k >= warmup:
                    runs[v].append(est.timings)
        torch_med = {}
        for (profile, backend), rs in runs.items():
            pose = [r["crops"] + r["render"] + r["networks"] for r in rs]
            med = {k: 1e3 * float(np.median([r[k] for r in rs])) for k in ("crops", "render", "networks")}
            pose_med = float(np.median(pose))
            if backend == "torch":
                torch_med[profile] = pose_med
            crop = PROFILES[profile][1]
            ref = f"{pose_med / REFERENCE_S[n]:.2f}x of {REFERENCE_S[n]} s" if n in REFERENCE_S else "-"
            up = "-" if backend == "torch" else f"{torch_med[profile] / pose_med:.2f}x"
            lines.append(f"| {profile} ({PROFILES[profile][0]}, {crop[0]}x{crop[1]}) | {backend} | {n} "
                         f"| {pose_med:.3f} | {min(pose):.3f} | {ref} | {med['crops']:.0f} | {med['render']:.0f} "
                         f"| {med['networks']:.0f} | {up} |")
            print(lines[-1], flush=True)
    renderer.close()
    return lines


def detector_table(ds, tmp: Path, threads: int, warmup: int, repeat: int) -> list[str]:
    import torch
    from bench_inference import pick_image

    from cosy_lite.config import load_config, packaged_config
    from cosy_lite.export.onnx_export import export_detector
    from cosy_lite.inference.onnx_runtime import OnnxDetector
    from cosy_lite.nets.detector import Detector, LabelMap, detect
    from cosy_lite.train.detector_task import DetectorTrainConfig

    cfg = load_config(DetectorTrainConfig, packaged_config("detector", "demo.yaml"))
    torch.manual_seed(0)
    model = Detector(LabelMap(tuple(ds.obj_ids)), cfg.detector).eval()
    export_detector(model, tmp / "detector.onnx")
    session = OnnxDetector(tmp / "detector.onnx", threads)
    rec, _ = pick_image(ds, 1)
    rgb = ds.load_rgb(rec)
    image = torch.from_numpy(rgb).permute(2, 0, 1).float() / 255.0
    torch.set_flush_denormal(True)
    with torch.inference_mode():
        t = _round_robin({"torch": lambda: detect(model, [image]), "onnx": lambda: session.run(rgb)}, warmup, repeat)
    torch.set_flush_denormal(False)
    n_torch, n_onnx = len(detect(model, [image])[0]), len(session.run(rgb)[0])
    lines = ["| detector | torch ms | onnxruntime ms | speed-up | detections (torch / onnx) |",
             "| --- | --- | --- | --- | --- |",
             f"| {cfg.detector.name} {cfg.detector.min_size}x{cfg.detector.max_size} (demo profile, untrained), "
             f"640x480 image | {_median_ms(t['torch']):.0f} | {_median_ms(t['onnx']):.0f} "
             f"| {np.median(t['torch']) / np.median(t['onnx']):.2f}x | {n_torch} / {n_onnx} |"]
    print(lines[-1], flush=True)
    return lines


def cpu_name() -> str:
    """The CPU model from /proc/cpuinfo (Linux), else the architecture."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return f"{line.split(':', 1)[1].strip()} ({platform.machine()})"
    except OSError:
        pass
    return platform.machine()


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--dataset", type=Path, default=Path("data/ycbvsynth"))
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeat", type=int, default=10)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--profiles", nargs="+", default=list(PROFILES), choices=list(PROFILES))
    p.add_argument("--batches", type=int, nargs="+", default=[1, 8])
    p.add_argument("--objects", type=int, nargs="+", default=[1, 5])
    p.add_argument("--no-int8", action="store_true", help="skip the int8 graphs")
    p.add_argument("--no-detector", action="store_true", help="skip the detector comparison")
    p.add_argument("--write", action="store_true", help="append the tables to bench/RESULTS.md")
    args = p.parse_args(argv)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads OpenMP; see infer.py

    from cosy_lite.render.gl import use_egl

    use_egl()
    import onnxruntime
    import torch

    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.inference import predictor as _  # noqa: F401  (torchvision before any rendering)

    torch.set_num_threads(args.threads)
    ds = BopDataset(args.dataset)
    load0 = os.getloadavg()
    head = (f"{cpu_name()}, {os.cpu_count()} CPUs, torch {torch.__version__}, "
            f"onnxruntime {onnxruntime.__version__}, {args.threads} threads, "
            f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}")
    print(f"# {head}", flush=True)
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        nets = {prof: build_nets(prof, Path(tmp), args.threads, not args.no_int8, True) for prof in args.profiles}
        print("## pose-network forward", flush=True)
        out += ["Pose-network forward (random crops in [0, 1], untrained weights with a random head):", ""]
        out += forward_table(nets, args.batches, args.warmup, args.repeat)
        nets = {prof: build_nets(prof, Path(tmp), args.threads, not args.no_int8, False) for prof in args.profiles}
        print("## end to end (coarse + 4 refiner iterations, oracle detections, no ICP)", flush=True)
        out += ["", "End to end, coarse + 4 refiner iterations, oracle detections (no detector), no ICP; "
                f"target: at most {TARGET_FRACTION:.2f} of the reference (0.247 s / 1.483 s):", ""]
        out += end_to_end_table(ds, nets, args.objects, args.warmup, args.repeat)
        if not args.no_detector:
            print("## detector", flush=True)
            out += ["", "Detector on the same kind of image:", ""]
            out += detector_table(ds, Path(tmp), args.threads, args.warmup, args.repeat)
    load1 = os.getloadavg()
    tail = (f"Load average (1, 5, 15 min) before {tuple(round(v, 2) for v in load0)}, "
            f"after {tuple(round(v, 2) for v in load1)}.")
    print(f"# {tail}")
    if args.write:
        cmd = "python bench/bench_onnx.py " + " ".join(argv if argv is not None else sys.argv[1:])
        block = [f"### Run of {datetime.date.today().isoformat()}", "",
                 f"Machine: {head}. Command: `{cmd.strip()}`.", "", *out, "", tail, ""]
        with open(RESULTS, "a") as f:
            f.write("\n" + "\n".join(block))
        print(f"appended to {RESULTS}")


if __name__ == "__main__":
    main()
