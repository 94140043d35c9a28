"""``cosy-lite score-start``: how often the start stage points the right way (issue 28's first number).

Instances: those of a split (default ``test``, never trained on) with a GT pose and a visible
fraction >= ``min_visib`` (0.5), their GT visible masks standing in for detections. Each goes through
the start stage of ``cosy-lite infer`` (:meth:`SilhouetteTemplates.match`, ranked by silhouettes, or
by appearance too with ``--start appearance``; with ``--candidates K`` > 1 the K best each get one
iteration of ``--refiner`` and the most confident is kept, as the predictor does). Reported: the
share whose chosen start is within 30 deg of GT (symmetry-aware: the closest pose of the object's
symmetry set), the share of the textured objects' starts that are flipped (> 150 deg), the median
error, the share for which one of the K candidates is within 30 deg, and seconds per instance; the
same per object (``per_object``: where the flips are).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from cosy_lite.geometry.symmetries import FLIPPED_DEG, WITHIN_DEG, rotation_errors_deg
from cosy_lite.inference.settings import InferenceConfig


def score_start(dataset_root: str | Path, start: str = "appearance", n_candidates: int = InferenceConfig.n_candidates,
                refiner: str | Path | None = None, split: str = "test", min_visib: float = 0.5, n: int | None = None,
                templates_cache: str | Path | None = None, seed: int = 0, progress: bool = True,
                scorer: str | Path | None = None) -> dict[str, Any]:
    """The numbers of the module doc as a dict (``within_30deg``, ``flipped_textured``,
    ``median_deg``, ``any_candidate_within_30deg``, ``seconds_per_instance``, ``instances``, ...)."""
    import torch
    from tqdm import tqdm

    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.data.pose_dataset import PoseDataset
    from cosy_lite.errors import CosyLiteError
    from cosy_lite.inference.object_meshes import ObjectMeshes, objects_and_renderer, start_templates
    from cosy_lite.nets.appearance_templates import textured_obj_ids
    from cosy_lite.nets.render_and_compare import refine_and_score
    from cosy_lite.weights.loaders import load_pose_model, load_scorer

    if n_candidates > 1 and refiner is None:
        raise CosyLiteError("--candidates > 1 chooses among the candidates with a refiner's confidence: give --refiner")
    ds = BopDataset(Path(dataset_root))
    items = PoseDataset(ds, split, min_visib_fract=min_visib)
    if len(items) == 0:
        raise CosyLiteError(f"{dataset_root}: no instance with a visible fraction >= {min_visib} in split {split!r}")
    order = np.random.default_rng(seed).permutation(len(items))[:n] if n else np.arange(len(items))
    model = None if refiner is None else load_pose_model(refiner, "refiner")
    models = ObjectMeshes(ds.models_dir)
    obj_ids = sorted(ds.models_info)
    objects, renderer, _ = objects_and_renderer(models, obj_ids, None, icp=False,
                                                shading=model.render_shading if model else "headlight")
    if scorer is not None and start != "appearance":
        raise CosyLiteError(f"--scorer {scorer}: a coarse scorer ranks the appearance templates (--start appearance)")
    scorer_net = None if scorer is None else load_scorer(scorer).net
    templates = start_templates(start, models, objects, renderer, templates_cache, scorer_net)
    assert templates is not None
    textured = set(textured_obj_ids(renderer, obj_ids))
    chosen, best, obj_of = [], [], []  # per matched instance: chosen start's error, best candidate's, object
    seconds = 0.0
    with torch.no_grad():
        for r in tqdm(order.tolist(), desc=f"score start ({start})", unit="instance", disable=not progress):
            it = items[r]
            o = int(objects.index([it.obj_id])[0])
            symmetries = objects.symmetries[o][objects.sym_mask[o]][:, :3, :3].double().numpy()
            templates.templates(it.obj_id)  # rendered (or read) outside the timing
            if templates.appearance is not None:
                templates.appearance.descriptors(it.obj_id)
            t0 = time.perf_counter()
            K = it.K.double().numpy()
            rgb = it.rgb.permute(1, 2, 0).numpy()
            m = templates.match(it.mask.numpy()[None], [it.obj_id], K, n_candidates,
                                rgb=rgb if start == "appearance" else None)
            if not m.found[0]:
                continue
            candidates = torch.from_numpy(m.TCO[0]).float()
            pick = 0
            if n_candidates > 1:
                assert model is not None  # candidates > 1 needs a refiner (checked above)
                k = len(candidates)
                _, confidence = refine_and_score(model.net, it.rgb.float()[None].expand(k, -1, -1, -1) / 255,
                                                 it.K[None].expand(k, 3, 3), candidates, [it.obj_id] * k,
                                                 objects.points[[o] * k], renderer, model.crop_resolution)
                pick = int(confidence.argmax())
            seconds += time.perf_counter() - t0
            err = rotation_errors_deg(candidates[:, :3, :3].double().numpy(), it.TCO[:3, :3].double().numpy(), symmetries)
            chosen.append(float(err[pick]))
            best.append(float(err.min()))
            obj_of.append(it.obj_id)
    renderer.close()
    if not chosen:
        raise CosyLiteError(f"{dataset_root}: no instance could be matched (every mask empty)")
    return {"split": split, "start": start, "candidates": n_candidates, "refiner": None if refiner is None else str(refiner),
            "scorer": None if scorer is None else str(scorer), "min_visib": min_visib,
            **start_errors_summary(np.array(chosen), np.array(best), np.array(obj_of), textured),
            "seconds_per_instance": seconds / len(chosen)}


def start_errors_summary(chosen: np.ndarray, best: np.ndarray, obj_ids: np.ndarray, textured: set[int]) -> dict[str, Any]:
    """The shares of :func:`score_start` from per-instance rotation errors (deg): ``chosen`` [N] of the
    chosen start, ``best`` [N] of the best candidate, ``obj_ids`` [N]; flips counted on ``textured``
    objects only (None where there is none). ``per_object``: the same per object id (as a string)."""

    def summary(sel: np.ndarray) -> dict[str, Any]:
        tex = sel & np.isin(obj_ids, sorted(textured))
        return {"instances": int(sel.sum()), "textured_instances": int(tex.sum()),
                "within_30deg": float(np.mean(chosen[sel] < WITHIN_DEG)),
                "flipped_textured": float(np.mean(chosen[tex] > FLIPPED_DEG)) if tex.any() else None,
                "median_deg": float(np.median(chosen[sel])),
                "any_candidate_within_30deg": float(np.mean(best[sel] < WITHIN_DEG))}

    out = summary(np.ones(len(chosen), bool))
    out["per_object"] = {str(o): summary(obj_ids == o) for o in sorted(set(obj_ids.tolist()))}
    return out


def add_arguments(p: argparse.ArgumentParser) -> None:
    from cosy_lite.inference.starts import TEMPLATE_STARTS

    p.add_argument("--dataset", default="ycbvsynth", help="dataset name (folder under $COSY_LITE_DATA or ./data) or path")
    p.add_argument("--split", default="test")
    p.add_argument("--start", choices=TEMPLATE_STARTS, default="appearance")
    p.add_argument("--candidates", type=int, default=InferenceConfig.n_candidates,
                   help="> 1: the most confident of the K best (needs --refiner)")
    p.add_argument("--refiner", default=None, metavar="FILE_OR_NAME",
                   help="refiner checkpoint / .safetensors or reference set name (for --candidates > 1)")
    p.add_argument("--scorer", default=None, metavar="FILE_OR_NAME",
                   help="--start appearance: the coarse scorer (a file, or a reference set name: its scorer)")
    p.add_argument("--min-visib", type=float, default=0.5, help="instances at least this visible")
    p.add_argument("-n", type=int, default=None, help="at most this many instances (drawn with --seed)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--templates-cache", type=Path, default=None, metavar="DIR")
    p.add_argument("--out", type=Path, default=None, metavar="JSON", help="also write the numbers here")
    p.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from cosy_lite.bop.folders import dataset_folder
    from cosy_lite.errors import CosyLiteError
    from cosy_lite.render.gl import use_egl
    from cosy_lite.weights.reference_models import reference_models, reference_names

    use_egl()
    refiner = args.refiner
    if refiner is not None and refiner in reference_names():
        refiner = reference_models(refiner).path("refiner")
    scorer = args.scorer
    if scorer is not None and scorer in reference_names():
        name, scorer = scorer, reference_models(scorer).path("scorer")
        if scorer is None:
            raise CosyLiteError(f"--scorer {name}: the reference set {name!r} has no scorer")
    out = score_start(dataset_folder(args.dataset, None), args.start, args.candidates, refiner, args.split,
                      args.min_visib, args.n, args.templates_cache, args.seed, progress=not args.no_progress, scorer=scorer)
    print(json.dumps(out, indent=1))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1) + "\n")
    return 0
