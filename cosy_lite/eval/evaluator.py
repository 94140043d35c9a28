"""Evaluate a BOP19 results CSV against a BOP dataset: errors of every evaluated estimate, then scores.

The rules of bop_toolkit ``eval_bop19_pose.py`` (with ``eval_calc_errors.py``,
``eval_calc_scores.py``, ``pose_matching.py``, ``score.py``), which this module follows:

* Only targets of ``test_targets_bop19.json`` are evaluated, keyed by (scene, image, object): a
  repeated entry replaces the earlier one. Estimates of other images or objects are ignored.
* Per target, the estimates are sorted by decreasing score with a stable sort (file order on equal
  scores) and the first ``inst_count`` are evaluated (``n_top = -1``); a target without estimates
  keeps its GT instances as misses.
* Each evaluated estimate is compared with every GT instance of its object in the image (see
  :mod:`cosy_lite.eval.image_errors` for VSD, MSSD, MSPD and the toolkit's shortcuts).
  Models are the ``models_eval`` meshes; symmetry sets as ``misc.get_symmetry_transformations``
  with ``max_sym_disc_step = 0.01``; VSD delta from the dataset table (15 mm, ITODD 5 mm),
  tau = 0.05..0.5 x diameter, costs normalised by the diameter.
* Scoring (:mod:`cosy_lite.eval.scoring`): valid GT, greedy matching per threshold, recall
  pooled over the dataset, AR = mean over thresholds, no rounding.
"""

from __future__ import annotations

import os
import threading
import time
from collections import defaultdict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Callable

import numpy as np

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.bop.io import Target
from cosy_lite.bop.results import PoseEstimate, read_results_csv
from cosy_lite.errors import BopFormatError
from cosy_lite.eval.depth_renderer import WindowDepthRenderer
from cosy_lite.eval.image_errors import ImageErrors
from cosy_lite.eval.object_errors import ObjectErrors
from cosy_lite.eval.scoring import VISIB_GT_MIN, Scores, TargetErrors, score_targets, valid_gt


@dataclass
class EvalResult:
    """Everything computed by :func:`evaluate` (``scores.auc_*`` None unless it was asked for the AUC)."""

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

    @property
    def images_without_estimates(self) -> list[tuple[int, int]]:
        """(scene_id, im_id) of the target images with no estimate of any target object."""
        has: dict[tuple[int, int], bool] = {}
        for te in self.targets:
            key = (te.scene_id, te.im_id)
            has[key] = has.get(key, False) or len(te.scores) > 0
        return sorted(k for k, v in has.items() if not v)

    @property
    def n_images(self) -> int:
        return len({(te.scene_id, te.im_id) for te in self.targets})

    def to_dict(self) -> dict:
        """JSON-ready dict with every number (thresholds, recalls, AR, per-object scores)."""
        from cosy_lite.eval.scoring import MSSD_THRESHOLDS, VSD_TAUS, VSD_THETAS

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
            "n_targets": s.n_targets, "seconds": self.seconds, "n_images": self.n_images,
            "images_without_estimates": [list(k) for k in self.images_without_estimates],
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


def _top_estimates(estimates: list[PoseEstimate]) -> dict[tuple[int, int, int], list[PoseEstimate]]:
    """(scene, im, obj) -> estimates sorted by decreasing score (stable: file order on ties, as the
    toolkit's ``sorted(..., reverse=True)``)."""
    out: dict[tuple[int, int, int], list[PoseEstimate]] = defaultdict(list)
    for e in estimates:
        out[(e.scene_id, e.im_id, e.obj_id)].append(e)
    return {k: sorted(v, key=lambda e: e.score, reverse=True) for k, v in out.items()}


