"""Evaluate a BOP19 results CSV against a BOP dataset: errors of every evaluated estimate, then scores.

Follows bop_toolkit ``eval_bop19_pose.py``: only the BOP19 targets are evaluated; per target the
top ``inst_count`` estimates by score (stable sort, CSV order on ties) are compared with every GT
instance of the object in the image. Models are the ``models_eval`` meshes; each estimate and
each GT pose is rendered once (depth only); symmetry sets and vertices are prepared once per object.
"""

from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.bop.results import PoseEstimate, read_results_csv
from cosy_lite.errors import BopFormatError
from cosy_lite.eval import pose_errors
from cosy_lite.eval.scoring import VISIB_GT_MIN, VSD_TAUS, Scores, TargetErrors, score_targets, valid_gt


@dataclass
class EvalResult:
    """Everything computed by :func:`evaluate`."""

    dataset: str
    split: str
    results_path: str
    n_estimates_in_file: int
    n_estimates_evaluated: int
    vsd_delta: float  # m
    im_width: int
    visib_gt_min: float
    scores: Scores
    targets: list[TargetErrors]
    seconds: float  # wall time of the evaluation

    def to_dict(self) -> dict:
        """JSON-ready dict with every number (thresholds, recalls, AR, per-object scores)."""
        from cosy_lite.eval.scoring import MSSD_THRESHOLDS, VSD_THETAS

        s = self.scores

        def metric_block(x) -> dict:
            return {
                "ar": x.ar, "ar_vsd": x.ar_vsd, "ar_mssd": x.ar_mssd, "ar_mspd": x.ar_mspd,
                "recall_vsd": x.recall_vsd.tolist(), "recall_mssd": x.recall_mssd.tolist(),
                "recall_mspd": x.recall_mspd.tolist(), "auc_add_s": x.auc_add_s, "auc_adi": x.auc_adi,
            }

        return {
            "dataset": self.dataset, "split": self.split, "results": self.results_path,
            "n_estimates_in_file": self.n_estimates_in_file, "n_estimates_evaluated": self.n_estimates_evaluated,
            "n_targets": s.n_targets, "seconds": self.seconds,
            "thresholds": {
                "vsd_delta_m": self.vsd_delta, "vsd_taus_x_diameter": VSD_TAUS.tolist(),
                "vsd_thetas": VSD_THETAS.tolist(), "mssd_x_diameter": MSSD_THRESHOLDS.tolist(),
                "mspd_px": s.mspd_thresholds_px.tolist(), "im_width": self.im_width, "visib_gt_min": self.visib_gt_min,
            },
            **metric_block(s),
            "per_object": {
                str(o): {"n_targets": x.n_targets, "n_estimates": x.n_estimates, **metric_block(x)}
                for o, x in s.per_object.items()
            },
        }


@dataclass
class _ObjectData:
    pts: np.ndarray  # [N,3] models_eval vertices (m)
    syms: np.ndarray  # [S,4,4]
    diameter: float  # m


def _top_estimates(estimates: list[PoseEstimate]) -> dict[tuple[int, int, int], list[PoseEstimate]]:
    """(scene, im, obj) -> estimates sorted by decreasing score (stable: file order on ties)."""
    out: dict[tuple[int, int, int], list[PoseEstimate]] = defaultdict(list)
    for e in estimates:
        out[(e.scene_id, e.im_id, e.obj_id)].append(e)
    return {k: sorted(v, key=lambda e: -e.score) for k, v in out.items()}


