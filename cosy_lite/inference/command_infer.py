"""``cosy-lite infer`` (also ``python infer.py ...``): estimate 6D poses on a BOP test split and write
the BOP19 submission CSV.

Parse, load the checkpoints (:meth:`cosy_lite.inference.predictor.Predictor.from_checkpoints`), the
shipped reference models (``--pretrained NAME``) or the exported ONNX networks (``--backend onnx``:
:meth:`~cosy_lite.inference.predictor.Predictor.from_onnx`), hand over to
:func:`cosy_lite.inference.bop_run.run_on_split` (ViVo targets, CSV ``METHOD_DATASET-SPLIT.csv``,
overlays, results checker). Examples::

    cosy-lite infer --dataset ycbvsynth --detector runs/ycbvsynth-detector/checkpoint.pt \\
        --coarse runs/ycbvsynth-coarse/checkpoint.pt --refiner runs/ycbvsynth-refiner/checkpoint.pt \\
        --out results/ --vis 8
    cosy-lite infer --dataset ycbvsynth --pretrained ycbvsynth --out results/   # the shipped reference models
    cosy-lite infer --dataset ycbvsynth --backend onnx --models onnx/ --threads 2 --out results/
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cosy_lite.inference.starts import STARTS, TEMPLATE_STARTS


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--dataset", default="ycbvsynth", help="dataset name (folder under --data-root) or path")
    ap.add_argument("--data-root", type=Path, default=None, help="default: $COSY_LITE_DATA or ./data")
    ap.add_argument("--split", default="test", help="test split (default: test)")
    ap.add_argument("--task", default="6d-localization", choices=["6d-localization", "6d-detection"],
                    help="6d-localization (BOP19: the inst_count best detections per target of test_targets_bop19.json) "
                         "or 6d-detection (BOP 2024/2025: every detection, at most 100 per image, of the images "
                         "of test_targets_bop24.json)")
    ap.add_argument("--pretrained", default=None, metavar="NAME",
                    help="the reference models NAME (e.g. ycbvsynth, shipped in the package) with their "
                         "inference settings; --detector/--coarse/--refiner/--start/--candidates given as well win")
    ap.add_argument("--detector", type=Path, default=None, metavar="CKPT", help="detector checkpoint")
    ap.add_argument("--coarse", type=Path, default=None, metavar="CKPT", help="coarse pose checkpoint (torch backend)")
    ap.add_argument("--refiner", type=Path, default=None, metavar="CKPT", help="refiner checkpoint (none: coarse only)")
    ap.add_argument("--scorer", type=Path, default=None, metavar="CKPT",
                    help="--start appearance: the coarse scorer (train.py --model scorer) that describes the detections "
                         "(none: frozen ImageNet features)")
    ap.add_argument("--n-refiner-iters", type=int, default=None,
                    help="refiner iterations (default: the --pretrained set's, else 4)")
    ap.add_argument("--start", default=None, choices=STARTS,
                    help="start poses: coarse (box pose -> the coarse network, CosyPose; the default) or templates "
                         "(the detection mask matched against rendered silhouettes; no coarse network needed)")
    ap.add_argument("--templates-cache", type=Path, default=None, metavar="DIR",
                    help="--start templates: keep the rendered templates in DIR between runs (default: render each run)")
    ap.add_argument("--candidates", type=int, default=None, metavar="K",
                    help="--start templates: the K best templates each get one refiner iteration, the most "
                         "confident goes on (K > 1 needs a flow refiner; default 1)")
    ap.add_argument("--min-score", type=float, default=0.0, metavar="S",
                    help="pose only detections scoring at least S (default 0: all; for BOP19 any threshold only "
                         "lowers AR, bench/RESULTS.md 'Detection threshold')")
    ap.add_argument("--one-per-region", action="store_true",
                    help="at most one detection per image region (mask IoU > 0.5, any class; the best scored)")
    ap.add_argument("--icp", action="store_true", help="refine with the depth images (point-to-plane ICP)")
    ap.add_argument("--icp-set", nargs="+", default=[], metavar="KEY=VALUE",
                    help="ICP settings (cosy_lite.inference.icp.IcpConfig), e.g. max_translation=0.1 or "
                         "verify_candidates=false (with --candidates K > 1, by default every candidate is ICP'd and "
                         "the one whose depth agrees best with the measured depth is kept; false: the RGB choice only)")
    ap.add_argument("--also-before-icp", default=None, metavar="METHOD",
                    help="with --icp: also write the poses before ICP as METHOD_DATASET-SPLIT.csv (the RGB-only "
                         "results of the same run, their time without ICP)")
    ap.add_argument("--detections", default=None, metavar="oracle|FILE.json",
                    help="instead of the detector: 'oracle' (ground-truth boxes and masks) or a BOP22 detections JSON")
    ap.add_argument("--out", type=Path, default=Path("results"), help="output folder (default results/)")
    ap.add_argument("--method", default="cosylite", help="method name of the CSV file (no '_')")
    ap.add_argument("--vis", type=int, default=0, metavar="N", help="write overlay PNGs for the first N images")
    ap.add_argument("--limit-images", type=int, default=None, metavar="N", help="only the first N target images")
    ap.add_argument("--backend", default="torch", choices=["torch", "onnx"],
                    help="torch: the checkpoints; onnx: the exported networks of --models in onnxruntime (CPU)")
    ap.add_argument("--models", type=Path, default=None, metavar="DIR",
                    help="export folder of 'cosy-lite export' (--backend onnx): manifest.json + .onnx files")
    ap.add_argument("--threads", type=int, default=None, metavar="N",
                    help="CPU threads of the networks (torch and onnxruntime; default: their own)")
    ap.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available; onnx: cpu)")
    ap.add_argument("--precision", default="fp32", choices=["fp32", "bf16", "int8"],
                    help="pose networks' arithmetic: fp32; bf16 autocast (torch, faster on CPUs with AVX512-BF16); "
                         "int8 (onnx, exported with --quantize int8)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")


# backend -> arguments that only it takes (anything given there for the other backend is an error)
BACKEND_ONLY = {"torch": ("coarse", "refiner", "detector", "pretrained", "scorer"), "onnx": ("models",)}
PRECISIONS = {"torch": ("fp32", "bf16"), "onnx": ("fp32", "int8")}


def _backend_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with the combination of --backend and the other arguments (None: nothing)."""
    other = "onnx" if args.backend == "torch" else "torch"
    given = [f"--{k}" for k in BACKEND_ONLY[other] if getattr(args, k) is not None]
    if given:
        return f"{' '.join(given)} not used with --backend {args.backend}"
    if args.also_before_icp is not None and not args.icp:
        return "--also-before-icp needs --icp"
    if args.precision not in PRECISIONS[args.backend]:
        return f"--precision {args.precision} needs another backend ({args.backend}: {list(PRECISIONS[args.backend])})"
    if args.backend == "onnx":
        return None if args.models is not None else "--backend onnx needs --models DIR (a 'cosy-lite export' folder)"
    if args.coarse is None and not (args.start in TEMPLATE_STARTS and args.refiner is not None):
        return "give --coarse CKPT (or --start templates with --refiner CKPT, or --backend onnx --models DIR)"
    if args.detector is None and args.detections is None:
        return "give --detector CKPT or --detections oracle|FILE.json"
    return None


