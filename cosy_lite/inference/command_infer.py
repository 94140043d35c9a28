"""``cosy-lite infer`` (also ``python infer.py ...``): estimate 6D poses on a BOP test split and write
the BOP19 submission CSV.

Parse, load the checkpoints (:meth:`cosy_lite.inference.predictor.Predictor.from_checkpoints`), the
shipped reference models (``--pretrained NAME``) or the exported ONNX networks (``--onnx DIR``:
:meth:`~cosy_lite.inference.predictor.Predictor.from_onnx`), hand over to
:func:`cosy_lite.inference.bop_run.run_on_split` (ViVo targets, CSV ``METHOD_DATASET-SPLIT.csv``,
overlays, results checker). Examples::

    cosy-lite infer --dataset ycbvsynth --detector runs/ycbvsynth-detector/checkpoint.pt \\
        --coarse runs/ycbvsynth-coarse/checkpoint.pt --refiner runs/ycbvsynth-refiner/checkpoint.pt \\
        --out results/ --vis 8
    cosy-lite infer --dataset ycbvsynth --pretrained ycbvsynth --out results/   # the shipped reference models
    cosy-lite infer --dataset ycbvsynth --onnx onnx/ --threads 2 --out results/
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cosy_lite.inference.settings import add_arguments as add_setting_arguments
from cosy_lite.inference.settings import flag_problem, templates_cache
from cosy_lite.inference.starts import TEMPLATE_STARTS

if TYPE_CHECKING:
    from cosy_lite.inference.settings import InferenceConfig


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
                         "inference settings (pipeline.json); networks and settings given as well win")
    ap.add_argument("--detector", type=Path, default=None, metavar="CKPT", help="detector checkpoint")
    ap.add_argument("--coarse", type=Path, default=None, metavar="CKPT", help="coarse pose checkpoint (torch backend)")
    ap.add_argument("--refiner", type=Path, default=None, metavar="CKPT", help="refiner checkpoint (none: coarse only)")
    ap.add_argument("--scorer", type=Path, default=None, metavar="CKPT",
                    help="--start appearance: the coarse scorer (train.py --model scorer) that describes the detections "
                         "(none: frozen ImageNet features)")
    ap.add_argument("--templates-cache", type=Path, default=None, metavar="DIR",
                    help="template starts: keep the rendered templates in DIR between runs (default: "
                         "$COSY_LITE_CACHE/templates, ~/.cache/cosy_lite/templates)")
    ap.add_argument("--also-before-icp", default=None, metavar="METHOD",
                    help="with --icp: also write the poses before ICP as METHOD_DATASET-SPLIT.csv (the RGB-only "
                         "results of the same run, their time without ICP)")
    ap.add_argument("--detections", default=None, metavar="oracle|FILE.json",
                    help="instead of the detector: 'oracle' (ground-truth boxes and masks) or a BOP22 detections JSON")
    ap.add_argument("--out", type=Path, default=Path("results"), help="output folder (default results/)")
    ap.add_argument("--method", default="cosylite", help="method name of the CSV file (no '_')")
    ap.add_argument("--vis", type=int, default=0, metavar="N", help="write overlay PNGs for the first N images")
    ap.add_argument("--limit-images", type=int, default=None, metavar="N", help="only the first N target images")
    ap.add_argument("--onnx", type=Path, default=None, metavar="DIR",
                    help="a 'cosy-lite export' folder: its networks in onnxruntime (CPU) instead of checkpoints, run "
                         "with its settings")
    ap.add_argument("--threads", type=int, default=None, metavar="N",
                    help="CPU threads of the networks (torch and onnxruntime; default: their own)")
    ap.add_argument("--device", default=None, help="torch backend: cpu or cuda (default: cuda when available)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_setting_arguments(ap, "images ")


CHECKPOINT_ARGUMENTS = ("coarse", "refiner", "detector", "pretrained", "scorer")  # not with --onnx
BACKEND_PRECISIONS = {"torch": ("fp32", "bf16"), "onnx": ("fp32", "int8")}


def _backend(args: argparse.Namespace) -> str:
    return "torch" if args.onnx is None else "onnx"


def _backend_problem(args: argparse.Namespace, config: InferenceConfig) -> str | None:
    """What is wrong with the combination of networks, settings and other arguments (None: nothing)."""
    backend = _backend(args)
    given = [f"--{k}" for k in CHECKPOINT_ARGUMENTS if getattr(args, k) is not None]
    if backend == "onnx" and given:
        return f"{' '.join(given)} not used with --onnx (the export's networks)"
    if args.also_before_icp is not None and not config.icp:
        return "--also-before-icp needs --icp"
    if config.precision not in BACKEND_PRECISIONS[backend]:
        return f"precision {config.precision} needs another backend ({backend}: {list(BACKEND_PRECISIONS[backend])})"
    if backend == "onnx":
        return None
    if args.coarse is None and not (config.start in TEMPLATE_STARTS and args.refiner is not None):
        return "give --pretrained NAME, --coarse CKPT (or --start templates with --refiner CKPT), or --onnx DIR"
    if args.detector is None and args.detections is None:
        return "give --detector CKPT or --detections oracle|FILE.json"
    return None


def _argument_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with a numeric argument (None: nothing); nothing is clamped silently."""
    for name, value, least in (("--threads", args.threads, 1), ("--limit-images", args.limit_images, 1),
                               ("--vis", args.vis, 0)):
        if value is not None and value < least:
            return f"{name} {value}: expected an integer >= {least}"
    return None