def evaluate(
    dataset_root: str | Path,
    results_csv: str | Path,
    split: str | None = None,
    name: str | None = None,
    max_sym_disc_step: float = 0.01,
    sym_zero_angle: bool = True,
    visib_gt_min: float = VISIB_GT_MIN,
    progress: bool = True,
) -> EvalResult:
    """Compute VSD, MSSD, MSPD, ADD and ADI of every evaluated estimate and score them (BOP19).

    Args:
        dataset_root: BOP dataset folder (``models_eval/``, ``test_targets_bop19.json``, test split).
        results_csv: BOP19 results CSV (validate it first with ``check_results``).
        split: split folder (default: the dataset's test split from the parameter table, else ``test``).
        name: dataset name for the parameter table (default: the folder name).
        max_sym_disc_step, sym_zero_angle: discretisation of continuous symmetries (see
            :func:`cosy_lite.geometry.symmetries.symmetry_transforms`; True = current bop_toolkit,
            False = the toolkit of the BOP 2019-2022 evaluations).
        visib_gt_min: which GT instances are targets (see :func:`cosy_lite.eval.scoring.valid_gt`;
            default -1 = the ``inst_count`` most visible, as the toolkit's BOP19 evaluation).
        progress: show a tqdm bar over images.
    """
    from tqdm import tqdm

    from cosy_lite.bop.params import DATASETS
    from cosy_lite.geometry.depth import depth_to_distance
    from cosy_lite.geometry.symmetries import symmetry_transforms
    from cosy_lite.render.object_renderer import ObjectRenderer

    t0 = time.perf_counter()
    ds = BopDataset(Path(dataset_root), name or "")
    params = DATASETS.get(ds.name)
    split = split or (params.test_split if params is not None else "test")
    delta = (params.vsd_delta_mm if params is not None else 15.0) * 1e-3
    symmetric = params.symmetric_obj_ids if params is not None else ()
    estimates = read_results_csv(results_csv)
    top = _top_estimates(estimates)
    targets = ds.test_targets()
    by_image: dict[tuple[int, int], list] = defaultdict(list)
    for t in targets:
        by_image[(t.scene_id, t.im_id)].append(t)

    info = ds.models_info
    target_objs = sorted({t.obj_id for t in targets})
    meshes = {o: ds.load_model(o, eval=True) for o in target_objs}
    objs = {
        o: _ObjectData(np.asarray(meshes[o].vertices, dtype=np.float64),
                       symmetry_transforms(info[o], max_sym_disc_step, include_zero_angle=sym_zero_angle), info[o].diameter)
        for o in target_objs
    }
    renderers: dict[tuple[int, int], ObjectRenderer] = {}  # one per image size (GL meshes bind to one context)
    sp = ds.split_params(split)
    im_width = sp.im_size[0] if sp is not None else 0

    out: list[TargetErrors] = []
    n_eval = 0
    try:
        bar = tqdm(sorted(by_image.items()), desc="eval", unit="im", disable=not progress)
        for (scene_id, im_id), im_targets in bar:
            rec = ds.image(split, scene_id, im_id)
            if rec.gt_info is None or len(rec.gt_info) != len(rec.gt):
                raise BopFormatError(ds.scene_dir(split, scene_id) / "scene_gt_info.json", str(im_id),
                                     "GT info (visib_fract) needed for every GT instance")
            work = []  # (target, ests, gt indices)
            for t in im_targets:
                ests = top.get((scene_id, im_id, t.obj_id), [])[: t.inst_count]
                gt_idx = [i for i, g in enumerate(rec.gt) if g.obj_id == t.obj_id]
                work.append((t, ests, gt_idx))
            if not any(ests and gi for _, ests, gi in work):
                for t, ests, gi in work:
                    out.append(_errors_without_render(t, ests, gi, rec, visib_gt_min))
                    n_eval += len(ests)
                continue
            depth = ds.load_depth(rec)
            h, w = depth.shape
            im_width = im_width or w
            K = rec.camera.K
            dist_test = depth_to_distance(depth, K)
            # Render every estimate and GT pose of this image once, in one batch.
            ids, poses = [], []
            for t, ests, gi in work:
                if ests and gi:
                    ids += [t.obj_id] * (len(ests) + len(gi))
                    poses += [e.TCO for e in ests] + [rec.gt[i].TCO for i in gi]
            if (w, h) not in renderers:
                renderers[(w, h)] = ObjectRenderer(meshes)
            renderer = renderers[(w, h)]
            _, depths = renderer.render(ids, np.stack(poses), K, w, h, depth_only=True)
            dists = [depth_to_distance(d, K) for d in depths]
            k = 0
            for t, ests, gi in work:
                if not (ests and gi):
                    out.append(_errors_without_render(t, ests, gi, rec, visib_gt_min))
                    n_eval += len(ests)
                    continue
                d_est, d_gt = dists[k:k + len(ests)], dists[k + len(ests):k + len(ests) + len(gi)]
                k += len(ests) + len(gi)
                out.append(_target_errors(t, ests, gi, rec, objs[t.obj_id], K, d_est, d_gt, dist_test, delta, visib_gt_min))
                n_eval += len(ests)
            bar.set_postfix(estimates=n_eval)
    finally:
        for r in renderers.values():
            r.delete()
    scores = score_targets(out, {o: d.diameter for o, d in objs.items()}, im_width, symmetric)
    return EvalResult(ds.name, split, str(results_csv), len(estimates), n_eval, delta, im_width, visib_gt_min, scores, out,
                      time.perf_counter() - t0)


