"""``cosy-lite predict``: one image in, detections + 6D poses out (JSON, the BOP19 CSV rows, an overlay, timings).

    cosy-lite predict --rgb IMG [--depth DEPTH [--depth-scale S]] --camera K.json --meshes NAME_OR_DIR
        (--coarse CKPT [--refiner CKPT] [--detector CKPT] | --onnx EXPORT_DIR) [--objects 1,5] [--icp]
        [--detections FILE.json] --out DIR

``--meshes`` are the objects' 3D models: a BOP ``models/`` folder, a dataset folder (its
``models/``) or a dataset name under ``$COSY_LITE_DATA`` (default ``./data``). The networks are
checkpoints (torch backend) or a ``cosy-lite export`` folder (onnxruntime backend). From Python the
same is :class:`~cosy_lite.inference.predictor.Predictor` (``from_checkpoints`` / ``from_onnx``,
then ``predict(rgb, K, depth)``) and :func:`predict_image` here (estimates as BOP JSON + overlay).

Writes ``DIR/predictions.json`` (per estimate: obj_id, score, box, R, t in mm, the BOP19 CSV row;
the camera; timings), ``DIR/predictions.csv`` (a BOP19 results file of the one image) and
``DIR/overlay.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cosy_lite.inference.settings import PREDICT_DEFAULTS, flag_problem, templates_cache
from cosy_lite.inference.settings import add_arguments as add_setting_arguments
from cosy_lite.inference.starts import TEMPLATE_STARTS

if TYPE_CHECKING:
    from cosy_lite.inference.pose_estimates import PoseEstimates
    from cosy_lite.inference.predictor import Predictor
    from cosy_lite.inference.settings import InferenceConfig


def obj_id_list(text: str) -> list[int]:
    """``--objects 1,5`` -> [1, 5] (argparse type: a usage error for anything else)."""
    try:
        ids = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected object ids separated by commas, e.g. 1,5") from None
    if not ids or min(ids) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected positive object ids separated by commas, e.g. 1,5")
    return ids


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rgb", type=Path, required=True, metavar="IMG", help="colour image (PNG/JPG)")
    p.add_argument("--depth", type=Path, default=None, metavar="DEPTH",
                   help="16-bit depth image aligned with --rgb (for --icp); value * --depth-scale = mm")
    p.add_argument("--depth-scale", type=float, default=None, metavar="S",
                   help="depth value * S = mm (default: the camera file's depth_scale, else 1)")
    p.add_argument("--camera", type=Path, required=True, metavar="K.json",
                   help="intrinsics: BOP camera.json (fx, fy, cx, cy), a scene_camera entry (cam_K) or {\"K\": 3x3}")
    p.add_argument("--meshes", default=None, metavar="NAME_OR_DIR",
                   help="the objects' 3D models: a BOP models/ folder, a dataset folder, or a dataset name "
                        "(default with --pretrained: the set's objects, generated from the package on first use)")
    p.add_argument("--pretrained", default=None, metavar="NAME",
                   help="the shipped reference models NAME (e.g. ycbvsynth) with their inference settings (pipeline.json; "
                        "torch backend); networks and settings given as well win")
    p.add_argument("--coarse", type=Path, default=None, metavar="CKPT", help="coarse checkpoint (torch backend)")
    p.add_argument("--refiner", type=Path, default=None, metavar="CKPT", help="refiner checkpoint (torch backend)")
    p.add_argument("--scorer", type=Path, default=None, metavar="CKPT",
                   help="--start appearance: the coarse scorer that describes the detections (torch backend)")
    p.add_argument("--detector", type=Path, default=None, metavar="CKPT", help="detector checkpoint (torch backend)")
    p.add_argument("--onnx", type=Path, default=None, metavar="EXPORT_DIR",
                   help="a 'cosy-lite export' folder: the networks in onnxruntime (instead of checkpoints)")
    p.add_argument("--detections", type=Path, default=None, metavar="FILE.json",
                   help="BOP22 detections of this image instead of the detector (all its entries must be one image)")
    p.add_argument("--objects", type=obj_id_list, default=None, metavar="1,5", help="estimate only these objects")
    p.add_argument("--templates-cache", type=Path, default=None, metavar="DIR",
                   help="template starts: keep the rendered templates in DIR between runs (default: "
                        "$COSY_LITE_CACHE/templates, ~/.cache/cosy_lite/templates)")
    p.add_argument("--device", default=None, help="torch backend: cpu or cuda (default: cuda when available)")
    p.add_argument("--threads", type=int, default=None, help="CPU threads of the networks")
    p.add_argument("--scene-id", type=int, default=0, help="scene_id of the CSV rows (default 0)")
    p.add_argument("--im-id", type=int, default=0, help="im_id of the CSV rows (default 0)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    add_setting_arguments(p, "image --depth ")


@dataclass
class ImagePrediction:
    """What :func:`predict_image` returns: the estimates (metres) and the overlay."""

    estimates: PoseEstimates  # (valid ones only)
    n_invalid: int  # poses dropped as invalid (NaN, not a rotation, behind the camera)
    overlay: np.ndarray  # [H,W,3] uint8
    seconds: float  # wall time of predict()


def models_folder(name_or_dir: str) -> Path:
    """The BOP ``models/`` folder of ``--meshes``: the folder itself if it has ``models_info.json``,
    else its ``models/``, else ``$COSY_LITE_DATA/NAME/models``. Errors name what was looked for."""
    from cosy_lite.bop.folders import dataset_folder
    from cosy_lite.errors import BopFormatError

    p = Path(name_or_dir)
    if (p / "manifest.json").is_file():
        raise BopFormatError(p, "--meshes", "this is a 'cosy-lite export' folder: pass it as --onnx; --meshes are the "
                             "objects' 3D models (a BOP models/ folder, a dataset folder or a dataset name)")
    for cand in (p, p / "models", dataset_folder(name_or_dir) / "models"):
        if (cand / "models_info.json").is_file():
            return cand
    raise BopFormatError(p, "--meshes", "no models_info.json in it, in its models/ or in "
                         f"{dataset_folder(name_or_dir) / 'models'} (expected a BOP models/ folder, a dataset "
                         "folder or a dataset name under $COSY_LITE_DATA)")


def _reference_meshes(name: str) -> Path:
    """The ``models/`` folder of the objects of the reference set ``name`` (its dataset's meshes)."""
    from cosy_lite.synth.library_meshes import library_models
    from cosy_lite.weights.reference_models import reference_models

    return library_models(reference_models(name).dataset)


def _argument_problem(args: argparse.Namespace) -> str | None:
    if args.onnx is not None and any(v is not None for v in (args.coarse, args.refiner, args.detector, args.pretrained,
                                                             args.scorer)):
        return ("give either checkpoints (--pretrained/--coarse/--refiner/--detector/--scorer) or --onnx EXPORT_DIR, "
                "not both")
    if args.meshes is None and args.pretrained is None:
        return "give --meshes NAME_OR_DIR (the objects' 3D models), or --pretrained NAME (its objects' meshes)"
    if args.depth_scale is not None and not (np.isfinite(args.depth_scale) and args.depth_scale > 0):
        return f"--depth-scale {args.depth_scale}: expected a number > 0 (depth value * S = mm)"
    for name, value, least in (("--threads", args.threads, 1), ("--scene-id", args.scene_id, 0), ("--im-id", args.im_id, 0)):
        if value is not None and value < least:
            return f"{name} {value}: expected an integer >= {least}"
    return None


def _setup_problem(args: argparse.Namespace, config: InferenceConfig) -> str | None:
    """What the networks and settings of the command line lack (None: nothing)."""
    if args.onnx is None and args.coarse is None and not (config.start in TEMPLATE_STARTS and args.refiner is not None):
        return ("give --coarse CKPT [--refiner CKPT --detector CKPT] (torch), --start templates --refiner CKPT, "
                "or --onnx EXPORT_DIR (onnxruntime)")
    if args.onnx is None and args.detector is None and args.detections is None:
        return "no detections: give --detector CKPT or --detections FILE.json"
    if config.icp and args.depth is None:
        return "--icp needs --depth DEPTH (the depth image it aligns the models with)"
    return None


def _settings(args: argparse.Namespace) -> Any:
    """The inference settings of the command line: over the --pretrained set's or the export's."""
    from cosy_lite.inference.settings import config_from_arguments, pretrained_config

    if args.onnx is not None:
        from cosy_lite.export.manifest import Manifest

        manifest = Manifest.read(args.onnx)
        return config_from_arguments(args, {**PREDICT_DEFAULTS, **manifest.inference}, manifest.path)
    return pretrained_config(args, defaults=PREDICT_DEFAULTS)


def _given_detections(path: Path, known: list[int], with_masks: bool = False):
    """The detections of the one image in a BOP22 file (objects without a 3D model are an error);
    with_masks: decode their ``segmentation`` (needed by ``--start templates``)."""
    from cosy_lite.bop.detections import read_detections_json
    from cosy_lite.errors import BopFormatError

    per_image = read_detections_json(path, valid_obj_ids=known, with_masks=with_masks)
    if len(per_image) > 1:
        raise BopFormatError(path, "scene_id/image_id", f"detections of {len(per_image)} images "
                             f"(e.g. {sorted(per_image)[:3]}); predict takes one image")
    if not per_image:
        from cosy_lite.bop.detections import Detections

        return Detections.empty()
    return next(iter(per_image.values()))


def predict_image(predictor, rgb: np.ndarray, K: np.ndarray, depth: np.ndarray | None = None,
                  detections=None, obj_ids: list[int] | None = None) -> ImagePrediction:
    """Run ``predictor`` on one image and draw the valid estimates over it.

    Args:
        rgb: [H,W,3] uint8; K: [3,3] px; depth: [H,W] metres (0 = unknown) or None.
        detections: :class:`~cosy_lite.bop.detections.Detections` or None (the predictor's detector).
        obj_ids: keep only these objects.
    """
    from cosy_lite.inference.overlay import draw_estimates

    t0 = time.perf_counter()
    est = predictor.predict(rgb, K, depth, detections=detections, obj_ids=obj_ids)
    seconds = time.perf_counter() - t0
    good = est.only_valid()
    overlay = draw_estimates(rgb, K, good.obj_ids.tolist(), good.TCO.numpy(), good.scores.tolist(), predictor.renderer)
    return ImagePrediction(good, len(est) - len(good), overlay, seconds)


def _detection_json(est: PoseEstimates, i: int) -> dict[str, Any]:
    """Estimate ``i``'s detection: box (x1, y1, x2, y2 px), score and mask (COCO RLE; None: a box only)."""
    from cosy_lite.bop.detections import mask_to_rle

    mask = None if est.masks is None else mask_to_rle(est.masks[i].numpy())
    return {"box_xyxy_px": [float(v) for v in est.boxes[i].tolist()], "score": float(est.scores[i]), "mask_rle": mask}


def _start_json(est: PoseEstimates, i: int) -> dict[str, Any]:
    """Where estimate ``i``'s refinement started (the chosen template or the coarse pose): R, t in mm."""
    T = est.TCO_coarse[i].double().numpy()
    return {"R": T[:3, :3].tolist(), "t": [float(v * 1000.0) for v in T[:3, 3]]}


def _load_inputs(args: argparse.Namespace):
    """rgb [H,W,3] uint8, K [3,3], depth [H,W] m or None; sizes checked against each other and the camera file."""
    from cosy_lite.bop import io
    from cosy_lite.errors import BopFormatError

    cam = io.load_camera_file(args.camera)
    rgb = io.load_image(args.rgb)
    H, W = rgb.shape[:2]
    if cam.size is not None and cam.size != (W, H):
        raise BopFormatError(args.camera, "width", f"the camera is {cam.size[0]}x{cam.size[1]} px, but {args.rgb} is "
                             f"{W}x{H}")
    depth = None
    if args.depth is not None:
        scale = args.depth_scale if args.depth_scale is not None else (cam.depth_scale or 1.0)
        depth = io.load_depth(args.depth, scale)
        if depth.shape != (H, W):
            raise BopFormatError(args.depth, "size", f"{depth.shape[1]}x{depth.shape[0]} px, but {args.rgb} is {W}x{H}")
    return rgb, cam.K, depth


def _build_predictor(args: argparse.Namespace, config: InferenceConfig, models_dir: Path) -> Predictor:
    from cosy_lite.devices import resolve_device
    from cosy_lite.inference.predictor import Predictor, SetupError

    common = dict(models_dir=models_dir, config=config, obj_ids=args.objects, templates_cache=templates_cache(args))
    if args.onnx is not None:
        p = Predictor.from_onnx(args.onnx, threads=args.threads, detector=args.detections is None, **common)
        if args.detections is None and p.detector is None:
            raise SetupError(f"{args.onnx / 'manifest.json'}: the export has no detector: export one "
                             "(cosy-lite export --detector CKPT) or give --detections FILE.json")
        return p
    return Predictor.from_checkpoints(detector=args.detector if args.detections is None else None, coarse=args.coarse,
                                      refiner=args.refiner, device=resolve_device(args.device), scorer=args.scorer,
                                      **common)


def run(args: argparse.Namespace) -> int:
    """Check the arguments and files, build the predictor, predict, write the outputs."""
    import cv2
    import torch

    from cosy_lite.bop.io import atomic_write_text
    from cosy_lite.bop.results import PoseEstimate, estimate_to_json, write_results_csv
    from cosy_lite.inference.predictor import TIMING_KEYS, SetupError
    from cosy_lite.render.gl import use_egl

    use_egl()
    if problem := flag_problem(args) or _argument_problem(args):
        print(f"error: {problem}", file=sys.stderr)
        return 2
    config = _settings(args)
    if problem := _setup_problem(args, config):
        print(f"error: {problem}", file=sys.stderr)
        return 2
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    models_dir = models_folder(args.meshes) if args.meshes is not None else _reference_meshes(args.pretrained)
    rgb, K, depth = _load_inputs(args)
    predictor = _build_predictor(args, config, models_dir)
    if args.objects:
        missing = sorted(set(args.objects) - set(predictor.obj_ids))
        if missing:
            raise SetupError(f"--objects {missing}: the pose models estimate obj_ids {predictor.obj_ids}")
    detections = None
    if args.detections is not None:
        from cosy_lite.bop.io import load_models_info

        detections = _given_detections(args.detections, sorted(load_models_info(models_dir / "models_info.json")),
                                       with_masks=config.start in TEMPLATE_STARTS)
    pred = predict_image(predictor, rgb, K, depth, detections, args.objects or predictor.obj_ids)
    est = pred.estimates
    rows = [PoseEstimate(args.scene_id, args.im_id, int(est.obj_ids[i]), float(est.scores[i]), est.TCO[i].numpy(),
                         pred.seconds) for i in range(len(est))]
    timings_ms = {k: 1000.0 * est.timings.get(k, 0.0) for k in TIMING_KEYS}
    out = {
        "rgb": str(args.rgb), "depth": None if args.depth is None else str(args.depth),
        "camera_K": np.asarray(K).tolist(), "backend": predictor.backend, "icp": config.icp,
        "estimates": [{**estimate_to_json(r), "detection": _detection_json(est, i), "start": _start_json(est, i)}
                      for i, r in enumerate(rows)],
        "n_invalid_dropped": pred.n_invalid, "seconds": pred.seconds, "timings_ms": timings_ms,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "predictions.json", json.dumps(out, indent=1) + "\n")
    write_results_csv(args.out / "predictions.csv", rows)
    if not cv2.imwrite(str(args.out / "overlay.png"), cv2.cvtColor(pred.overlay, cv2.COLOR_RGB2BGR)):
        raise OSError(f"{args.out / 'overlay.png'}: could not write the overlay PNG")
    for e in out["estimates"]:
        print(f"obj {e['obj_id']:>3} score {e['score']:.3f} t [mm] {' '.join(f'{v:8.1f}' for v in e['t'])}")
    if pred.n_invalid:
        print(f"WARNING: {pred.n_invalid} invalid poses dropped")
    stages = "  ".join(f"{k} {v:.0f}" for k, v in timings_ms.items() if k not in ("total", "templates"))
    once = f"; once: templates {timings_ms['templates']:.0f} ms" if timings_ms["templates"] > 0 else ""
    print(f"{len(rows)} estimates ({predictor.backend}) in {timings_ms['total']:.0f} ms: {stages}{once}")
    print(f"wrote {args.out / 'predictions.json'}, predictions.csv, overlay.png")
    return 0