def _argument_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with a numeric argument (None: nothing); nothing is clamped silently."""
    for name, value, least in (("--threads", args.threads, 1), ("--limit-images", args.limit_images, 1),
                               ("--n-refiner-iters", args.n_refiner_iters, 0), ("--vis", args.vis, 0),
                               ("--candidates", args.candidates, 1)):
        if value is not None and value < least:
            return f"{name} {value}: expected an integer >= {least}"
    if not 0.0 <= args.min_score <= 1.0:
        return f"--min-score {args.min_score}: expected a score in [0, 1]"
    return None


def run(args: argparse.Namespace) -> int:
    """Check the arguments, build the predictor, run it over the split, report."""
    import torch

    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.results import results_filename
    from cosy_lite.inference.bop_run import run_on_split
    from cosy_lite.inference.detection_filter import DetectionFilter
    from cosy_lite.config import load_config
    from cosy_lite.errors import ConfigError
    from cosy_lite.inference.icp import IcpConfig
    from cosy_lite.inference.predictor import Predictor, SetupError
    from cosy_lite.render.gl import use_egl
    from cosy_lite.model_files.reference_models import fill_arguments
    from cosy_lite.synth.command import dataset_folder

    use_egl()
    fill_arguments(args, args.backend == "torch")
    problem = _backend_problem(args) or _argument_problem(args)
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    try:
        icp_config = load_config(IcpConfig, None, args.icp_set)
    except ConfigError as e:  # named with the flag that gave the overrides
        raise ConfigError(f"--icp-set: {e.where}", e.field, e.problem) from None
    method = args.method.replace("_", "")
    if method != args.method:
        print(f"note: method name {args.method!r} written as {method!r} (BOP file names have one '_')")
    try:
        results_filename(method, "dataset", args.split)
        if args.also_before_icp is not None:
            results_filename(args.also_before_icp, "dataset", args.split)
    except ValueError as e:
        print(f"error: --method / --also-before-icp / --split: {e}", file=sys.stderr)
        return 2
    if args.also_before_icp == method:
        print("error: --also-before-icp: the same name as --method (the two CSV files would be one)", file=sys.stderr)
        return 2
    root = dataset_folder(args.dataset, args.data_root)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    dataset = BopDataset(root)
    detection_filter = DetectionFilter(args.min_score, args.one_per_region)
    if args.backend == "onnx":
        predictor = Predictor.from_onnx(
            args.models, dataset=dataset, n_refiner_iterations=args.n_refiner_iters, icp=args.icp,
            icp_config=icp_config, threads=args.threads, precision=args.precision, detector=args.detections is None,
            start=args.start, n_candidates=args.candidates, templates_cache=args.templates_cache,
            detection_filter=detection_filter)
        if args.detections is None and predictor.detector is None:
            raise SetupError(f"{args.models / 'manifest.json'}: the export has no detector: export one "
                             "(cosy-lite export --detector CKPT) or give --detections oracle|FILE.json")
        detector_path = predictor.detector.path if predictor.detector is not None else None
    else:
        device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
        predictor = Predictor.from_checkpoints(
            detector=args.detector if args.detections is None else None, coarse=args.coarse,
            refiner=args.refiner, dataset=dataset, device=device,
            n_refiner_iterations=args.n_refiner_iters if args.refiner else 0, icp=args.icp,
            icp_config=icp_config, precision=args.precision, start=args.start, n_candidates=args.candidates,
            templates_cache=args.templates_cache, scorer=args.scorer, detection_filter=detection_filter)
        detector_path = args.detector if args.detections is None else None
    summary = run_on_split(predictor, dataset, args.out, args.split, method, args.detections, args.vis,
                           args.limit_images, progress=not args.no_progress, detector_path=detector_path,
                           task=args.task, method_before_icp=args.also_before_icp)
    for p in summary.problems:
        print(p)
    for line in summary.lines():
        print(line)
    return 0 if summary.ok else 1