def _settings(args: argparse.Namespace) -> Any:
    """The inference settings of the command line: over the --pretrained set's (torch) or the export's (onnx)."""
    from cosy_lite.inference.settings import config_from_arguments, pretrained_config

    if args.onnx is not None:
        from cosy_lite.export.manifest import Manifest

        manifest = Manifest.read(args.onnx)
        return config_from_arguments(args, manifest.inference, manifest.path)
    return pretrained_config(args)


def run(args: argparse.Namespace) -> int:
    """Check the arguments, build the predictor, run it over the split, report."""
    import torch

    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.folders import dataset_folder
    from cosy_lite.bop.results import results_filename
    from cosy_lite.devices import resolve_device
    from cosy_lite.inference.bop_run import run_on_split
    from cosy_lite.inference.predictor import Predictor, SetupError
    from cosy_lite.render.gl import use_egl

    use_egl()
    if problem := flag_problem(args) or _argument_problem(args):
        print(f"error: {problem}", file=sys.stderr)
        return 2
    config = _settings(args)
    if problem := _backend_problem(args, config):
        print(f"error: {problem}", file=sys.stderr)
        return 2
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
    if args.onnx is not None:
        predictor = Predictor.from_onnx(args.onnx, dataset=dataset, config=config, threads=args.threads,
                                        detector=args.detections is None, templates_cache=templates_cache(args))
        if args.detections is None and predictor.detector is None:
            raise SetupError(f"{args.onnx / 'manifest.json'}: the export has no detector: export one "
                             "(cosy-lite export --detector CKPT) or give --detections oracle|FILE.json")
        detector_path = getattr(predictor.detector, "path", None)  # the export's detector.onnx
    else:
        predictor = Predictor.from_checkpoints(
            detector=args.detector if args.detections is None else None, coarse=args.coarse,
            refiner=args.refiner, dataset=dataset, config=config, device=resolve_device(args.device),
            templates_cache=templates_cache(args), scorer=args.scorer)
        detector_path = args.detector if args.detections is None else None
    summary = run_on_split(predictor, dataset, args.out, args.split, method, args.detections, args.vis,
                           args.limit_images, progress=not args.no_progress, detector_path=detector_path,
                           task=args.task, method_before_icp=args.also_before_icp)
    for p in summary.problems:
        print(p)
    for line in summary.lines():
        print(line)
    return 0 if summary.ok else 1
