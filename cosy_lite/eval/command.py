"""``cosy-lite eval``: validate a BOP19 results CSV, score it (VSD, MSSD, MSPD, AR), write JSON + PNG;
``--task 6d-detection``: the BOP 2024/2025 mAP instead (:mod:`cosy_lite.eval.pose_detection`);
``--task 2d-detection | 2d-segmentation``: COCO AP of a BOP22 detections JSON, as the toolkit's
``eval_bop22_coco.py`` (:func:`cosy_lite.eval.detection.bop22_coco_scores`)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dataset", required=True, metavar="DIR",
                   help="BOP dataset folder, or a name under $COSY_LITE_DATA (default ./data)")
    p.add_argument("--results", required=True, type=Path, metavar="FILE.csv",
                   help="results METHOD_DATASET-SPLIT.csv (the 2D tasks: a BOP22 detections METHOD_DATASET-SPLIT.json)")
    p.add_argument("--split", default=None, help="split folder (default: the dataset's BOP19 test split)")
    p.add_argument("--name", default=None, help="dataset name (default: the folder name)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="where to write the scores (default: outputs/eval/RESULTS_STEM/ in the current folder, never beside "
                        "the results file)")
    p.add_argument("--max-sym-disc-step", type=float, default=0.01,
                   help="discretisation step of continuous symmetries (BOP: 0.01)")
    p.add_argument("--old-toolkit-symmetries", dest="sym_zero_angle", action="store_false",
                   help="discretise continuous symmetries without the 0 angle, as bop_toolkit before mid 2023 "
                        "(BOP 2019-2022 scores); default: the current toolkit")
    p.add_argument("--visib-gt-min", type=float, default=-1.0,
                   help="GT instances with visib_fract >= this are targets; -1 (default, the toolkit's BOP19 "
                        "setting): the inst_count most visible instances of each target")
    p.add_argument("--task", default="6d-localization",
                   choices=["6d-localization", "6d-detection", "2d-detection", "2d-segmentation"],
                   help="6d-localization: BOP19 AR (VSD, MSSD, MSPD) over test_targets_bop19.json; 6d-detection: "
                        "BOP 2024/2025 mAP (MSSD, MSPD; bop24_mAP, bop25_mAP) over test_targets_bop24.json; "
                        "2d-detection / 2d-segmentation: COCO box / mask AP of a BOP22 detections JSON over the "
                        "images of --targets (scores_bop22_coco_bbox.json / _segm.json, the toolkit's keys)")
    p.add_argument("--targets", default=None, metavar="FILE",
                   help="2D tasks: the targets file in the dataset folder whose images are scored (default "
                        "test_targets_bop19.json, as the toolkit; test_targets_bop24.json for BOP 2024/2025)")
    p.add_argument("--bbox-type", default="amodal", choices=["amodal", "modal"],
                   help="2d-detection: GT boxes of the whole object (amodal, the toolkit's default) or of its "
                        "visible part (modal: scores_bop22_coco_bbox_modal.json)")
    p.add_argument("--auc", action="store_true",
                   help="also compute ADD and ADI and report the YCB-V AUC of ADD(-S) and of ADI (PoseCNN's "
                        "metric, not part of BOP19; about 40 %% more time)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="processes computing the errors (6d-localization; the images are split between them, "
                        "the scores are the same; default: one per core, at most 4, and 1 for fewer than 20 images)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def scores_folder(results: Path) -> Path:
    """Where ``cosy-lite eval`` writes the scores of ``results`` without ``--out``: a results folder of
    the current directory, not the folder of the input (which may be a dataset, a checkout or read-only)."""
    return Path("outputs") / "eval" / results.stem


def format_table(result) -> str:
    """AR per metric, overall and per object, then the dataset's recall at every threshold, as aligned text."""
    from cosy_lite.eval.scoring import MSSD_THRESHOLDS, VSD_THETAS

    s = result.scores
    head = (f"{'object':>8} {'targets':>8} {'ests':>6} {'AR':>7} {'AR_VSD':>7} {'AR_MSSD':>7} {'AR_MSPD':>7} "
            f"{'AUC_ADD(-S)':>11} {'AUC_ADI':>7}")
    lines = [f"{result.dataset} / {result.split}: {result.n_estimates_evaluated} of {result.n_estimates_in_file} "
             f"estimates evaluated, {s.n_targets} targets, {result.seconds:.1f} s"]
    empty = result.images_without_estimates
    if empty:  # they count, with recall 0: say so
        shown = ", ".join(f"scene {sc} image {im}" for sc, im in empty[:5]) + (", ..." if len(empty) > 5 else "")
        lines.append(f"{len(empty)} of {result.n_images} target images have no estimate (their targets count as "
                     f"missed): {shown}")
    lines += [head, "-" * len(head)]
    rows = [(str(o), x) for o, x in s.per_object.items()] + [("all", s)]

    def auc(v: float | None, width: int) -> str:  # "-": not computed (cosy-lite eval without --auc)
        return f"{v:{width}.4f}" if v is not None else f"{'-':>{width}}"

    for label, x in rows:
        lines.append(f"{label:>8} {x.n_targets:>8} {x.n_estimates:>6} {x.ar:7.4f} {x.ar_vsd:7.4f} {x.ar_mssd:7.4f} "
                     f"{x.ar_mspd:7.4f} {auc(x.auc_add_s, 11)} {auc(x.auc_adi, 7)}")

    def curve(name: str, thresholds, recalls) -> str:
        return f"{name:<27}" + " ".join(f"{t:>5.3g}" for t in thresholds) + f"\n{'  recall':<27}" + " ".join(
            f"{r:5.3f}" for r in recalls)

    lines += ["", "recall of all targets per threshold (AR = mean):",
              curve("VSD theta (mean over tau)", VSD_THETAS, s.recall_vsd.mean(axis=0)),
              curve("MSSD [x diameter]", MSSD_THRESHOLDS, s.recall_mssd),
              curve("MSPD [px]", s.mspd_thresholds_px, s.recall_mspd)]
    return "\n".join(lines)