def _targets_by_image(targets: list[Target]) -> dict[tuple[int, int], list[Target]]:
    """(scene, im) -> targets in file order; a repeated (scene, im, obj) keeps its last entry (the toolkit's dict)."""
    last: dict[tuple[int, int, int], Target] = {}
    for t in targets:
        last[(t.scene_id, t.im_id, t.obj_id)] = t
    out: dict[tuple[int, int], list[Target]] = defaultdict(list)
    for t in last.values():
        out[(t.scene_id, t.im_id)].append(t)
    return out


def eval_split(name: str, split: str | None = None) -> str:
    """The split folder to evaluate: ``split``, else the dataset's BOP19 test split (table), else ``test``."""
    from cosy_lite.bop.params import DATASETS

    params = DATASETS.get(name)
    return split or (params.test_split if params is not None else "test")


ImageKey = tuple[int, int]


class _ImageEvaluation:
    """The per-image part of :func:`evaluate` (errors of every target of some images), built from
    the same arguments in every process that runs it."""

    def __init__(self, dataset_root: str | Path, results_csv: str | Path, split: str | None, name: str | None,
                 max_sym_disc_step: float, sym_zero_angle: bool, visib_gt_min: float, auc: bool):
        from cosy_lite.bop.params import DATASETS

        self.ds = ds = BopDataset(Path(dataset_root), name or "")
        self.params = params = DATASETS.get(ds.name)
        self.split = eval_split(ds.name, split)
        self.delta = (params.vsd_delta_mm if params is not None else 15.0) * 1e-3
        self.estimates = read_results_csv(results_csv)
        self.top = _top_estimates(self.estimates)
        self.by_image = _targets_by_image(ds.test_targets())
        self.visib_gt_min, self.auc = visib_gt_min, auc
        self.target_objs = sorted({t.obj_id for ts in self.by_image.values() for t in ts})
        self._symmetries = (max_sym_disc_step, sym_zero_angle)
        self.sp = ds.split_params(self.split)
        self.renderers: dict[tuple[int, int], WindowDepthRenderer] = {}  # per image size
        self.depths: dict[ImageKey, np.ndarray] = {}  # test depths decoded ahead (see _DepthPrefetch)

    @cached_property
    def meshes(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """obj_id -> (vertices [N,3] m, faces [F,3]) of its ``models_eval`` mesh."""
        return {o: self.ds.load_model_geometry(o, eval=True) for o in self.target_objs}

    @cached_property
    def objs(self) -> dict[int, ObjectErrors]:
        """Per target object its error tables (built where the errors are computed: in each
        spawned worker, or before the workers are forked)."""
        from cosy_lite.geometry.symmetries import symmetry_transforms

        step, zero_angle = self._symmetries
        info = self.ds.models_info
        return {o: ObjectErrors.from_model(self.meshes[o][0],
                                           symmetry_transforms(info[o], step, include_zero_angle=zero_angle),
                                           info[o].diameter)
                for o in self.target_objs}

    def prepare(self) -> None:
        """Build now what :meth:`run` builds on first use (meshes, object tables, the renderer of
        the split's image size, the compiled rasteriser), e.g. before forking workers."""
        from cosy_lite.render.depth_raster import warm_up

        import_numba_without_blas()
        _ = self.objs
        if self.sp is not None:
            self.renderer(*self.sp.im_size)
        warm_up()

    def renderer(self, w: int, h: int) -> WindowDepthRenderer:
        if (w, h) not in self.renderers:
            self.renderers[(w, h)] = WindowDepthRenderer(self.meshes, w, h)
        return self.renderers[(w, h)]

    def run(self, keys: list[ImageKey], progress: bool = False) -> tuple[dict[ImageKey, list[TargetErrors]], int]:
        """(image -> the errors of its targets in target-file order, the first image's width)."""
        from tqdm import tqdm

        ds, split, sp = self.ds, self.split, self.sp
        out: dict[ImageKey, list[TargetErrors]] = {}
        im_width = 0
        pool = ThreadPoolExecutor(1)  # MSSD/MSPD/ADD/ADI beside the VSD rendering (see ImageErrors.target)
        pending: list[Future] = []  # their jobs, awaited once every image is rendered
        try:
            bar = tqdm(keys, desc="eval", unit="im", disable=not progress)
            n_eval = 0
            for scene_id, im_id in bar:
                rec = ds.image(split, scene_id, im_id)
                if rec.gt_info is None or len(rec.gt_info) != len(rec.gt):
                    raise BopFormatError(ds.scene_dir(split, scene_id) / "scene_gt_info.json", str(im_id),
                                         "GT info (visib_fract) needed for every GT instance")
                load_depth = _depth_loader(ds, rec, self.depths.get((scene_id, im_id)))
                size = sp.im_size if sp is not None else load_depth().shape[::-1]  # (width, height)
                im_width = im_width or size[0]
                image = ImageErrors(self.renderer(*size), load_depth, rec.camera.K, self.delta, pool, add_adi=self.auc)
                errors = out[(scene_id, im_id)] = []
                targets = []
                for t in self.by_image[(scene_id, im_id)]:
                    ests = self.top.get((scene_id, im_id, t.obj_id), [])[: t.inst_count]
                    gt_idx = [i for i, g in enumerate(rec.gt) if g.obj_id == t.obj_id]
                    targets.append((t.obj_id, self.objs[t.obj_id], ests, [rec.gt[i].TCO for i in gt_idx], gt_idx))
                image.prefetch(targets)  # the image's renders as one batch
                for t, (_, obj, ests, gt_TCO, gt_idx) in zip(self.by_image[(scene_id, im_id)], targets):
                    pair = image.target(t.obj_id, obj, ests, gt_TCO, gt_idx, pending)
                    gt_valid = valid_gt(np.array([rec.gt_info[i].visib_fract for i in gt_idx]), t.inst_count,
                                        self.visib_gt_min)
                    errors.append(TargetErrors(scene_id, im_id, t.obj_id, t.inst_count,
                                               np.array([e.score for e in ests], dtype=np.float64), gt_valid,
                                               pair.vsd, pair.mssd, pair.mspd, pair.add, pair.adi))
                    n_eval += len(ests)
                bar.set_postfix(estimates=n_eval, refresh=False)
            for job in pending:  # errors filled in place into ``out``; re-raises a job's exception
                job.result()
        finally:
            pool.shutdown(cancel_futures=True)
        return out, im_width


def import_numba_without_blas() -> None:
    """Import numba's array functions before anything else does, with ``scipy.linalg`` hidden.

    numba's ``np.arraymath`` imports ``scipy.linalg`` (0.15 s, a third of numba's start) only to
    learn whether ``np.convolve`` / ``np.correlate`` may call BLAS; the evaluator's kernels call
    neither, and ``scipy.linalg`` stays importable for the code that uses it. Nothing is done if
    either module is already imported."""
    import sys

    if "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules:
        return
    sys.modules["scipy.linalg"] = None  # type: ignore[assignment]  # an import of it raises ImportError
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        del sys.modules["scipy.linalg"]


MAX_AUTO_WORKERS = 4  # workers=None: one process per available core, at most this many ...
MIN_IMAGES_PER_WORKER = 10  # ... and no more than one per this many images (a spawned worker costs ~2 s to start)


def auto_workers(n_images: int) -> int:
    """Processes for ``evaluate(workers=None)``: one per core this process may use, at most
    :data:`MAX_AUTO_WORKERS`, one per :data:`MIN_IMAGES_PER_WORKER` images (1 for a small split)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(cores, MAX_AUTO_WORKERS, n_images // MIN_IMAGES_PER_WORKER))


_WORKER: _ImageEvaluation | None = None  # a worker process's evaluation (evaluate(workers > 1))


def _init_worker(*args) -> None:
    global _WORKER
    _WORKER = _ImageEvaluation(*args)


def _run_worker(keys: list[ImageKey]) -> tuple[dict[ImageKey, list[TargetErrors]], int]:
    assert _WORKER is not None
    return _WORKER.run(keys)


def guided_chunks(keys: list, workers: int) -> list[list]:
    """``keys`` cut into consecutive chunks that shrink as the work left does (each a
    ``1 / (2 workers)`` share of what remains, at least one key): few chunks to hand out, and the
    workers end within about one image of each other."""
    chunks, i = [], 0
    while i < len(keys):
        size = max(1, -(-(len(keys) - i) // (2 * workers)))
        chunks.append(keys[i:i + size])
        i += size
    return chunks


def _parallel_errors(args: tuple, keys: list[ImageKey], workers: int, progress: bool,
                     ev: _ImageEvaluation | None = None) -> tuple[dict[ImageKey, list[TargetErrors]], int]:
    """:meth:`_ImageEvaluation.run` over ``keys`` in ``workers`` processes, in chunks of
    consecutive images. With ``ev`` (this process's evaluation, meshes and object tables built), the
    workers are forked from this process and start with all of it; else they
    are spawned and build their own from ``args``."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from tqdm import tqdm

    global _WORKER
    chunks = guided_chunks(keys, workers)
    out: dict[ImageKey, list[TargetErrors]] = {}
    widths: dict[int, int] = {}
    if ev is not None:
        _WORKER = ev  # inherited by the forked workers
        pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("fork"))
    else:
        pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_init_worker, initargs=args)
    try:
        with pool as ex:
            futures = {ex.submit(_run_worker, c): k for k, c in enumerate(chunks)}
            bar = tqdm(total=len(keys), desc=f"eval ({workers} processes)", unit="im", disable=not progress)
            for f in as_completed(futures):
                errors, width = f.result()
                out.update(errors)
                widths[futures[f]] = width
                bar.update(len(chunks[futures[f]]))
            bar.close()
    finally:
        _WORKER = None
    return out, widths[0] if widths else 0


