"""``cosy-lite score-refiner``: a refiner's median errors on held-out instances, before and after
each iteration (the refiner numbers of a reference-model card).

Instances: ``n`` object instances of a split with a GT pose (default the ``test`` split, which
training never reads; visible fraction >= 0.1), drawn with a fixed seed; start poses: GT + the
refiner's training noise (15 deg per Euler angle, (1, 1, 5) cm per camera axis, the same draw for
every refiner), or the GT itself (``--from-gt``: the drift from a perfect start). Errors as in
training validation (:func:`~cosy_lite.train.pose_task.pose_errors`: symmetry-aware rotation and
translation, MSSD and ADD-S recall at 0.1 diameter).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from cosy_lite.inference.settings import InferenceConfig

if TYPE_CHECKING:
    from cosy_lite.structures import PoseSample

NOISE_ROT_DEG = 15.0
NOISE_TRANS_M = (0.01, 0.01, 0.05)
CHUNK = 32  # instances whose full images are held in memory at once


def score_refiner(refiner: str | Path, dataset_root: str | Path, n: int = 256,
                  n_iterations: int = InferenceConfig.n_refiner_iterations,
                  split: str = "test", seed: int = 12345, progress: bool = True, from_gt: bool = False,
                  fine_iterations: Sequence[int] = (), fine_resolution: Sequence[int] = ()) -> dict[str, Any]:
    """``{"instances", "split", "start": {...}, "iter1": {...}, ...}``: each a dict of
    ``rot_err_deg_median``, ``trans_err_cm_median``, ``adds_recall_0.1d``, ``mssd_recall_0.1d``.
    ``from_gt``: start AT the GT poses (the same instances): how far the refiner drifts from a perfect start.
    ``fine_iterations`` / ``fine_resolution``: those iterations on larger crops, their input depth kept
    (InferenceConfig.refiner_fine_iterations, :class:`~cosy_lite.nets.render_and_compare.FineCrops`)."""
    import torch
    from tqdm import tqdm

    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.data.pose_dataset import PoseDataset
    from cosy_lite.errors import CosyLiteError
    from cosy_lite.nets.initial_pose import add_pose_noise
    from cosy_lite.nets.object_table import ObjectTable
    from cosy_lite.nets.render_and_compare import FineCrops, iterate_poses
    from cosy_lite.render.renderer import GlRenderer
    from cosy_lite.train.pose_task import PoseErrors, pose_errors
    from cosy_lite.weights.loaders import load_pose_model

    settings = InferenceConfig(refiner_fine_iterations=[int(i) for i in fine_iterations],
                               refiner_fine_resolution=[int(v) for v in fine_resolution])  # (checks them)
    fine = FineCrops.of(settings.refiner_fine_iterations, settings.refiner_fine_resolution)
    ds = BopDataset(Path(dataset_root))
    model = load_pose_model(refiner, "refiner")
    if fine is not None and model.output != "flow":
        raise CosyLiteError(f"{refiner}: fine iterations need a flow refiner (net.arch=flow); this one regresses its "
                            "update from crops of its own size only")
    obj_ids = sorted(set(model.obj_ids) & set(ds.models_info))  # the refiner's objects this dataset has
    items: PoseDataset | list[PoseSample] = (
        PoseDataset(ds, split, obj_ids=obj_ids or None, min_visib_fract=0.1) if obj_ids else []
    )
    if len(items) == 0:
        raise CosyLiteError(f"{dataset_root}: no instance of the refiner's obj_ids {model.obj_ids} in split {split!r}")
    g = torch.Generator().manual_seed(seed)
    rows = torch.randperm(len(items), generator=g)[:n].tolist()
    objects = ObjectTable.from_dataset(ds, obj_ids)
    renderer = GlRenderer.from_dataset(ds, shading=model.render_shading)
    keys = ["start"] + [f"iter{i + 1}" for i in range(n_iterations)]
    errors: dict[str, list[PoseErrors]] = {k: [] for k in keys}
    diameters = []
    with torch.no_grad():
        for s in tqdm(range(0, len(rows), CHUNK), desc="score refiner", unit="chunk", disable=not progress):
            batch = [items[r] for r in rows[s:s + CHUNK]]
            gt = torch.stack([b.TCO for b in batch]).double()
            obj = [b.obj_id for b in batch]
            idx = objects.index(obj)
            points, syms, mask = objects.points[idx], objects.symmetries[idx], objects.sym_mask[idx]
            start = add_pose_noise(gt, NOISE_ROT_DEG, NOISE_TRANS_M, generator=g).float()
            start = gt.float() if from_gt else start
            images = torch.stack([b.rgb for b in batch]).float() / 255
            K = torch.stack([b.K for b in batch]).float()
            poses = iterate_poses(model.net, images, K, start, obj, points.float(), renderer, n_iterations,
                                  model.crop_resolution, output=model.output, fine=fine)
            for k, T in zip(keys, [start] + poses):
                errors[k].append(pose_errors(T, gt, points, syms, mask))
            diameters.append(objects.diameters[idx])
    diam = torch.cat(diameters)
    out: dict[str, Any] = {"refiner": str(refiner), "split": split, "instances": len(rows), "seed": seed,
                           "start_noise": ({"rot_deg": 0.0, "trans_m": [0.0, 0.0, 0.0]} if from_gt else
                                           {"rot_deg": NOISE_ROT_DEG, "trans_m": list(NOISE_TRANS_M)})}
    if fine is not None:
        out["fine_crops"] = {"iterations": sorted(fine.iterations), "resolution": list(fine.resolution)}
    for k in keys:
        e = errors[k]
        joined = PoseErrors(*(torch.cat([getattr(x, f.name) for x in e]) for f in fields(PoseErrors)))
        out[k] = {name: round(v, 4) for name, v in joined.summary(diam).items()}
    return out


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--refiner", required=True, metavar="FILE_OR_NAME",
                   help="refiner checkpoint / .safetensors, or the name of shipped reference models (e.g. ycbvsynth)")
    p.add_argument("--dataset", default="ycbvsynth", help="dataset name (folder under $COSY_LITE_DATA or ./data) or path")
    p.add_argument("--split", default="test")
    p.add_argument("-n", type=int, default=256, help="instances (default 256)")
    p.add_argument("--iterations", type=int, default=InferenceConfig.n_refiner_iterations)
    p.add_argument("--seed", type=int, default=12345)
    p.add_argument("--out", type=Path, default=None, metavar="JSON", help="also write the numbers here")
    p.add_argument("--from-gt", action="store_true", help="start at the GT poses instead of GT + noise (the drift)")
    p.add_argument("--fine-iterations", type=int, nargs="+", default=[], metavar="I",
                   help="run these iterations (1-based) on larger crops, keeping their input's depth (as the "
                        "inference setting refiner_fine_iterations); needs --fine-resolution")
    p.add_argument("--fine-resolution", type=int, nargs=2, default=[], metavar=("H", "W"),
                   help="crop size of the fine iterations, px (multiples of 16), e.g. 240 320")
    p.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from cosy_lite.bop.folders import dataset_folder
    from cosy_lite.errors import ConfigError, CosyLiteError, FieldValueError
    from cosy_lite.render.gl import use_egl
    from cosy_lite.weights.reference_models import ReferenceModelError, reference_models

    use_egl()
    refiner = Path(args.refiner)
    if not refiner.exists() and "/" not in args.refiner and not refiner.suffix:
        reference_refiner = reference_models(args.refiner).path("refiner")
        if reference_refiner is None:
            raise ReferenceModelError(f"reference models {args.refiner!r} have no refiner")
        refiner = reference_refiner
    if args.n < 1 or args.iterations < 1:
        raise CosyLiteError(f"-n {args.n} / --iterations {args.iterations}: expected integers >= 1")
    try:  # (score_refiner checks the fine crops first, before loading anything)
        scores = score_refiner(refiner, dataset_folder(args.dataset), args.n, args.iterations, args.split, args.seed,
                               progress=not args.no_progress, from_gt=args.from_gt,
                               fine_iterations=args.fine_iterations, fine_resolution=args.fine_resolution)
    except FieldValueError as e:
        raise ConfigError("--fine-iterations / --fine-resolution", e.field, e.problem) from None
    print(f"{scores['instances']} instances of {args.split}, from GT{'' if args.from_gt else ' + noise'}:")
    print("| iteration | rot (deg) | trans (cm) | ADD-S recall 0.1 d | MSSD recall 0.1 d |\n| --- | ---: | ---: | ---: | ---: |")
    for k in ["start"] + [f"iter{i + 1}" for i in range(args.iterations)]:
        s = scores[k]
        print(f"| {k} | {s['rot_err_deg_median']:.2f} | {s['trans_err_cm_median']:.2f} | "
              f"{s['adds_recall_0.1d']:.3f} | {s['mssd_recall_0.1d']:.3f} |")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(scores, indent=1) + "\n")
    return 0