class RecallFigure:
    """Recall vs threshold: VSD (one curve per tau, vs theta), MSSD (vs fraction of diameter), MSPD
    (vs px), in two steps: the axes, grid, labels and legend once the MSPD thresholds are known
    (``mspd_thresholds_px``: the width scaling), then :meth:`save` of a result draws only its curves
    and AR titles over them (the first step while the errors are computed, off the path to the scores)."""

    def __init__(self, mspd_thresholds_px):
        import numpy as np
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure  # no pyplot: no GUI state, less to import

        from cosy_lite.eval.scoring import MSSD_THRESHOLDS, VSD_TAUS, VSD_THETAS

        self.mspd_thresholds_px = np.asarray(mspd_thresholds_px, dtype=np.float64)
        self.fig = fig = Figure(figsize=(15, 4.2))
        self.canvas = FigureCanvasAgg(fig)
        self.axes = axes = fig.subplots(1, 3)
        self.vsd = [axes[0].plot([], [], marker=".", label=f"tau={tau:.2f}d")[0] for tau in VSD_TAUS]
        self.mssd = axes[1].plot([], [], marker="o")[0]
        self.mspd = axes[2].plot([], [], marker="o")[0]
        axes[0].set(xlabel="theta", ylabel="recall")
        self.legend = axes[0].legend(fontsize=6, ncol=2)
        axes[1].set(xlabel="threshold [x diameter]")
        axes[2].set(xlabel="threshold [px]")
        for ax, x in zip(axes, (VSD_THETAS, MSSD_THRESHOLDS, self.mspd_thresholds_px)):
            pad = 0.05 * (x.max() - x.min())  # (matplotlib's default margins, as when the curves set them)
            ax.set_xlim(x.min() - pad, x.max() + pad)
            ax.set_ylim(0, 1.02)
            ax.grid(alpha=0.3)
        self.suptitle = fig.suptitle(" ")
        fig.subplots_adjust(left=0.045, right=0.99, bottom=0.12, top=0.86, wspace=0.15)  # (tight_layout: 0.05 s more)
        over = [self.legend, *(spine for ax in axes for spine in ax.spines.values())]
        for artist in over:  # drawn over the curves by save(), as a full draw orders them: not in the background
            artist.set_visible(False)
        self.canvas.draw()
        self.background = self.canvas.copy_from_bbox(fig.bbox)
        for artist in over:
            artist.set_visible(True)

    def save(self, result, path: Path) -> None:
        """Draw the curves of ``result`` (an :class:`~cosy_lite.eval.evaluator.EvalResult`) and write the PNG."""
        import numpy as np
        from PIL import Image

        from cosy_lite.eval.scoring import MSSD_THRESHOLDS, VSD_THETAS

        s = result.scores
        if not np.array_equal(s.mspd_thresholds_px, self.mspd_thresholds_px):
            raise ValueError(f"the figure was laid out for MSPD thresholds {self.mspd_thresholds_px.tolist()}, "
                             f"the result has {s.mspd_thresholds_px.tolist()}")
        self.canvas.restore_region(self.background)
        axes = self.axes
        for line, recall in zip(self.vsd, s.recall_vsd):
            line.set_data(VSD_THETAS, recall)
        self.mssd.set_data(MSSD_THRESHOLDS, s.recall_mssd)
        self.mspd.set_data(self.mspd_thresholds_px, s.recall_mspd)
        for ax, lines, title in ((axes[0], self.vsd, f"VSD (AR {s.ar_vsd:.3f})"),
                                 (axes[1], [self.mssd], f"MSSD (AR {s.ar_mssd:.3f})"),
                                 (axes[2], [self.mspd], f"MSPD (AR {s.ar_mspd:.3f})")):
            for artist in [*lines, *ax.spines.values()]:
                ax.draw_artist(artist)
            ax.set_title(title)
            ax.draw_artist(ax.title)
        axes[0].draw_artist(self.legend)
        self.suptitle.set_text(f"{result.dataset}/{result.split}: AR {s.ar:.4f}")
        self.fig.draw_artist(self.suptitle)
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.asarray(self.canvas.buffer_rgba())).save(path, dpi=(self.fig.dpi, self.fig.dpi))


