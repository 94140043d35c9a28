"""Per-image latency of a reference set's pipeline under several settings, side by side.

Usage: python bench/bench_reference_pipeline.py [--pretrained ycbvsynth] [--dataset data/ycbvsynth]
       [--images 5] [--repeats 2] [--threads 2] [--onnx EXPORT_DIR] [--targets]
       [--variant NAME KEY=VALUE ...] [--variant ...]

The pipeline of ``cosy-lite infer --pretrained NAME`` (its detector, start, refiner; the templates
from the cache, rendered before the clock starts) on the first ``--images`` test images, with
``--threads`` CPU threads: RGB only, and with the depth image (ICP). Each ``--variant`` changes the
set's settings (``inference_config`` overrides, e.g. ``n_candidates=1``); without one, the set's
own settings alone. ``--onnx``: the same with the networks of a ``cosy-lite export`` folder in
onnxruntime. The variants are called in turn on every image (round-robin, so they share the
machine's load); the table gives the median seconds per image and each one's ratio to the first
variant of its backend and mode. Every detection is posed, as ``cosy-lite predict``; ``--targets``:
only those of each image's BOP19 targets, as ``cosy-lite infer`` (``Predictor.predict(...,
inst_counts)``: its ``inst_count`` best per object, or with ``vivo_candidates`` N the N x
``inst_count`` best, of which the most confident go on).

The settings of the pipeline issue 28 was filed on (964259a: silhouette templates, 5 candidates
ranked by the refiner's confidence, 4 iterations on 144x192 crops, ICP of the chosen one only, one
detection per instance, masks above 0.5), in today's code: ``--variant filed start=templates
n_candidates=5 candidate_choice=confidence icp_settings.verify_candidates=false mask_threshold=0.5
vivo_candidates=1 n_refiner_iterations=4 refiner_fine_iterations=[] refiner_depth_drift=[]``
(bench/RESULTS.md: sessions 17 and 32 also timed that commit's own code and set).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np


def parse_variants(given: list[list[str]] | None) -> dict[str, list[str]]:
    """``--variant NAME KEY=VALUE ...`` -> {NAME: overrides}; none given: the set's own settings."""
    if not given:
        return {"set": []}
    return {v[0]: v[1:] for v in given}


MODES = {"RGB": [], "+ ICP": ["icp=true"]}  # mode -> the settings it adds (ICP: with the depth image)


def predictors(args, variants: dict[str, list[str]], ds):
    """{(backend, mode, variant): Predictor} for the torch backend and, with ``--onnx``, onnxruntime."""
    from cosy_lite.inference.predictor import Predictor
    from cosy_lite.inference.settings import inference_config
    from cosy_lite.weights.reference_models import reference_models

    ref = reference_models(args.pretrained)
    if args.templates_cache is None:  # as the commands: $COSY_LITE_CACHE/templates
        from cosy_lite.bop.folders import default_cache_dir

        args.templates_cache = default_cache_dir() / "templates"
    out = {}
    for backend in ("torch", "onnx") if args.onnx is not None else ("torch",):
        for mode, added in MODES.items():
            for name, overrides in variants.items():
                config = inference_config(ref.inference, ref.pipeline_path, None, [*overrides, *added])
                out[(backend, mode, name)] = (
                    Predictor.from_pretrained(args.pretrained, dataset=ds, config=config,
                                              templates_cache=args.templates_cache) if backend == "torch" else
                    Predictor.from_onnx(args.onnx, dataset=ds, config=config, threads=args.threads,
                                        templates_cache=args.templates_cache))
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--pretrained", default="ycbvsynth")
    p.add_argument("--dataset", type=Path, default=Path("data/ycbvsynth"))
    p.add_argument("--images", type=int, default=5)
    p.add_argument("--repeats", type=int, default=2, help="timed passes over the images (after one warm-up pass)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--onnx", type=Path, default=None, metavar="EXPORT_DIR")
    p.add_argument("--templates-cache", type=Path, default=None, metavar="DIR",
                   help="default: $COSY_LITE_CACHE/templates, as cosy-lite infer")
    p.add_argument("--variant", nargs="+", action="append", metavar="NAME KEY=VALUE",
                   help="a name and the settings it changes, e.g. --variant one n_candidates=1")
    p.add_argument("--targets", action="store_true",
                   help="pose only the detections of each image's BOP19 targets, as cosy-lite infer (default: all)")
    args = p.parse_args(argv)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads OpenMP; see infer.py

    import torch

    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.inference.vivo import targets_by_image
    from cosy_lite.render.gl import use_egl

    use_egl()
    torch.set_num_threads(args.threads)
    ds = BopDataset(args.dataset)
    records = list(ds.images("test"))[:args.images]
    variants = parse_variants(args.variant)
    preds = predictors(args, variants, ds)
    targets = targets_by_image(ds.test_targets()) if args.targets else {}
    images = [(ds.load_rgb(r), ds.load_depth(r), r.camera.K, targets.get((r.scene_id, r.im_id))) for r in records]
    for pred in preds.values():  # templates rendered (or read) and the networks warmed before the clock
        for rgb, depth, K, counts in images:
            pred.predict(rgb, K, depth, inst_counts=counts)
    load0 = os.getloadavg()
    seconds: dict[tuple[str, str, str], list[float]] = {}
    for _ in range(args.repeats):
        for rgb, depth, K, counts in images:
            for key, pred in preds.items():
                t = time.perf_counter()
                pred.predict(rgb, K, depth, inst_counts=counts)
                seconds.setdefault(key, []).append(time.perf_counter() - t)
    load1 = os.getloadavg()
    print(f"# {platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, {args.threads} threads; "
          f"reference set {args.pretrained}, {len(images)} test images of {ds.root}, detector included, "
          f"{'the BOP19 targets posed' if args.targets else 'every detection posed'}; "
          f"load average before {tuple(round(v, 2) for v in load0)}, after {tuple(round(v, 2) for v in load1)}")
    print("| backend | mode | variant | settings | s / image (median) | vs first variant |")
    print("| --- | --- | --- | --- | ---: | ---: |")
    for (backend, mode, name), s in seconds.items():
        first = seconds[(backend, mode, next(iter(variants)))]
        ratio = float(np.median(s)) / float(np.median(first))
        print(f"| {backend} | {mode} | {name} | {' '.join(variants[name] + MODES[mode]) or '(the set)'} | {np.median(s):.3f} "
              f"| {ratio:.2f}x |")


if __name__ == "__main__":
    main()
