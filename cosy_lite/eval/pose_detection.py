"""BOP 2024/2025 6D object detection: average precision over MSSD and MSPD thresholds.

The rules of bop_toolkit ``eval_bop24_pose.py`` (with ``eval_calc_errors.py`` and
``eval_calc_scores.py`` in ``--eval_mode=detection``, ``pose_matching.match_poses``,
``score.calc_pose_detection_scores``, ``score.calc_ap``):

* Per image, only the 100 highest-scoring estimates are kept (stable sort: file order on ties;
  estimates of every object count). Only images of ``test_targets_bop24.json`` are evaluated.
* Per image, each object of the image's GT (in order of first appearance) is a group: its
  estimates (decreasing score, stable) against all of its GT instances, whatever their visibility.
  Estimates of objects without a GT instance in the image are not evaluated at all (neither true
  nor false positives), as in the toolkit.
* Per threshold, greedy matching (:func:`cosy_lite.eval.scoring.match_greedy`, every GT valid):
  estimates in decreasing score take the lowest-error unmatched GT if that error is below the
  threshold. Errors: MSSD / diameter (thresholds 0.05..0.5), MSSD in mm (2..20 mm), MSPD x 640 /
  image width (5..50 px); MSSD is +inf where the bounding spheres do not overlap.
* GT with ``visib_fract < 0.1`` are ignored: not counted, and an estimate matched to one is
  dropped. Every other unmatched estimate is a false positive.
* Per object and threshold, the estimates of all images sorted by decreasing score (stable, in
  the order scenes / images first appear in the targets file, objects in GT order) give the
  precision/recall curve; AP = COCO's 101-point interpolated precision (``calc_ap``). The object's
  score is the mean AP over the thresholds; objects without a counted GT instance are left out;
  mAP = mean over objects. ``bop24_mAP`` = mean of the MSSD and MSPD mAP; ``bop25_mAP`` = MSSD mAP.
"""

from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cosy_lite.bop.io import image_header
from cosy_lite.bop.results import PoseEstimate
from cosy_lite.eval.scoring import MSPD_THRESHOLDS_PX, MSSD_THRESHOLDS, match_greedy

MAX_ESTIMATES_PER_IMAGE = 100  # the toolkit's max_num_estimates_per_image (xyzibd: 200)
VISIB_GT_MIN = 0.1  # GT less visible than this are ignored
MSSD_MM_THRESHOLDS = np.arange(2, 21, 2).astype(np.float64)  # mm, not normalised (bop25_mAP_mm)
RECALL_POINTS = np.linspace(0.0, 1.00, 101, endpoint=True)  # COCO's recall thresholds
ERROR_TYPES = ("mssd", "mssd_mm", "mspd")


@dataclass
class GroupErrors:
    """Errors of one object in one image: E estimates (decreasing score) x G GT instances of it."""

    scene_id: int
    im_id: int
    obj_id: int
    scores: np.ndarray  # [E]
    gt_visib_fract: np.ndarray  # [G]
    mssd: np.ndarray  # [E,G] m (inf: bounding spheres apart)
    mspd: np.ndarray  # [E,G] px
    im_width: int


def top_per_image(estimates: list[PoseEstimate], n: int = MAX_ESTIMATES_PER_IMAGE) -> tuple[list[PoseEstimate], int]:
    """The ``n`` best estimates of each image (stable sort by decreasing score), images in order of first
    appearance, each image's estimates score-sorted; and the number dropped (toolkit ``load_bop_results``)."""
    by_image: dict[tuple[int, int], list[PoseEstimate]] = defaultdict(list)
    for e in estimates:
        by_image[(e.scene_id, e.im_id)].append(e)
    kept: list[PoseEstimate] = []
    dropped = 0
    for ests in by_image.values():
        ests = sorted(ests, key=lambda e: e.score, reverse=True)
        kept += ests[:n]
        dropped += max(0, len(ests) - n)
    return kept, dropped


def average_precision(recall: np.ndarray, precision: np.ndarray) -> float:
    """COCO-style AP (the toolkit's ``score.calc_ap``): the mean over 101 recall thresholds r of the
    highest precision at a recall >= r, after adding the points (0, 0) and (1, 0)."""
    mrec = np.concatenate(([0.0], np.asarray(recall, dtype=np.float64), [1.0]))
    mpre = np.concatenate(([0.0], np.asarray(precision, dtype=np.float64), [0.0]))
    return float(np.mean([mpre[mrec >= r].max() if np.any(mrec >= r) else 0.0 for r in RECALL_POINTS]))


