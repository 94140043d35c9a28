"""`cosy-lite eval` against the official BOP toolkit, on the same results file in the same run.

Usage: python bench/bench_eval_toolkit.py DATASET_DIR (RESULTS_CSV | --noisy N) [--toolkit DIR --toolkit-python PY]
           [--workers 2 1] [--toolkit-workers N] [--repeat R]

Times the BOP19 evaluation (VSD, MSSD, MSPD, AR) of RESULTS_CSV (e.g. the demo's detector + ICP
file, ``outputs/results/cosyliteicp_ycbvsynth-test.csv``) by ``cosy-lite eval --workers N`` for
each N, and by the toolkit's ``scripts/eval_bop19_pose.py``, alternating within each repeat; prints
a table with each wall time, the ratio toolkit / cosy-lite and both ARs (which must agree).
``--noisy N`` evaluates N GT poses plus noise instead (``bench_eval.py``'s estimates).

The toolkit is not on the package registries and the project never depends on it: give a fetched
copy (``--toolkit``, the repository folder holding ``scripts/`` and ``bop_toolkit_lib/``) and the
Python of a scratch venv where it and its requirements are installed (``--toolkit-python``);
without them only cosy-lite is timed and the table says so. The toolkit knows only the datasets of
its parameter table: the dataset is shown to it, through symlinks in a temporary folder, as
``--toolkit-dataset`` (default ``ycbv``, whose image size, VSD tolerance and object ids a
``ycbvsynth`` folder shares) with its scene ids moved into that dataset's list
(``--toolkit-scene-offset``, default 48), and its ``BOP_NUM_WORKERS`` is ``--toolkit-workers``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TOOLKIT_SCORES = "scores_bop19.json"


def toolkit_view(dataset: Path, results_csv: Path, work: Path, name: str, scene_offset: int) -> tuple[Path, Path, str]:
    """(datasets folder, results folder, result file name) of a symlinked copy the toolkit reads as
    dataset ``name``, with every scene id moved by ``scene_offset`` (into the toolkit's scene list of
    ``name``: it scores only those) in the folders, the targets file and the results file."""
    from cosy_lite.bop.results import parse_results_filename

    view = work / "datasets" / name
    view.mkdir(parents=True)
    for p in dataset.iterdir():
        if p.name not in ("test", "test_targets_bop19.json"):
            (view / p.name).symlink_to(p.resolve())
    (view / "test").mkdir()
    for scene in (dataset / "test").iterdir():
        if scene.is_dir() and scene.name.isdigit():
            (view / "test" / f"{int(scene.name) + scene_offset:06d}").symlink_to(scene.resolve())
    targets = json.loads((dataset / "test_targets_bop19.json").read_text())
    (view / "test_targets_bop19.json").write_text(json.dumps([dict(t, scene_id=t["scene_id"] + scene_offset)
                                                              for t in targets]))
    method, _, split = parse_results_filename(results_csv)
    results = work / "results"
    results.mkdir()
    file_name = f"{method}_{name}-{split}.csv"
    lines = results_csv.read_text().splitlines()
    moved = [lines[0]] + [f"{int(line.split(',', 1)[0]) + scene_offset},{line.split(',', 1)[1]}" for line in lines[1:] if line]
    (results / file_name).write_text("\n".join(moved))
    return work / "datasets", results, file_name


def run_toolkit(toolkit: Path, python: Path, dataset: Path, results_csv: Path, name: str, workers: int,
                scene_offset: int) -> tuple[float, float]:
    """(wall seconds, AR) of the toolkit's eval_bop19_pose.py on ``results_csv``."""
    with tempfile.TemporaryDirectory(prefix="bop_toolkit_") as tmp:
        work = Path(tmp)
        datasets, results, file_name = toolkit_view(dataset, results_csv, work, name, scene_offset)
        env = dict(os.environ, BOP_PATH=str(datasets), BOP_RESULTS_PATH=str(results), BOP_EVAL_PATH=str(work / "eval"),
                   BOP_NUM_WORKERS=str(workers), PYTHONPATH=str(toolkit), EGL_PLATFORM="surfaceless",  # vispy offscreen
                   PATH=f"{python.parent}{os.pathsep}{os.environ.get('PATH', '')}")  # its scripts call `python`
        cmd = [str(python), str(toolkit / "scripts" / "eval_bop19_pose.py"), f"--result_filenames={file_name}",
               f"--num_workers={workers}"]
        t0 = time.perf_counter()
        done = subprocess.run(cmd, env=env, capture_output=True, text=True)
        seconds = time.perf_counter() - t0
        scores = list((work / "eval").rglob(TOOLKIT_SCORES))
        if done.returncode != 0 or not scores:
            raise RuntimeError(f"the toolkit failed ({' '.join(cmd)}):\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
        return seconds, float(json.loads(scores[0].read_text())["bop19_average_recall"])


def run_cosy_lite(dataset: Path, results_csv: Path, workers: int) -> tuple[float, float]:
    """(wall seconds, AR) of ``cosy-lite eval --workers N`` (in a fresh process, as a user runs it)."""
    with tempfile.TemporaryDirectory(prefix="cosy_lite_eval_") as tmp:
        cmd = [sys.executable, "-m", "cosy_lite.cli", "eval", "--dataset", str(dataset), "--results", str(results_csv),
               "--workers", str(workers), "--no-progress", "--out", tmp]
        t0 = time.perf_counter()
        done = subprocess.run(cmd, capture_output=True, text=True)
        seconds = time.perf_counter() - t0
        if done.returncode != 0:
            raise RuntimeError(f"cosy-lite eval failed ({' '.join(cmd)}):\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
        return seconds, float(json.loads((Path(tmp) / "scores.json").read_text())["ar"])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("results", type=Path, nargs="?", help="a BOP19 results CSV for DATASET's test split")
    ap.add_argument("--noisy", type=int, default=None, metavar="N", help="instead: N GT poses plus noise")
    ap.add_argument("--toolkit", type=Path, default=None, help="a fetched bop_toolkit repository")
    ap.add_argument("--toolkit-python", type=Path, default=None, help="the Python of a venv where it is installed")
    ap.add_argument("--toolkit-dataset", default="ycbv", help="the name the toolkit reads the dataset as")
    ap.add_argument("--toolkit-scene-offset", type=int, default=48,
                    help="added to every scene id for the toolkit (ycbv's test scenes are 48..59)")
    ap.add_argument("--toolkit-workers", type=int, default=2, help="the toolkit's BOP_NUM_WORKERS")
    ap.add_argument("--workers", type=int, nargs="+", default=[2, 1], help="cosy-lite eval --workers values")
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args(argv)

    if (args.results is None) == (args.noisy is None):
        ap.error("give RESULTS_CSV or --noisy N")
    with tempfile.TemporaryDirectory(prefix="bench_eval_toolkit_") as tmp:
        if args.noisy is not None:
            args.results = noisy_results(args.dataset, args.noisy, Path(tmp))
        return compare(args)


def noisy_results(dataset: Path, n: int, folder: Path) -> Path:
    from bench_eval import noisy_estimates

    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.results import results_filename, write_results_csv

    ds = BopDataset(dataset)
    path = folder / results_filename("noisy", ds.name, "test")
    write_results_csv(path, noisy_estimates(ds, n))
    return path


def compare(args: argparse.Namespace) -> int:
    """Time every variant, alternating, and print the table (1 if the ARs differ)."""
    with_toolkit = args.toolkit is not None and args.toolkit_python is not None
    if not with_toolkit:
        print("toolkit not timed: give --toolkit DIR (a fetched bop_toolkit) and --toolkit-python PY (its venv's "
              "Python); only cosy-lite eval is timed")
    elif not (args.toolkit / "scripts" / "eval_bop19_pose.py").is_file() or not args.toolkit_python.is_file():
        print(f"error: no scripts/eval_bop19_pose.py in {args.toolkit} or no Python at {args.toolkit_python}")
        return 2
    times: dict[str, list[float]] = {}
    ars: dict[str, float] = {}
    for _ in range(args.repeat):  # alternate, so that a change of load hits every variant alike
        for w in args.workers:
            s, ar = run_cosy_lite(args.dataset, args.results, w)
            times.setdefault(f"cosy-lite eval --workers {w}", []).append(s)
            ars[f"cosy-lite eval --workers {w}"] = ar
        if with_toolkit:
            s, ar = run_toolkit(args.toolkit, args.toolkit_python, args.dataset, args.results, args.toolkit_dataset,
                                args.toolkit_workers, args.toolkit_scene_offset)
            name = f"toolkit eval_bop19_pose.py ({args.toolkit_workers} workers)"
            times.setdefault(name, []).append(s)
            ars[name] = ar
    toolkit_best = min((min(v) for k, v in times.items() if k.startswith("toolkit")), default=None)
    print(f"\n{args.results.name} on {args.dataset} (best of {args.repeat}; load {os.getloadavg()[0]:.2f})\n")
    print("| evaluator | wall s | toolkit / this | AR |")
    print("| --- | ---: | ---: | ---: |")
    for k, v in times.items():
        ratio = f"{toolkit_best / min(v):.1f}x" if toolkit_best is not None else "-"
        print(f"| {k} | {min(v):.1f} | {ratio} | {ars[k]:.6f} |")
    if with_toolkit and len({round(a, 9) for a in ars.values()}) > 1:
        print("error: the ARs differ")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
