"""Benchmark of the BOP19 evaluator: end-to-end time (load, render, score) per number of estimates.

Usage: python bench/bench_eval.py DATASET_DIR [--estimates 34 1000] [--repeat R]
For the test split of DATASET_DIR (e.g. data/ycbvsynth from `make demo`) it writes a results CSV
of the GT poses perturbed by a fixed noise (1 estimate per target instance, in image order,
truncated to N) and a targets file restricted to the images holding them, then times
``cosy_lite.eval.evaluator.evaluate`` on it (the best of R runs) and prints a table. When N is
larger than the number of targets, the test scenes are repeated under new scene ids (a symlinked
copy of the dataset in a temporary folder), so that exactly N estimates are evaluated.

With ``--phases`` one more run per size splits the time by phase: the evaluator runs serially
(the errors that normally overlap the rendering on a second thread run inline) with a timer
around each phase's functions; the phases therefore add up to that run's wall time, not to
the (overlapped) timed runs.

Each size is timed per variant, alternating within each repeat: ``bop19`` (VSD, MSSD, MSPD, as the
toolkit's BOP19, in one process: ``cosy-lite eval --workers 1``), ``+auc`` (``cosy-lite eval --auc``:
also ADD and ADI for the YCB-V AUC), ``bop19-2proc`` (``--workers 2``: the images split between two
processes; its CPU column counts the parent process only) and ``bop19-auto`` (``cosy-lite eval``'s
default: one process per core, at most 4, one per 10 images). ``--variants`` restricts that.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import tempfile
import time
from collections import defaultdict
from concurrent.futures import Future
from pathlib import Path

import numpy as np

REPEAT_SCENE_OFFSET = 1000  # repeated scenes get ids scene_id + k * 1000
# name -> evaluate(**kwargs): the default evaluation, with the AUC, and the default on 2 processes
VARIANTS = {"bop19": {"auc": False}, "+auc": {"auc": True}, "bop19-2proc": {"auc": False, "workers": 2},
            "bop19-auto": {"auc": False, "workers": None}}


def noisy_estimates(ds, n: int, seed: int = 0, split: str = "test"):
    """One GT-plus-noise estimate (<= 10 deg, 5 mm sigma) per BOP19 target instance, image order, at most n."""
    from cosy_lite.bop.results import PoseEstimate
    from cosy_lite.geometry.transforms import rotation_about_axis

    rng = np.random.default_rng(seed)
    wanted = {(t.scene_id, t.im_id, t.obj_id) for t in ds.test_targets()}
    out = []
    for rec in ds.images(split):
        for g in rec.gt:
            if (rec.scene_id, rec.im_id, g.obj_id) not in wanted:
                continue
            T = g.TCO.copy()
            T[:3, :3] = rotation_about_axis(rng.normal(size=3), np.deg2rad(rng.uniform(0, 10))) @ T[:3, :3]
            T[:3, 3] += rng.normal(scale=0.005, size=3)
            out.append(PoseEstimate(rec.scene_id, rec.im_id, g.obj_id, float(rng.random()), T, 0.1))
            if len(out) == n:
                return out
    return out


def bench_view(src: Path, dst: Path, n: int, split: str = "test") -> Path:
    """``dst``: a symlinked copy of dataset ``src`` whose test split repeats its scenes until it holds >= n targets."""
    from cosy_lite.bop import io
    from cosy_lite.bop.dataset import BopDataset

    targets = BopDataset(src).test_targets()
    copies = max(1, -(-n // max(1, sum(t.inst_count for t in targets))))
    dst.mkdir(parents=True)
    for p in src.iterdir():
        if p.name not in (split, "test_targets_bop19.json"):
            (dst / p.name).symlink_to(p.resolve())
    (dst / split).mkdir()
    all_targets = []
    for k in range(copies):
        for scene in sorted((src / split).iterdir()):
            if scene.is_dir() and scene.name.isdigit():
                (dst / split / f"{int(scene.name) + k * REPEAT_SCENE_OFFSET:06d}").symlink_to(scene.resolve())
        off = k * REPEAT_SCENE_OFFSET
        all_targets += [io.Target(t.scene_id + off, t.im_id, t.obj_id, t.inst_count) for t in targets]
    io.save_json(dst / "test_targets_bop19.json", io.targets_to_json(all_targets))
    return dst


PHASES = ("load", "depth I/O", "render", "VSD", "MSSD/MSPD", "ADD/ADI", "matching+scores")


class _InlineExecutor:
    """Stands in for the evaluator's thread pool: runs each job at once (serial phase timing)."""

    def __init__(self, *_):
        pass

    def submit(self, fn, *args) -> Future:
        f: Future = Future()
        f.set_result(fn(*args))
        return f

    def shutdown(self, cancel_futures: bool = False) -> None:
        pass