def _normalised(g: GroupErrors, error_type: str, diameter_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(errors [E,G] in the unit of the thresholds, thresholds [K])."""
    if error_type == "mssd":
        return g.mssd / diameter_m, MSSD_THRESHOLDS
    if error_type == "mssd_mm":
        return g.mssd * 1000.0, MSSD_MM_THRESHOLDS
    return g.mspd * (640.0 / g.im_width), MSPD_THRESHOLDS_PX


def object_average_precisions(groups: list[GroupErrors], error_type: str, diameter_m: float,
                              visib_gt_min: float = VISIB_GT_MIN) -> tuple[np.ndarray, int]:
    """AP [K] per threshold of ``error_type`` for one object, and its number of counted GT instances.

    ``groups``: the object's (image, object) groups in the toolkit's order (see the module docstring).
    """
    K = len(_normalised(groups[0], error_type, diameter_m)[1]) if groups else len(MSSD_THRESHOLDS)
    n_gt = int(sum(np.count_nonzero(g.gt_visib_fract >= visib_gt_min) for g in groups))
    scores: list[np.ndarray] = []
    tp: list[np.ndarray] = []  # [K,E] per group: 1 matched to a counted GT, 0 false positive
    keep: list[np.ndarray] = []  # [K,E] per group: False where matched to an ignored GT
    for g in groups:
        err, th = _normalised(g, error_type, diameter_m)
        E, G = err.shape
        match = match_greedy(err, np.ones(G, dtype=bool), th)  # [K,G] estimate index per GT
        matched = np.zeros((K, E), dtype=bool)
        ignored = np.zeros((K, E), dtype=bool)
        counted = g.gt_visib_fract >= visib_gt_min
        for k, gi in zip(*np.nonzero(match >= 0)):
            (matched if counted[gi] else ignored)[k, match[k, gi]] = True
        scores.append(g.scores)
        tp.append(matched)
        keep.append(~ignored)
    aps = np.zeros(K)
    if n_gt == 0 or not scores:
        return aps, n_gt
    all_scores = np.concatenate(scores)
    all_tp, all_keep = np.concatenate(tp, axis=1), np.concatenate(keep, axis=1)
    for k in range(K):
        s, t = all_scores[all_keep[k]], all_tp[k][all_keep[k]]
        order = np.argsort(-s, kind="stable")  # = sorted(..., reverse=True) of the toolkit
        t = t[order]
        tps, fps = np.cumsum(t), np.cumsum(~t)
        recall = tps / float(n_gt)
        with np.errstate(divide="ignore", invalid="ignore"):
            precision = np.nan_to_num(tps / (tps + fps), nan=0.0, posinf=0.0)
        aps[k] = average_precision(recall, precision)
    return aps, n_gt


@dataclass
class DetectionScores6D:
    """Scores of the 6D detection task. ``ap[error_type][obj_id]``: AP [K] per threshold."""

    map: dict[str, float]  # error type -> mAP (mean over objects with counted GT of the mean AP over thresholds)
    ap: dict[str, dict[int, np.ndarray]]
    n_gt: dict[int, int]  # obj_id -> counted GT instances
    n_estimates: dict[int, int]  # obj_id -> evaluated estimates

    @property
    def bop24_map(self) -> float:
        return float(np.mean([self.map["mssd"], self.map["mspd"]]))

    @property
    def bop25_map(self) -> float:
        return self.map["mssd"]


def score_groups(groups: list[GroupErrors], diameters_m: dict[int, float], obj_ids: list[int] | None = None,
                 visib_gt_min: float = VISIB_GT_MIN) -> DetectionScores6D:
    """mAP per error type over ``obj_ids`` (default: the objects of ``groups``) from groups in the toolkit's order."""
    by_obj: dict[int, list[GroupErrors]] = defaultdict(list)
    for g in groups:
        by_obj[g.obj_id].append(g)
    obj_ids = sorted(by_obj) if obj_ids is None else list(obj_ids)
    ap: dict[str, dict[int, np.ndarray]] = {t: {} for t in ERROR_TYPES}
    n_gt: dict[int, int] = {}
    for o in obj_ids:
        for t in ERROR_TYPES:
            ap[t][o], n_gt[o] = object_average_precisions(by_obj.get(o, []), t, diameters_m.get(o, np.nan), visib_gt_min)
    counted = [o for o in obj_ids if n_gt[o] > 0]
    maps = {t: float(np.mean([ap[t][o].mean() for o in counted])) if counted else float("nan") for t in ERROR_TYPES}
    n_est = {o: int(sum(len(g.scores) for g in by_obj.get(o, []))) for o in obj_ids}
    return DetectionScores6D(maps, ap, n_gt, n_est)


@dataclass
class Detection6DResult:
    """Everything :func:`evaluate_6d_detection` computed."""

    dataset: str
    split: str
    results_path: str
    n_estimates_in_file: int
    n_estimates_dropped: int  # beyond the per-image maximum
    n_estimates_evaluated: int
    average_time_per_image: float  # s; -1 if some estimate has no time
    scores: DetectionScores6D
    seconds: float
    groups: list[GroupErrors] = field(default_factory=list)

    def to_dict(self) -> dict:
        s = self.scores
        return {
            "task": "6d-detection", "dataset": self.dataset, "split": self.split, "results": self.results_path,
            "n_estimates_in_file": self.n_estimates_in_file, "n_estimates_dropped": self.n_estimates_dropped,
            "n_estimates_evaluated": self.n_estimates_evaluated, "seconds": self.seconds,
            "bop24_mAP": s.bop24_map, "bop25_mAP": s.bop25_map, "bop25_mAP_mm": s.map["mssd_mm"],
            **{f"bop24_mAP_{t}": s.map[t] for t in ERROR_TYPES},
            "bop24_average_time_per_image": self.average_time_per_image,
            "thresholds": {"mssd_x_diameter": MSSD_THRESHOLDS.tolist(), "mssd_mm": MSSD_MM_THRESHOLDS.tolist(),
                           "mspd_px_at_640": MSPD_THRESHOLDS_PX.tolist(), "visib_gt_min": VISIB_GT_MIN,
                           "max_estimates_per_image": MAX_ESTIMATES_PER_IMAGE},
            "per_object": {str(o): {"n_gt": s.n_gt[o], "n_estimates": s.n_estimates[o],
                                    **{f"ap_{t}": s.ap[t][o].tolist() for t in ERROR_TYPES}} for o in s.n_gt},
        }


def average_time(estimates: list[PoseEstimate]) -> float:
    """Mean per-image time of the estimates (first time seen per image); -1 if any is unknown (< 0)."""
    times: dict[tuple[int, int], float] = {}
    for e in estimates:
        if e.time < 0:
            return -1.0
        times.setdefault((e.scene_id, e.im_id), e.time)
    return float(np.mean(list(times.values()))) if times else -1.0


def evaluate_6d_detection(dataset_root: str | Path, results_csv: str | Path, split: str | None = None,
                          name: str | None = None, max_sym_disc_step: float = 0.01,
                          max_per_image: int = MAX_ESTIMATES_PER_IMAGE, progress: bool = True) -> Detection6DResult:
    """Score a BOP19-format results CSV for the BOP 2024/2025 6D detection task.

    Args:
        dataset_root: BOP dataset folder (``models_eval/``, ``test_targets_bop24.json``, the test split).
        results_csv: results file (validate it first: ``check_results``; ``cosy-lite eval`` does).
        split: split folder (default: the dataset's test split from the parameter table, else ``test``).
        name: dataset name for the parameter table (default: the folder name).
        max_sym_disc_step: discretisation of continuous symmetries (BOP: 0.01).
    """
    from tqdm import tqdm

    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.results import read_results_csv
    from cosy_lite.eval.evaluator import eval_split
    from cosy_lite.eval.image_errors import mssd_mspd_errors
    from cosy_lite.eval.object_errors import ObjectErrors
    from cosy_lite.geometry.symmetries import symmetry_transforms

    t0 = time.perf_counter()
    ds = BopDataset(Path(dataset_root), name or "")
    split = eval_split(ds.name, split)
    estimates = read_results_csv(results_csv)
    kept, dropped = top_per_image(estimates, max_per_image)
    by_image_obj: dict[tuple[int, int, int], list[PoseEstimate]] = defaultdict(list)
    for e in kept:  # score-sorted per image, so per (image, object) too
        by_image_obj[(e.scene_id, e.im_id, e.obj_id)].append(e)
    # scenes in order of first appearance, images within a scene likewise (the toolkit's nested dicts)
    scenes: dict[int, dict[int, None]] = {}
    for t in ds.test_image_targets():
        scenes.setdefault(t.scene_id, {})[t.im_id] = None
    info = ds.models_info
    objs: dict[int, ObjectErrors] = {}

    def object_errors(o: int) -> ObjectErrors:
        if o not in objs:
            objs[o] = ObjectErrors.from_model(ds.load_model_geometry(o, eval=True)[0],
                                              symmetry_transforms(info[o], max_sym_disc_step), info[o].diameter)
        return objs[o]

    sp = ds.split_params(split)
    groups: list[GroupErrors] = []
    keys = [(s, i) for s, ims in scenes.items() for i in ims]
    for scene_id, im_id in tqdm(keys, desc="eval 6d-detection", unit="im", disable=not progress):
        rec = ds.image(split, scene_id, im_id)
        if rec.gt_info is None or len(rec.gt_info) != len(rec.gt):
            from cosy_lite.errors import BopFormatError

            raise BopFormatError(ds.scene_dir(split, scene_id) / "scene_gt_info.json", str(im_id),
                                 "GT info (visib_fract) needed for every GT instance")
        width = sp.im_size[0] if sp is not None else image_header(rec.rgb_path)[0][0]
        for o in dict.fromkeys(g.obj_id for g in rec.gt):
            ests = by_image_obj.get((scene_id, im_id, o), [])
            gt_idx = [i for i, g in enumerate(rec.gt) if g.obj_id == o]
            E, G = len(ests), len(gt_idx)
            mssd, mspd = np.full((E, G), np.inf), np.full((E, G), np.inf)
            if E:
                T_est = np.stack([e.TCO for e in ests])
                for j, gi in enumerate(gt_idx):
                    mssd[:, j], mspd[:, j] = mssd_mspd_errors(object_errors(o), T_est, rec.gt[gi].TCO, rec.camera.K)
            groups.append(GroupErrors(scene_id, im_id, o, np.array([e.score for e in ests], dtype=np.float64),
                                      np.array([rec.gt_info[i].visib_fract for i in gt_idx]), mssd, mspd, width))
    diameters = {o: i.diameter for o, i in info.items()}
    scores = score_groups(groups, diameters, ds.obj_ids)
    n_eval = sum(len(g.scores) for g in groups)
    return Detection6DResult(ds.name, split, str(results_csv), len(estimates), dropped, n_eval,
                             average_time(kept), scores, time.perf_counter() - t0, groups)


def format_table(result: Detection6DResult) -> str:
    """mAP per error type and per-object mean AP as aligned text."""
    s = result.scores
    head = f"{'object':>8} {'GT':>6} {'ests':>6} {'AP_MSSD':>8} {'AP_MSPD':>8} {'AP_MSSD_mm':>10}"
    lines = [f"{result.dataset} / {result.split} (6D detection, BOP 2024/2025): {result.n_estimates_evaluated} of "
             f"{result.n_estimates_in_file} estimates evaluated ({result.n_estimates_dropped} beyond "
             f"{MAX_ESTIMATES_PER_IMAGE} per image dropped), {result.seconds:.1f} s", head, "-" * len(head)]
    for o in s.n_gt:
        if s.n_gt[o] == 0:
            continue
        lines.append(f"{o:>8} {s.n_gt[o]:>6} {s.n_estimates[o]:>6} {s.ap['mssd'][o].mean():8.4f} "
                     f"{s.ap['mspd'][o].mean():8.4f} {s.ap['mssd_mm'][o].mean():10.4f}")
    lines += ["", f"bop24_mAP {s.bop24_map:.4f} (mean of MSSD {s.map['mssd']:.4f} and MSPD {s.map['mspd']:.4f}); "
              f"bop25_mAP {s.bop25_map:.4f}; bop25_mAP_mm {s.map['mssd_mm']:.4f}"]
    return "\n".join(lines)
