"""BOP19 scoring: greedy matching, recalls, Average Recall (AR), and the YCB-V AUC of ADD(-S).

Semantics of bop_toolkit ``eval_calc_scores.py`` / ``score.py`` (``match_poses``,
``calc_localization_scores``) with the BOP19 settings: per target (image, object) the estimates
are the top ``inst_count`` by score; for each threshold, estimates in decreasing score take the
lowest-error unmatched valid GT instance (strict ``<``, first in GT order on ties) if that error is
below the threshold. Valid GT (see :func:`valid_gt`): the toolkit's BOP19 default
(``visib_gt_min = -1``) takes the ``inst_count`` most visible instances of the object; with
``visib_gt_min >= 0`` those with ``visib_fract >= visib_gt_min``. On BOP datasets both give the
instances with ``visib_fract >= 0.1`` (that is how ``inst_count`` was made). Invalid instances can
be neither matched nor counted. Recall = matched valid GT / valid GT, pooled over all targets; 0
when there is none. Errors are normalised as the toolkit does before thresholding (MSSD / diameter,
MSPD x 640 / image width).

AUC of ADD(-S) (YCB-V, PoseCNN): per target, estimates in decreasing score take the lowest-error
free valid GT instance if that error is below 10 cm (the largest error the curve counts); each valid
GT instance contributes its matched error (inf if none). With one instance per object and image,
as in YCB-V, this is the usual per-instance AUC.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

VSD_TAUS = np.arange(0.05, 0.51, 0.05)  # x diameter (vsd_normalized_by_diameter)
VSD_THETAS = np.arange(0.05, 0.51, 0.05)  # correct if VSD error < theta
MSSD_THRESHOLDS = np.arange(0.05, 0.51, 0.05)  # x diameter
MSPD_THRESHOLDS_PX = np.arange(5, 51, 5).astype(np.float64)  # x image width / 640
VISIB_GT_MIN = -1.0  # the toolkit's BOP19 setting: the inst_count most visible GT instances are valid
AUC_MAX_M = 0.1  # YCB-V AUC of ADD(-S): thresholds 0..10 cm


@dataclass
class TargetErrors:
    """Errors of one BOP19 target (image, object): E estimates (top ``inst_count``, score-descending) x G GT.

    ``G`` counts every GT instance of the object in the image; ``gt_valid`` marks the targets.
    """

    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int
    scores: np.ndarray  # [E] descending
    gt_valid: np.ndarray  # [G] bool, see valid_gt
    vsd: np.ndarray  # [E,G,T] errors in [0,1] per tau of VSD_TAUS
    mssd: np.ndarray  # [E,G] m
    mspd: np.ndarray  # [E,G] px
    add: np.ndarray  # [E,G] m
    adi: np.ndarray  # [E,G] m

    @property
    def n_valid(self) -> int:
        return int(np.count_nonzero(self.gt_valid))

    @staticmethod
    def empty(scene_id: int, im_id: int, obj_id: int, inst_count: int, gt_valid: np.ndarray) -> TargetErrors:
        """A target without estimates."""
        G = len(gt_valid)
        return TargetErrors(
            scene_id, im_id, obj_id, inst_count, np.zeros(0), np.asarray(gt_valid, dtype=bool),
            np.zeros((0, G, len(VSD_TAUS))), *(np.zeros((0, G)) for _ in range(4)),
        )


def valid_gt(visib_fract: np.ndarray, inst_count: int, visib_gt_min: float = VISIB_GT_MIN) -> np.ndarray:
    """Which GT instances of one target (image, object) may be matched and are counted.

    Args:
        visib_fract: [G] visible fractions of the object's GT instances, in GT order.
        inst_count: the target's ``inst_count``.
        visib_gt_min: < 0: the ``inst_count`` most visible (stable: GT order on ties), as the
            toolkit's BOP19 evaluation; >= 0: every instance with ``visib_fract >= visib_gt_min``.
    Returns:
        [G] bool.
    """
    v = np.asarray(visib_fract, dtype=np.float64).reshape(-1)
    if visib_gt_min >= 0:
        return v >= visib_gt_min
    valid = np.zeros(len(v), dtype=bool)
    valid[np.argsort(-v, kind="stable")[:inst_count]] = True
    return valid


def match_greedy(errors: np.ndarray, gt_valid: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """Greedy matching of the toolkit's ``match_poses``, for K thresholds at once.

    Args:
        errors: [E,G] or [E,G,K] errors, estimates in decreasing score order (NaN = inf).
        gt_valid: [G] bool, GT instances that may be matched.
        thresholds: [K] an estimate matches its best GT if that error is < threshold.
    Returns:
        [K,G] index of the estimate matched to each GT, -1 if none.
    """
    th = np.asarray(thresholds, dtype=np.float64).reshape(-1)
    errors = np.nan_to_num(np.asarray(errors, dtype=np.float64), nan=np.inf)
    E, G = errors.shape[:2]
    K = len(th)
    err = np.broadcast_to(errors if errors.ndim == 3 else errors[:, :, None], (E, G, K))
    valid = np.asarray(gt_valid, dtype=bool).reshape(G)
    match = np.full((K, G), -1, dtype=np.int64)
    if G == 0:
        return match
    rows = np.arange(K)
    for e in range(E):
        cand = np.where(valid[None, :] & (match < 0), err[e].T, np.inf)  # [K,G]
        best = cand.argmin(axis=1)
        ok = cand[rows, best] < th
        match[rows[ok], best[ok]] = e
    return match


def auc_threshold_curve(errors: np.ndarray, max_error: float = AUC_MAX_M) -> float:
    """Area under the accuracy-vs-threshold curve for thresholds 0..``max_error``, normalised to [0,1].

    ``errors``: [M] one per GT target (inf = missed). accuracy(t) = fraction of errors <= t; its exact
    integral is ``mean(max(0, max_error - e)) / max_error``. (PoseCNN's VOC-style sum, used by
    CosyPose, is a right-endpoint sum of the same curve: at most 1/M higher.) 0 if M = 0.
    """
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    if len(e) == 0:
        return 0.0
    return float(np.clip(max_error - np.nan_to_num(e, nan=np.inf), 0.0, None).mean() / max_error)


class _AverageRecalls:
    """AR_VSD, AR_MSSD, AR_MSPD (means of the recall arrays) and AR (their mean)."""

    recall_vsd: np.ndarray
    recall_mssd: np.ndarray
    recall_mspd: np.ndarray

    @property
    def ar_vsd(self) -> float:
        return float(self.recall_vsd.mean())

    @property
    def ar_mssd(self) -> float:
        return float(self.recall_mssd.mean())

    @property
    def ar_mspd(self) -> float:
        return float(self.recall_mspd.mean())

    @property
    def ar(self) -> float:
        return (self.ar_vsd + self.ar_mssd + self.ar_mspd) / 3.0


@dataclass
class ObjectScores(_AverageRecalls):
    """Scores of one object (its targets only)."""

    obj_id: int
    n_targets: int  # valid GT instances
    n_estimates: int  # estimates evaluated (top inst_count)
    recall_vsd: np.ndarray  # [T,Theta]
    recall_mssd: np.ndarray  # [10]
    recall_mspd: np.ndarray  # [10]
    auc_add_s: float | None  # ADD, or ADI for symmetric objects (None: not computed)
    auc_adi: float | None


@dataclass
class Scores(_AverageRecalls):
    """Dataset-level scores; recalls pooled over all targets."""

    n_targets: int
    n_estimates: int
    recall_vsd: np.ndarray  # [T,Theta] tau of VSD_TAUS (rows) x theta of VSD_THETAS (columns)
    recall_mssd: np.ndarray  # [10] at MSSD_THRESHOLDS x diameter
    recall_mspd: np.ndarray  # [10] at MSPD_THRESHOLDS_PX x width/640
    mspd_thresholds_px: np.ndarray  # [10] after the width scaling
    auc_add_s: float | None  # None: ADD/ADI not computed (BOP19 proper has no AUC)
    auc_adi: float | None
    per_object: dict[int, ObjectScores] = field(default_factory=dict)


def _recall(tps: np.ndarray, n: int) -> np.ndarray:
    return tps / n if n > 0 else np.zeros_like(tps, dtype=np.float64)


def score_targets(
    targets: list[TargetErrors], diameters: dict[int, float], im_width: int, symmetric_obj_ids: tuple[int, ...] = (),
    auc: bool = True,
) -> Scores:
    """Recalls, AR and AUC over BOP19 targets.

    Args:
        targets: one :class:`TargetErrors` per (scene, image, object) target, with or without estimates.
        diameters: obj_id -> model diameter (m) for the MSSD thresholds.
        im_width: test image width (px); MSPD thresholds are scaled by ``im_width / 640``.
        symmetric_obj_ids: objects scored with ADI in the AUC of ADD(-S).
        auc: score the AUC of ADD(-S) and of ADI (the targets' ``add``/``adi`` were computed); else
            ``auc_add_s`` and ``auc_adi`` are None.
    """
    mspd_th = MSPD_THRESHOLDS_PX * (im_width / 640.0)  # reported; matching uses normalised errors
    mspd_factor = 640.0 / im_width if im_width > 0 else 1.0
    T, Th = len(VSD_TAUS), len(VSD_THETAS)
    vsd_th = np.tile(VSD_THETAS, T)  # K = T*Theta, tau-major
    def zeros() -> dict[str, np.ndarray]:
        return {"vsd": np.zeros(T * Th), "mssd": np.zeros(len(MSSD_THRESHOLDS)), "mspd": np.zeros(len(mspd_th))}

    tp: dict[int, dict[str, np.ndarray]] = defaultdict(zeros)
    n_gt: dict[int, int] = defaultdict(int)
    n_est: dict[int, int] = defaultdict(int)
    auc_err: dict[str, dict[int, list[float]]] = {"add_s": defaultdict(list), "adi": defaultdict(list)}
    for t in targets:
        o = t.obj_id
        n_gt[o] += t.n_valid
        n_est[o] += len(t.scores)
        if len(t.scores) and len(t.gt_valid):
            vsd_err = np.repeat(t.vsd, Th, axis=2)  # [E,G,T*Theta]
            tp[o]["vsd"] += (match_greedy(vsd_err, t.gt_valid, vsd_th) >= 0).sum(axis=1)
            tp[o]["mssd"] += (match_greedy(t.mssd / diameters[o], t.gt_valid, MSSD_THRESHOLDS) >= 0).sum(axis=1)
            tp[o]["mspd"] += (match_greedy(t.mspd * mspd_factor, t.gt_valid, MSPD_THRESHOLDS_PX) >= 0).sum(axis=1)
        else:
            tp[o]  # noqa: B018 (creates the zero entry)
        if not auc:
            continue
        valid_idx = np.nonzero(t.gt_valid)[0]
        for name, errs in (("add_s", t.adi if o in symmetric_obj_ids else t.add), ("adi", t.adi)):
            m = match_greedy(errs, t.gt_valid, np.array([AUC_MAX_M]))[0]  # errors >= 10 cm add nothing to the AUC
            auc_err[name][o] += [float(errs[m[g], g]) if m[g] >= 0 else np.inf for g in valid_idx]

    def auc_of(errors: list[float]) -> float | None:
        return auc_threshold_curve(np.array(errors)) if auc else None

    per_object = {}
    for o in sorted(tp):
        per_object[o] = ObjectScores(
            o, n_gt[o], n_est[o], _recall(tp[o]["vsd"], n_gt[o]).reshape(T, Th), _recall(tp[o]["mssd"], n_gt[o]),
            _recall(tp[o]["mspd"], n_gt[o]), auc_of(auc_err["add_s"][o]), auc_of(auc_err["adi"][o]),
        )
    n_all = sum(n_gt.values())
    tot = zeros()
    for o in tp:
        for k in tot:
            tot[k] += tp[o][k]
    all_err = {k: [e for o in v for e in v[o]] for k, v in auc_err.items()}
    return Scores(
        n_all, sum(n_est.values()), _recall(tot["vsd"], n_all).reshape(T, Th), _recall(tot["mssd"], n_all),
        _recall(tot["mspd"], n_all), mspd_th, auc_of(all_err["add_s"]), auc_of(all_err["adi"]), per_object,
    )


def ar_core(ar_by_dataset: dict[str, float], core: tuple[str, ...] | None = None) -> float:
    """AR_Core of the BOP Challenge: the mean of the per-dataset AR over the core datasets.

    Args:
        ar_by_dataset: dataset name -> AR (mean of AR_VSD, AR_MSSD, AR_MSPD) of that dataset.
        core: the datasets to average (default :data:`cosy_lite.bop.params.BOP_CORE`).
    Raises:
        KeyError naming the core datasets without a score (the challenge needs all of them).
    """
    from cosy_lite.bop.params import BOP_CORE

    core = BOP_CORE if core is None else core
    missing = [d for d in core if d not in ar_by_dataset]
    if missing:
        raise KeyError(f"AR_Core needs an AR for every core dataset; missing: {missing}")
    return float(np.mean([ar_by_dataset[d] for d in core]))