@contextlib.contextmanager
def phase_timers(seconds: dict[str, float]):
    """Wrap the evaluator's functions with wall-clock timers; ``seconds`` gets phase -> s (outermost
    call only, so nested phases are not counted twice). "load" = the rest (dataset, models, CSV, symmetries,
    Python glue)."""
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.eval import evaluator, image_errors
    from cosy_lite.eval.depth_renderer import WindowDepthRenderer
    from cosy_lite.eval.object_errors import ObjectErrors

    active: list[str] = []

    def timed(phase: str, fn):
        def wrapper(*a, **k):
            if active:
                return fn(*a, **k)
            active.append(phase)
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                seconds[phase] += time.perf_counter() - t0
                active.pop()
        return wrapper

    patches = [
        (BopDataset, "load_depth", "depth I/O"),
        (WindowDepthRenderer, "render", "render"),
        (image_errors, "distance_map", "VSD"),
        (image_errors.pose_errors, "vsd", "VSD"),
        (image_errors, "_paste", "VSD"),
        (ObjectErrors, "mssd_mspd", "MSSD/MSPD"),
        (ObjectErrors, "add", "ADD/ADI"),
        (ObjectErrors, "adi", "ADD/ADI"),
        (evaluator, "score_targets", "matching+scores"),
    ]
    saved = [(obj, name, getattr(obj, name)) for obj, name, _ in patches]
    saved.append((evaluator, "ThreadPoolExecutor", evaluator.ThreadPoolExecutor))
    try:
        for obj, name, phase in patches:
            setattr(obj, name, timed(phase, getattr(obj, name)))
        evaluator.ThreadPoolExecutor = _InlineExecutor
        yield seconds
    finally:
        for obj, name, fn in saved:
            setattr(obj, name, fn)


def main(argv: list[str] | None = None) -> int:
    from cosy_lite.bop import io
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.results import results_filename, write_results_csv
    from cosy_lite.eval.evaluator import evaluate

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--estimates", type=int, nargs="+", default=[34, 1000])
    ap.add_argument("--repeat", type=int, default=1, help="runs per size; the fastest is reported")
    ap.add_argument("--phases", action="store_true", help="one more, serial run per size: the time per phase")
    ap.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS),
                    help="bop19: VSD, MSSD, MSPD (the default evaluation); +auc: also ADD, ADI (eval --auc); "
                         "bop19-2proc: on 2 processes (eval --workers 2); bop19-auto: cosy-lite eval's default "
                         "number of processes (one per core, at most 4)")
    args = ap.parse_args(argv)
    name = BopDataset(args.dataset).name
    rows, phase_rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.estimates:
            view = bench_view(args.dataset, Path(tmp) / f"view{n}", n)
            ds = BopDataset(view, name)
            ests = noisy_estimates(ds, n)
            images = {(e.scene_id, e.im_id) for e in ests}
            # Evaluate only the images that hold these estimates: a targets file restricted to them.
            io.save_json(view / "test_targets_bop19.json", io.targets_to_json(
                [t for t in ds.test_targets() if (t.scene_id, t.im_id) in images]))
            csv = Path(tmp) / results_filename("bench", name, "test")
            write_results_csv(csv, ests)
            times: dict[str, list[float]] = defaultdict(list)
            cpus: dict[str, list[float]] = defaultdict(list)
            results = {}
            for _ in range(args.repeat):  # variants alternate: A and B see the same load
                for v in args.variants:
                    t0, c0 = time.perf_counter(), time.process_time()
                    results[v] = evaluate(view, csv, name=name, progress=False, **VARIANTS[v])
                    times[v].append(time.perf_counter() - t0)
                    cpus[v].append(time.process_time() - c0)
            for v in [v for v in args.variants if VARIANTS[v].get("workers", 1) == 1] if args.phases else []:
                seconds: dict[str, float] = defaultdict(float)
                t0 = time.perf_counter()
                with phase_timers(seconds):
                    evaluate(view, csv, name=name, progress=False, **VARIANTS[v])
                total = time.perf_counter() - t0
                seconds["load"] = total - sum(seconds.values())
                phase_rows.append((n, v, total, dict(seconds)))
            for v in args.variants:
                best = int(np.argmin(times[v]))
                dt = times[v][best]
                res = results[v]
                s = res.scores
                auc = f"{s.auc_add_s:.3f}" if s.auc_add_s is not None else "-"
                rows.append((res.n_estimates_evaluated, v, len(images), times[v][0], dt, cpus[v][best],
                             1000 * dt / len(ests), s.ar_vsd, s.ar_mssd, s.ar_mspd, auc))
    print(f"dataset {args.dataset} (test split); GT + noise (<=10 deg, 5 mm sigma), 1 estimate per target; "
          f"best of {args.repeat} run(s); the first run of the process also imports trimesh/pyrender/OpenGL; "
          f"CPU = process CPU time of the best run (all threads); load average {os.getloadavg()[0]:.1f}")
    print("| estimates | variant | images | first run (s) | best (s) | CPU (s) | ms/estimate (best) "
          "| AR_VSD | AR_MSSD | AR_MSPD | AUC ADD(-S) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]:.2f} | {r[4]:.2f} | {r[5]:.2f} | {r[6]:.1f} | {r[7]:.3f} "
              f"| {r[8]:.3f} | {r[9]:.3f} | {r[10]} |")
    if phase_rows:
        print("\nserial run, wall seconds per phase (share of the serial total):")
        print("| estimates | variant | " + " | ".join(PHASES) + " | serial total |")
        print("| --- " * (len(PHASES) + 3) + "|")
        for n, v, total, sec in phase_rows:
            print(f"| {n} | {v} | " + " | ".join(f"{sec.get(p, 0.0):.2f} ({100 * sec.get(p, 0.0) / total:.0f} %)"
                                          for p in PHASES) + f" | {total:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