def plot_curves(result, path: Path) -> None:
    """The recall curves of ``result`` (:class:`RecallFigure`) in one go."""
    RecallFigure(result.scores.mspd_thresholds_px).save(result, path)


def _argument_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with a numeric option (None: nothing)."""
    if not (math.isfinite(args.max_sym_disc_step) and args.max_sym_disc_step > 0):
        return f"--max-sym-disc-step {args.max_sym_disc_step}: expected a step > 0 (BOP: 0.01)"
    if not (args.visib_gt_min == -1.0 or 0.0 <= args.visib_gt_min <= 1.0):
        return (f"--visib-gt-min {args.visib_gt_min}: expected -1 (BOP19: the inst_count most visible) "
                "or a fraction in [0, 1]")
    if getattr(args, "workers", None) is not None and args.workers < 1:
        return f"--workers {args.workers}: expected an integer >= 1"
    return None


def run(args: argparse.Namespace) -> int:
    """Check the options, the results file and the dataset (every problem reported, nothing scored
    on bad input), then score and write ``scores.json`` + ``recall_curves.png``."""
    from functools import partial

    from cosy_lite.bop.folders import dataset_folder
    from cosy_lite.bop.io import atomic_write_text
    from cosy_lite.bop.validate import report
    from cosy_lite.eval.checks_and_figure import ChecksAndFigure
    from cosy_lite.eval.evaluator import evaluate

    if problem := _argument_problem(args):
        print(f"error: {problem}", file=sys.stderr)
        return 2
    task = getattr(args, "task", "6d-localization")  # (namespaces built in code before the option existed)
    root = dataset_folder(args.dataset)
    if task.startswith("2d-"):
        return _run_2d(args, root, task)
    subject = f"{args.results} on {root}"
    if task == "6d-detection":
        problems = _input_problems(args, root, task)
        if _accepted(problems):
            return _run_6d_detection(args, root)
        return report(problems, subject)
    # the checks and the figure's axes run beside the evaluation (a second core)
    side = ChecksAndFigure(partial(_input_problems, args, root, task), partial(_figure_layout, args, root), plot_curves)
    try:
        result = evaluate(root, args.results, args.split, args.name, args.max_sym_disc_step,
                          args.sym_zero_angle, args.visib_gt_min, progress=not args.no_progress,
                          auc=getattr(args, "auc", False), workers=getattr(args, "workers", None),
                          before_errors=lambda: _stop_unless_accepted(side.problems()))
    except Exception:  # bad input may fail the reading before the checks have said why: their report first
        problems = side.problems()
        side.close()
        if not _accepted(problems, quiet=True):
            return report(problems, subject)
        raise
    try:
        print(format_table(result))
        out = args.out or scores_folder(args.results)
        atomic_write_text(out / "scores.json", json.dumps(result.to_dict(), indent=1) + "\n")
        side.draw(result, out / "recall_curves.png")
    finally:
        side.close()
    print(f"wrote {out / 'scores.json'} and {out / 'recall_curves.png'}")
    return 0


def _figure_layout(args: argparse.Namespace, root: Path) -> RecallFigure | None:
    """The figure's axes drawn for the test images' width, when the dataset's parameters give it
    (else the first depth image does, and the whole figure is drawn at the end)."""
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.eval.evaluator import eval_split
    from cosy_lite.eval.scoring import MSPD_THRESHOLDS_PX

    ds = BopDataset(root, args.name or "")
    sp = ds.split_params(eval_split(ds.name, args.split))
    return None if sp is None else RecallFigure(MSPD_THRESHOLDS_PX * (sp.im_size[0] / 640.0))


def _input_problems(args: argparse.Namespace, root: Path, task: str) -> list:
    """Every problem of the results file and of the dataset parts the task reads."""
    from cosy_lite.bop.params import dataset_name_of
    from cosy_lite.bop.validate import TARGETS_FILE, Problem, check_dataset, check_results
    from cosy_lite.eval.evaluator import eval_split

    problems = check_results(args.results, root, args.name, args.split,
                             allow_unknown_objects=task == "6d-detection")
    if root.is_dir():  # (a missing folder is reported by check_results)
        split = eval_split(dataset_name_of(root, args.name), args.split)
        problems += check_dataset(root, args.name, splits=[split], model_dirs=("models_eval",))  # what it reads
        targets = TARGETS_FILE if task == "6d-localization" else "test_targets_bop24.json"
        if not (root / targets).is_file():
            problems.append(Problem(str(root / targets), "", f"file not found: the {task} evaluation scores "
                                    "the targets it lists"))
    return problems


def _accepted(problems: list, quiet: bool = False) -> bool:
    """True if ``problems`` holds no error; then its warnings are printed (one line per kind) unless ``quiet``."""
    from cosy_lite.bop.validate import summarised

    if any(p.severity == "error" for p in problems):
        return False
    for p in summarised(problems) if not quiet else []:
        print(p)
    return True


class _Rejected(Exception):
    """The checks found errors: the evaluation stops before computing any error."""


def _stop_unless_accepted(problems: list) -> None:
    if not _accepted(problems):
        raise _Rejected


def _run_6d_detection(args: argparse.Namespace, root: Path) -> int:
    """Score the 6D detection task and write ``scores_bop24.json`` (the toolkit's keys)."""
    from cosy_lite.bop.io import atomic_write_text
    from cosy_lite.eval.pose_detection import evaluate_6d_detection
    from cosy_lite.eval.pose_detection import format_table as format_6d

    result = evaluate_6d_detection(root, args.results, args.split, args.name, args.max_sym_disc_step,
                                   progress=not args.no_progress)
    print(format_6d(result))
    out = args.out or scores_folder(args.results)
    atomic_write_text(out / "scores_bop24.json", json.dumps(result.to_dict(), indent=1) + "\n")
    print(f"wrote {out / 'scores_bop24.json'}")
    return 0


def _run_2d(args: argparse.Namespace, root: Path, task: str) -> int:
    """Score a BOP22 detections JSON for a BOP 2D task and write ``scores_bop22_coco_{bbox|segm}.json``."""
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.io import atomic_write_text, load_image_targets
    from cosy_lite.bop.params import dataset_name_of
    from cosy_lite.bop.validate import TARGETS_FILE, Problem, check_dataset, report
    from cosy_lite.eval.detection import ANN_TYPES, COCO_KEYS, bop22_coco_scores
    from cosy_lite.eval.evaluator import eval_split

    if not root.is_dir():
        return report([Problem(str(root), "", "dataset folder not found")], f"{args.results} on {root}")
    split = eval_split(dataset_name_of(root, args.name), args.split)
    targets = root / (args.targets or TARGETS_FILE)
    problems = check_dataset(root, args.name, splits=[split], model_dirs=())  # no mesh is read
    if not targets.is_file():
        problems.append(Problem(str(targets), "", f"file not found: the {task} evaluation scores the images it lists"))
    if not args.results.is_file():
        problems.append(Problem(str(args.results), "", "results file not found"))
    if any(p.severity == "error" for p in problems):
        return report(problems, f"{args.results} on {root}")
    dataset = BopDataset(root) if args.name is None else BopDataset(root, args.name)
    image_targets = load_image_targets(targets)
    scene_rank = {s: k for k, s in enumerate(dict.fromkeys(t.scene_id for t in image_targets))}
    # the toolkit's image order: scenes as the targets list them, images ascending (ties across images)
    keys = sorted({(t.scene_id, t.im_id) for t in image_targets}, key=lambda k: (scene_rank[k[0]], k[1]))
    records = [dataset.image(split, scene_id, im_id) for scene_id, im_id in keys]
    ann_type = ANN_TYPES[task]
    scores = bop22_coco_scores(dataset, records, args.results, ann_type, args.bbox_type)
    print(f"{task} ({ann_type}, {args.bbox_type if ann_type == 'bbox' else 'visible masks'}) of {args.results} "
          f"on {len(records)} images of {targets.name}:")
    print("  " + "  ".join(f"{k} {scores[k]:.3f}" for k in COCO_KEYS[:3] + ("AR100",)))
    out = args.out or scores_folder(args.results)
    name = f"scores_bop22_coco_{ann_type}" + ("_modal" if ann_type == "bbox" and args.bbox_type == "modal" else "")
    atomic_write_text(out / f"{name}.json", json.dumps(scores, indent=1) + "\n")
    print(f"wrote {out / name}.json")
    return 0