def fork_is_safe() -> bool:
    """Whether worker processes may be forked from this one: Linux, no torch loaded (its thread
    pools and GL contexts do not survive a fork) and no thread but the main one (and tqdm's
    monitor, which only sleeps and refreshes bars)."""
    import sys
    import threading

    others = [t for t in threading.enumerate() if t is not threading.main_thread() and t.name != "tqdm_monitor"]
    return sys.platform.startswith("linux") and not others and "torch" not in sys.modules


def evaluate(
    dataset_root: str | Path,
    results_csv: str | Path,
    split: str | None = None,
    name: str | None = None,
    max_sym_disc_step: float = 0.01,
    sym_zero_angle: bool = True,
    visib_gt_min: float = VISIB_GT_MIN,
    progress: bool = True,
    auc: bool = False,
    workers: int | None = 1,
    before_errors: Callable[[], None] | None = None,
) -> EvalResult:
    """Compute VSD, MSSD and MSPD (and ADD, ADI with ``auc``) of every evaluated estimate and score them (BOP19).

    Args:
        dataset_root: BOP dataset folder (``models_eval/``, ``test_targets_bop19.json``, test split).
        results_csv: BOP19 results CSV (validate it and the dataset first: ``check_results``,
            ``check_dataset``; ``cosy-lite eval`` does).
        split: split folder (default: the dataset's test split from the parameter table, else ``test``).
        name: dataset name for the parameter table (default: the folder name).
        max_sym_disc_step, sym_zero_angle: discretisation of continuous symmetries (see
            :func:`cosy_lite.geometry.symmetries.symmetry_transforms`; True = current bop_toolkit,
            False = the toolkit of the BOP 2019-2022 evaluations).
        visib_gt_min: which GT instances are targets (see :func:`cosy_lite.eval.scoring.valid_gt`;
            default -1 = the ``inst_count`` most visible, as the toolkit's BOP19 evaluation).
        progress: show a tqdm bar over images.
        auc: also compute ADD and ADI and score the YCB-V AUC of ADD(-S) and of ADI (PoseCNN's metric;
            not part of BOP19, which the toolkit's evaluation computes without; ~40 % more time).
        workers: processes computing the errors (images split between them; the same scores as 1);
            None: :func:`auto_workers` of the number of images.
        before_errors: called (once) when everything is read and prepared, before any error is
            computed or any worker process forked: e.g. to wait for checks of the input that ran
            meanwhile; an exception raised there stops the evaluation.
    """
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be >= 1 (or None: automatic), got {workers}")
    t0 = time.perf_counter()
    args = (dataset_root, results_csv, split, name, max_sym_disc_step, sym_zero_angle, visib_gt_min, auc)
    ev = _ImageEvaluation(*args)
    keys = sorted(ev.by_image)
    if workers is None:
        workers = auto_workers(len(keys))
    before = before_errors or (lambda: None)
    if workers == 1 or len(keys) < 2:
        before()
        errors, im_width = ev.run(keys, progress)
    elif fork_is_safe():
        prefetch = _DepthPrefetch(ev, keys)  # the other core decodes depth images while this one prepares
        prefetch.start()
        try:
            ev.prepare()
        finally:
            prefetch.stop()  # (no thread may run at the fork)
        before()
        errors, im_width = _parallel_errors(args, keys, min(workers, len(keys)), progress, ev)
    else:
        before()
        errors, im_width = _parallel_errors(args, keys, min(workers, len(keys)), progress)
    out = [te for k in keys for te in errors[k]]
    n_eval = sum(len(te.scores) for te in out)
    params, info = ev.params, ev.ds.models_info
    # ADD-S objects of the AUC: the table's list (the toolkit's dataset_params), else those with symmetries.
    symmetric = (params.symmetric_obj_ids if params is not None and params.symmetric_obj_ids
                 else tuple(o for o, i in info.items() if i.is_symmetric))
    if ev.sp is not None:
        im_width = ev.sp.im_size[0]
    scores = score_targets(out, {o: info[o].diameter for o in ev.target_objs}, im_width, symmetric, auc=auc)
    return EvalResult(ev.ds.name, ev.split, str(results_csv), len(ev.estimates), n_eval, ev.delta, im_width,
                      visib_gt_min, scores, out, time.perf_counter() - t0)


