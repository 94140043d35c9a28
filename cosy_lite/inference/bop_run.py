"""Run a :class:`~cosy_lite.inference.predictor.Predictor` over a BOP test split and write the
BOP19-format submission ``METHOD_DATASET-SPLIT.csv`` (ViVo task, or the BOP 2024/2025 6D detection
task: every detection of the images of ``test_targets_bop24.json``, no instance counts), overlays,
and the checker's verdict.

Per target image of ``test_targets_bop19.json``: read the image (and depth when ICP is on) ->
detections (the detector, the ground truth ("oracle"), or a BOP22 detections JSON file) -> per
object its ``inst_count`` best detections (with the setting ``vivo_candidates`` N > 1: its N x
``inst_count`` best, of which the ``inst_count`` the refiner is most confident of go on;
:mod:`~cosy_lite.inference.vivo`) -> poses -> one CSV row per valid estimate, ranked by score.
``time`` is the wall time of the image from detection to the last pose (file reading excluded),
plus the file's own detection time for a detections JSON (BOP: detection time counts); oracle
detections cost nothing. Invalid poses (NaN, not a rotation, behind the camera) are never written:
they are counted and reported.
When the predictor's detector runs, all its detections (before the per-object selection) are also
written as BOP22 ``METHOD_DATASET-SPLIT.json`` beside the CSV: the input of the BOP 2D tasks'
evaluation (``cosy-lite eval --task 2d-detection | 2d-segmentation``).
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from cosy_lite.bop.dataset import BopDataset, ImageRecord
from cosy_lite.bop.detections import (
    MIN_BOX_SIZE_PX,
    Detections,
    degenerate_boxes,
    detections_to_bop22,
    oracle_detections,
    read_detections_json,
    write_bop22_entries,
)
from cosy_lite.bop.results import PoseEstimate, results_filename, write_results_csv
from cosy_lite.bop.validate import Problem, check_results, resolve_split_folder
from cosy_lite.errors import BopFormatError
from cosy_lite.inference.icp import icp_rejection_kind
from cosy_lite.inference.predictor import TIMING_KEYS, PoseEstimates, Predictor, SetupError
from cosy_lite.inference.vivo import select_candidates, targets_by_image

ORACLE = "oracle"
TASKS = ("6d-localization", "6d-detection")  # BOP19 ViVo (test_targets_bop19.json) | BOP24 (test_targets_bop24.json)
MAX_DETECTIONS_6D = 100  # the BOP24 evaluation keeps the 100 best estimates per image
ORACLE_MIN_VISIB_FRACT = 0.1  # as the BOP19 targets: instances at least 10 % visible
DetectionSource = Callable[[ImageRecord], Detections]


def _oracle_source(dataset: BopDataset, with_masks: bool) -> DetectionSource:
    def source(rec: ImageRecord) -> Detections:
        det = oracle_detections(dataset, rec, with_masks=with_masks, min_visib_fract=ORACLE_MIN_VISIB_FRACT)
        det.time_s = 0.0
        return det

    return source


def _json_source(path: Path, dataset: BopDataset, with_masks: bool) -> DetectionSource:
    per_image = read_detections_json(path, valid_obj_ids=dataset.obj_ids, with_masks=with_masks)
    targets = targets_by_image(dataset.test_targets())
    if per_image and not set(per_image) & set(targets):
        some = sorted(per_image)[:3]
        raise BopFormatError(path, "scene_id/image_id", (
            f"none of its {len(per_image)} images (e.g. (scene_id, image_id) {some}) is a target image of "
            f"{dataset.test_targets_path}: detections of another dataset or split?"))

    def source(rec: ImageRecord) -> Detections:
        det = per_image.get((rec.scene_id, rec.im_id))
        return det if det is not None else Detections.empty()

    return source


# name -> builder(dataset, with_masks); anything else is a detections JSON file
DETECTION_SOURCES: dict[str, Callable[[BopDataset, bool], DetectionSource]] = {ORACLE: _oracle_source}


def detection_source(spec: str | Path | None, dataset: BopDataset, with_masks: bool) -> DetectionSource | None:
    """Detections per image from ``spec``: None (the predictor's detector: returns None), a key of
    :data:`DETECTION_SOURCES` ("oracle"), or a BOP22 detections JSON file."""
    if spec is None:
        return None
    if str(spec) in DETECTION_SOURCES:
        return DETECTION_SOURCES[str(spec)](dataset, with_masks)
    path = Path(spec)
    if not path.is_file():
        raise BopFormatError(path, "--detections", f"detections file not found (expected {sorted(DETECTION_SOURCES)} "
                             "or a BOP22 JSON file)")
    return _json_source(path, dataset, with_masks)


@dataclass
class RunSummary:
    """What a run wrote and measured.

    image_times: the ``time`` of each image (s); timings: seconds per stage summed over images
    (:data:`~cosy_lite.inference.predictor.TIMING_KEYS`); n_invalid: estimates not written (invalid
    pose); n_degenerate: detections skipped for a box side under ``MIN_BOX_SIZE_PX``; problems:
    the results checker's findings on the CSV.
    """

    csv_path: Path
    n_images: int
    n_detections: int
    n_estimates: int
    n_invalid: int
    seconds: float
    image_times: list[float] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    icp_accepted: int = 0
    icp_runs: int = 0
    icp_rejections: Counter = field(default_factory=Counter)  # why ICP kept the input pose (icp_rejection_kind)
    no_depth: int = 0  # images without a depth file (ICP asked for but skipped)
    n_degenerate: int = 0
    vis_paths: list[Path] = field(default_factory=list)
    problems: list[Problem] = field(default_factory=list)
    csv_before_icp: Path | None = None  # the same run's poses before ICP (method_before_icp)
    detections_json: Path | None = None  # the detector's detections (BOP22), when it ran

    @property
    def ok(self) -> bool:
        return not any(p.severity == "error" for p in self.problems)

    def lines(self) -> list[str]:
        n = max(1, self.n_images)
        per = "  ".join(f"{k} {1000 * self.timings.get(k, 0.0) / n:.0f}" for k in TIMING_KEYS if k != "templates")
        per += f"; templates rendered once: {self.timings.get('templates', 0.0):.1f} s (not in the images' time)"
        out = [f"{self.n_images} images, {self.n_estimates} estimates written ({self.n_detections} detections kept, "
               f"{self.n_invalid} invalid poses dropped) in {self.seconds:.1f} s",
               f"time per image: mean {np.mean(self.image_times or [0.0]):.3f} s; ms per image: {per}"]
        if self.icp_runs:
            why = ", ".join(f"{n} {kind}" for kind, n in self.icp_rejections.most_common())
            out.append(f"ICP accepted {self.icp_accepted} of {self.icp_runs} poses" + (f"; rejected: {why}" if why else ""))
        if self.n_degenerate:
            out.append(f"WARNING: {self.n_degenerate} detections with a box side under {MIN_BOX_SIZE_PX} px "
                       "(or non-finite) skipped: no pose estimated for them")
        if self.no_depth:
            out.append(f"WARNING: {self.no_depth} images have no depth file: ICP skipped on them")
        if self.vis_paths:
            out.append(f"overlays: {self.vis_paths[0].parent} ({len(self.vis_paths)} PNGs)")
        verdict = "passes the results checker" if self.ok else "FAILS the results checker (see above)"
        out.append(f"results: {self.csv_path} ({verdict})")
        if self.csv_before_icp is not None:
            out.append(f"results before ICP: {self.csv_before_icp}")
        if self.detections_json is not None:
            out.append(f"detections (BOP22, every one; cosy-lite eval --task 2d-detection): {self.detections_json}")
        return out


def _write_overlay(path: Path, rgb: np.ndarray, rec: ImageRecord, est, predictor: Predictor) -> Path:
    import cv2

    from cosy_lite.inference.overlay import draw_estimates

    gt = [g for g in rec.gt if g.obj_id in set(predictor.obj_ids)]
    image = draw_estimates(rgb, rec.camera.K, est.obj_ids.tolist(), est.TCO.numpy(), est.scores.tolist(),
                           predictor.renderer, [g.obj_id for g in gt], np.stack([g.TCO for g in gt]) if gt else None)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
        raise OSError(f"{path}: could not write the overlay PNG")
    return path


def check_coverage(predictor: Predictor, targets_path: Path, target_obj_ids: set[int],
                   detector_path: Path | None) -> None:
    """SetupError naming the checkpoint when the pose models (or the detector) miss target objects."""
    models = [m for m in (predictor.coarse, predictor.refiner) if m is not None]
    for m in models:
        missing = sorted(target_obj_ids - set(m.obj_ids))
        if missing:
            raise SetupError(f"{m.describe()}: the {m.kind} checkpoint covers obj_ids {m.obj_ids}, but {targets_path} "
                             f"asks for {sorted(target_obj_ids)} (missing {missing})")
    missing = sorted(target_obj_ids - set(predictor.obj_ids))
    if missing:
        raise SetupError(f"the predictor estimates obj_ids {predictor.obj_ids}, but {targets_path} "
                         f"asks for {missing} too")
    if predictor.detector is not None and detector_path is not None:
        det_ids = set(predictor.detector.label_map.obj_ids)
        missing = sorted(target_obj_ids - det_ids)
        if missing:
            raise SetupError(f"{detector_path}: the detector knows obj_ids {sorted(det_ids)}, but {targets_path} "
                             f"asks for {missing} too")


def select_top_detections(detections: Detections, obj_ids: set[int], n: int = MAX_DETECTIONS_6D) -> Detections:
    """The ``n`` highest-scoring detections of objects in ``obj_ids`` (6D detection: no instance counts),
    by decreasing score (ties: input order)."""
    known = torch.tensor([int(o) in obj_ids for o in detections.obj_ids.tolist()], dtype=torch.bool)
    det = detections.select(torch.nonzero(known).reshape(-1))
    order = torch.argsort(det.scores, descending=True, stable=True)[:n]
    return det.select(order)


def _image_targets(dataset: BopDataset, task: str, predictor: Predictor, detector_path: Path | None):
    """(image keys, per image a function Detections -> the detections to estimate (6d-detection), or its
    ``{obj_id: inst_count}`` (6d-localization)) for ``task``."""
    if task == "6d-detection":
        known = set(predictor.obj_ids)
        keys = list(dict.fromkeys((t.scene_id, t.im_id) for t in dataset.test_image_targets()))
        return keys, {k: (lambda det: select_top_detections(det, known)) for k in keys}
    per_image = targets_by_image(dataset.test_targets())
    check_coverage(predictor, dataset.test_targets_path, {o for c in per_image.values() for o in c}, detector_path)
    return list(per_image), per_image


def _to_estimate(predictor: Predictor, det: Detections, target: Callable[[Detections], Detections] | dict[int, int]
                 ) -> tuple[Detections, dict[int, int] | None]:
    """(the detections to pose, the ViVo instance counts for :meth:`Predictor.predict`) of one image: ``target``
    is the task's choice of detections (6d-detection) or the image's ``{obj_id: inst_count}`` (6d-localization)."""
    if callable(target):
        return target(det), None
    cfg = predictor.config
    return select_candidates(det, target, cfg.vivo_candidates, cfg.vivo_score_ratio), target


def _image_inputs(dataset: BopDataset, rec: ImageRecord, icp: bool, source: Callable[[Any], Detections | None] | None,
                  detections: str | Path | None) -> tuple[np.ndarray, np.ndarray | None, Detections | None]:
    """(rgb, depth (with ICP, when the image has one), the given detections) of one image, their sizes checked."""
    rgb = dataset.load_rgb(rec)
    depth = dataset.load_depth(rec) if icp and rec.depth_path is not None else None
    if depth is not None and depth.shape != rgb.shape[:2]:
        raise BopFormatError(str(rec.depth_path), "size", f"{depth.shape[1]}x{depth.shape[0]} pixels, but the image "
                             f"{rec.rgb_path} is {rgb.shape[1]}x{rgb.shape[0]}")
    given = source(rec) if source is not None else None
    if given is not None and given.masks is not None and len(given) and given.masks.shape[1:] != rgb.shape[:2]:
        raise BopFormatError(str(detections), "segmentation.size", (
            f"masks of scene {rec.scene_id} image {rec.im_id} are {list(given.masks.shape[1:])} (H, W); "
            f"the image {rec.rgb_path} is {list(rgb.shape[:2])}"))
    return rgb, depth, given


def _count(summary: RunSummary, est: PoseEstimates, n_detections: int, t_image: float, t_detection: float) -> None:
    """Add one image's times, detections, invalid poses and ICP outcomes to ``summary``."""
    summary.image_times.append(t_image)
    timings = dict(est.timings, detection=t_detection)
    for key in TIMING_KEYS:
        summary.timings[key] += timings.get(key, 0.0) if key != "total" else t_image
    summary.n_detections += n_detections
    summary.n_invalid += int((~est.valid).sum())
    if est.icp is not None:
        summary.icp_runs += len(est.icp)
        summary.icp_accepted += sum(r.accepted for r in est.icp)
        summary.icp_rejections.update(icp_rejection_kind(r.reason) for r in est.icp if not r.accepted)


def _rows(est: PoseEstimates, scene_id: int, im_id: int, seconds: float) -> list[PoseEstimate]:
    """The BOP19 rows of one image's (valid) estimates."""
    return [PoseEstimate(scene_id, im_id, int(est.obj_ids[i]), float(est.scores[i]), est.TCO[i].numpy(), seconds)
            for i in range(len(est))]


def run_on_split(predictor: Predictor, dataset: BopDataset, out_dir: str | Path, split: str = "test",
                 method: str = "cosylite", detections: str | Path | None = None, n_vis: int = 0,
                 limit_images: int | None = None, progress: bool = True,
                 detector_path: Path | None = None, task: str = "6d-localization",
                 method_before_icp: str | None = None) -> RunSummary:
    """Estimate the poses of the targets of ``split`` and write ``out_dir/METHOD_DATASET-SPLIT.csv``.

    Args:
        detections: None (the predictor's detector), "oracle", or a BOP22 detections JSON file.
        n_vis: overlays written for the first ``n_vis`` images (``out_dir/vis/``).
        limit_images: only the first target images.
        task: "6d-localization" (BOP19 ViVo: per image and object its ``inst_count`` best detections)
            or "6d-detection" (BOP 2024/2025: the images of ``test_targets_bop24.json``, every detection
            of a known object, at most the 100 best per image).
        method_before_icp: with ICP, also write the refiner's poses before ICP as
            ``out_dir/METHOD_BEFORE_ICP_DATASET-SPLIT.csv`` (their ``time`` without the ICP stage): the
            RGB-only results of the same run, at no extra cost.
    """
    from tqdm import tqdm

    if task not in TASKS:
        raise ValueError(f"task {task!r}: expected one of {list(TASKS)}")
    out_dir = Path(out_dir)
    csv_path = out_dir / results_filename(method, dataset.name, split)
    if method_before_icp is not None and not predictor.config.icp:
        raise SetupError(f"method_before_icp={method_before_icp!r}: there is no 'before ICP' without ICP")
    csv_before = None if method_before_icp is None else out_dir / results_filename(method_before_icp, dataset.name, split)
    if csv_before == csv_path:
        raise SetupError(f"method_before_icp is the method name {method!r}: the two CSV files would be one")
    split_dir = resolve_split_folder(dataset.root, split, None)
    split_folder = split_dir.name if split_dir is not None else split
    image_keys, choose = _image_targets(dataset, task, predictor, detector_path)
    keys = image_keys[:limit_images] if limit_images is not None else image_keys
    source = detection_source(detections, dataset, with_masks=predictor.reads_masks)
    if source is None and predictor.detector is None:
        raise SetupError("no detections: load a detector checkpoint or give detections ('oracle' or a JSON file)")
    estimates: list[PoseEstimate] = []
    estimates_before: list[PoseEstimate] = []
    summary = RunSummary(csv_path, len(keys), 0, 0, 0, 0.0, timings=dict.fromkeys(TIMING_KEYS, 0.0),
                         csv_before_icp=csv_before)
    t_run = time.perf_counter()
    detector_entries: list[dict] = []
    bar = tqdm(keys, desc=f"infer {dataset.name}/{split}", unit="img", disable=None if progress else True)
    for k, (scene_id, im_id) in enumerate(bar):
        rec = dataset.image(split_folder, scene_id, im_id)
        rgb, depth, given = _image_inputs(dataset, rec, predictor.config.icp, source, detections)
        summary.no_depth += int(predictor.config.icp and depth is None)
        t0 = time.perf_counter()
        det = given if given is not None else predictor.detect(rgb)
        bad = degenerate_boxes(det)
        summary.n_degenerate += int(bad.sum())
        det = det.select(~bad)
        if given is None:  # the detector's: all of them, for the BOP 2D tasks
            detector_entries += detections_to_bop22({(scene_id, im_id): det})
        det, inst_counts = _to_estimate(predictor, predictor.detection_filter(det), choose[(scene_id, im_id)])
        est = predictor.predict(rgb, rec.camera.K, depth, detections=det, inst_counts=inst_counts)
        t_image = (time.perf_counter() - t0 - est.timings.get("templates", 0.0)  # (one-time: not the image's)
                   + (max(given.time_s, 0.0) if given is not None else 0.0))
        _count(summary, est, len(det), t_image, max(given.time_s, 0.0) if given is not None else det.time_s)
        good = est.only_valid()
        estimates += _rows(good, scene_id, im_id, t_image)
        if csv_before is not None:
            estimates_before += _rows(est.before_icp().only_valid(), scene_id, im_id,
                                      t_image - est.timings.get("icp", 0.0))
        if k < n_vis:
            name = f"{csv_path.stem}_{scene_id:06d}_{im_id:06d}.png"
            summary.vis_paths.append(_write_overlay(out_dir / "vis" / name, rgb, rec, good, predictor))
    bar.close()
    out_dir.mkdir(parents=True, exist_ok=True)
    write_results_csv(csv_path, estimates)
    if source is None:
        summary.detections_json = csv_path.with_suffix(".json")
        write_bop22_entries(summary.detections_json, detector_entries)
    summary.n_estimates = len(estimates)
    summary.seconds = time.perf_counter() - t_run
    summary.problems = check_results(csv_path, dataset.root, dataset.name, split)
    if csv_before is not None:
        write_results_csv(csv_before, estimates_before)
        summary.problems += check_results(csv_before, dataset.root, dataset.name, split)
    return summary