def _gt_valid(rec, gt_idx: list[int], inst_count: int, visib_gt_min: float) -> np.ndarray:
    return valid_gt(np.array([rec.gt_info[i].visib_fract for i in gt_idx]), inst_count, visib_gt_min)


def _errors_without_render(t, ests, gt_idx, rec, visib_gt_min: float) -> TargetErrors:
    """A target with no estimate or no GT instance: nothing to compare."""
    te = TargetErrors.empty(t.scene_id, t.im_id, t.obj_id, t.inst_count, _gt_valid(rec, gt_idx, t.inst_count, visib_gt_min))
    te.scores = np.array([e.score for e in ests], dtype=np.float64)
    E, G = len(ests), len(gt_idx)  # one of them is 0
    te.vsd, te.mssd, te.mspd, te.add, te.adi = np.ones((E, G, len(VSD_TAUS))), *(np.full((E, G), np.inf) for _ in range(4))
    return te


def _target_errors(t, ests, gt_idx, rec, obj: _ObjectData, K, d_est, d_gt, dist_test, delta, visib_gt_min) -> TargetErrors:
    E, G = len(ests), len(gt_idx)
    vsd = np.ones((E, G, len(VSD_TAUS)))
    mssd, mspd, add, adi = (np.full((E, G), np.inf) for _ in range(4))
    taus = VSD_TAUS * obj.diameter
    T_est_all = np.stack([e.TCO for e in ests])
    for g, gi in enumerate(gt_idx):
        T_gt = rec.gt[gi].TCO
        mssd[:, g], mspd[:, g] = pose_errors.mssd_mspd(T_est_all, T_gt, K, obj.pts, obj.syms)
        for e, T_est in enumerate(T_est_all):
            if pose_errors.sphere_projections_overlap(0.5 * obj.diameter, T_est[:3, 3], T_gt[:3, 3]):
                vsd[e, g] = pose_errors.vsd(d_est[e], d_gt[g], dist_test, delta, taus)
            # The toolkit's shortcut: MSSD is inf when the bounding spheres do not overlap.
            if np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]) >= obj.diameter:
                mssd[e, g] = np.inf
            add[e, g] = pose_errors.add(T_est, T_gt, obj.pts)
            adi[e, g] = pose_errors.adi(T_est, T_gt, obj.pts)
    return TargetErrors(t.scene_id, t.im_id, t.obj_id, t.inst_count, np.array([e.score for e in ests], dtype=np.float64),
                        _gt_valid(rec, gt_idx, t.inst_count, visib_gt_min), vsd, mssd, mspd, add, adi)