PREFETCH_MAX_IMAGES = 256  # depth images decoded ahead at most (float32: 1.2 MB each at 640 x 480)


class _DepthPrefetch(threading.Thread):
    """Decodes the test depths of ``keys``, in order, into ``ev.depths`` until :meth:`stop`: work for
    a second core while one prepares what forked workers inherit (cv2 decodes without the GIL).
    An image that fails to load is left to the worker, which reports it."""

    def __init__(self, ev: _ImageEvaluation, keys: list[ImageKey]):
        super().__init__(name="depth prefetch", daemon=True)
        self.ev, self.keys = ev, keys[:PREFETCH_MAX_IMAGES]
        self._stop_event = threading.Event()

    def run(self) -> None:
        ds, split = self.ev.ds, self.ev.split
        for key in self.keys:
            if self._stop_event.is_set():
                return
            try:
                self.ev.depths[key] = ds.load_depth(ds.image(split, *key))
            except Exception:  # (BopFormatError, a missing file...): raised again where the image is evaluated
                return

    def stop(self) -> None:
        """Stop after the image being decoded; return when the thread has ended."""
        self._stop_event.set()
        self.join()


def _depth_loader(ds: BopDataset, rec, depth: np.ndarray | None = None):
    """A function returning the test depth [H,W] (m) of ``rec``: ``depth`` if given (decoded
    ahead), else read from disk on the first call only."""
    cache: list[np.ndarray] = [] if depth is None else [depth]

    def load() -> np.ndarray:
        if not cache:
            cache.append(ds.load_depth(rec))
        return cache[0]

    return load
