"""``cosy-lite demo``: the whole job end to end on the embedded default data (the README's main command).

Steps, each a separate process (the commands a user would type), each skipped when its output
is already there, so an interrupted demo continues where it stopped:

1. generate the default dataset ``ycbvsynth`` (if absent) and validate it;
2. train the detector and the refiner (``configs/MODEL/demo.yaml`` with a shorter time budget per
   model, :attr:`DemoConfig.train_minutes`), each as two single-threaded DDP processes; a run
   folder with a checkpoint but no ``DONE`` marker is resumed. The poses start from silhouette
   templates matched to the detection masks (``infer.py --start templates``): at this budget the
   trained coarse network starts no better than the box pose (bench/RESULTS.md, issue 13), so it
   is trained only with ``DemoConfig(start="coarse")``;
3. infer on the test split: detector -> templates -> refiner -> depth ICP, and the same with oracle
   (ground-truth) detections, so detector and pose errors can be told apart; each run also writes its
   poses before ICP (the RGB-only results: ``infer.py --also-before-icp``); the two runs side by side,
   one core each (logs in ``OUT/logs/``);
4. evaluate every CSV (``cosy-lite eval``) and print one AR table (also written to
   ``OUT/demo_summary.md`` and ``OUT/demo_ar.png``), with where the overlays are.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
MODELS = ("detector", "coarse", "refiner")
METRICS = {"AR": "ar", "AR_VSD": "ar_vsd", "AR_MSSD": "ar_mssd", "AR_MSPD": "ar_mspd"}  # column -> scores.json key


@dataclass
class InferRun:
    """One ``infer.py`` run of the demo: its method name (CSV prefix) and extra arguments;
    before_icp: (method, label) of the same run's poses before ICP (``--also-before-icp``)."""

    method: str
    label: str
    args: list[str]
    before_icp: tuple[str, str] | None = None


@dataclass
class DemoConfig:
    dataset: str = "ycbvsynth"
    data_root: Path = REPO / "data"
    runs: Path = REPO / "runs" / "demo"
    out: Path = REPO / "outputs"
    # detector: its profile's 1200 steps would take 17.5-21 min on the 2-core machine (0.95-1.15 steps/s
    # with 2 DDP processes), so the budget, a cap, ends it first (1026 steps in 18 min: validation
    # AP50 0.57); then the refiner, also on both cores (start="coarse": coarse and refiner side by side,
    # one core each). 16 + 9.5 min keep make demo within its 45 minutes from a clean clone (measured
    # 42 min: setup + generation ~8, detector 16.4, refiner 10.4, inference 6.9, evaluation 0.6)
    train_minutes: dict[str, float] = field(default_factory=lambda: {"detector": 16.0, "coarse": 9.5, "refiner": 9.5})
    n_refiner_iters: int = 4
    start: str = "templates"  # infer.py --start: "templates" (no coarse network) or "coarse"
    n_candidates: int = 5  # infer.py --candidates (start="templates")
    vis: int = 4
    threads: int = 2


def trained_models(cfg: DemoConfig) -> tuple[str, ...]:
    """The models the demo trains: no coarse network when the poses start from templates."""
    return MODELS if cfg.start == "coarse" else tuple(m for m in MODELS if m != "coarse")


def infer_runs(cfg: DemoConfig) -> list[InferRun]:
    det = ["--detector", str(cfg.runs / "detector" / "checkpoint.pt")]
    start = "coarse" if cfg.start == "coarse" else f"templates (top {cfg.n_candidates})"
    masks = "GT boxes + masks" if cfg.start == "templates" else "GT boxes"
    # each ICP run also writes its poses before ICP: the RGB-only results at no extra cost
    return [
        InferRun("cosyliteicp", f"detector + {start} + refiner + depth ICP",
                 det + ["--icp", "--vis", str(cfg.vis), "--also-before-icp", "cosylite"],
                 ("cosylite", f"detector + {start} + refiner (RGB)")),
        InferRun("cosyliteoracleicp", f"{masks} (oracle) + {start} + refiner + depth ICP",
                 ["--detections", "oracle", "--icp", "--also-before-icp", "cosyliteoracle"],
                 ("cosyliteoracle", f"{masks} (oracle) + {start} + refiner (RGB)")),
    ]


def scored_runs(cfg: DemoConfig) -> list[InferRun]:
    """The results the demo scores, one per CSV: each run's poses before ICP, then after."""
    out = []
    for run in infer_runs(cfg):
        if run.before_icp is not None:
            out.append(InferRun(run.before_icp[0], run.before_icp[1], run.args))
        out.append(run)
    return out


def _csv(cfg: DemoConfig, method: str) -> Path:
    return cfg.out / "results" / f"{method}_{cfg.dataset}-test.csv"


def _run(cmd: list[str], what: str, env: dict[str, str] | None = None) -> None:
    print(f"\n=== {what}\n$ {' '.join(cmd)}", flush=True)
    t = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, env=None if env is None else {**os.environ, **env})
    if proc.returncode != 0:
        raise SystemExit(f"demo: step '{what}' failed (exit {proc.returncode}); fix it and re-run: finished steps are skipped")
    print(f"=== {what}: {time.perf_counter() - t:.0f} s", flush=True)


def _py(*args: str) -> list[str]:
    return [sys.executable, *args]


def prepare_dataset(cfg: DemoConfig) -> Path:
    root = cfg.data_root / cfg.dataset
    if not (root / "test_targets_bop19.json").is_file():
        synth_cfg = REPO / "configs" / "synth" / f"{cfg.dataset}.yaml"
        extra = ["--config", str(synth_cfg)] if synth_cfg.is_file() else []
        _run(_py("-m", "cosy_lite.cli", "generate", "--out", str(root), "--workers", "2", *extra), "generate the dataset")
    _run(_py("-m", "cosy_lite.cli", "check-dataset", str(root)), "validate the dataset")
    return root


def train_command(cfg: DemoConfig, root: Path, model: str) -> list[str]:
    """``train.py`` for ``model`` with the demo profile and budget; the detector as two single-threaded
    DDP processes (torchrun), which train 1.9x faster than one two-threaded process on 2 cores."""
    run_dir = cfg.runs / model
    args = ["train.py", "--dataset", str(root), "--model", model, "--profile", "demo", "--out", str(run_dir)]
    if (run_dir / "checkpoint.pt").is_file():
        args.append("--resume")
    args.append(f"loop.max_minutes={cfg.train_minutes[model]}")
    if model == "detector" or (model == "refiner" and "coarse" not in trained_models(cfg)):
        return _py("-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", *args, "loop.num_workers=0")
    return _py(*args)


def _run_parallel(cmds: list[list[str]], whats: list[str], logs: list[Path]) -> None:
    """Run ``cmds`` at the same time, one OpenMP thread each (stdout/stderr to ``logs``); fail if any fails."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    procs = []
    for cmd, what, log in zip(cmds, whats, logs):
        print(f"\n=== {what} (log: {log})\n$ {' '.join(cmd)}", flush=True)
        log.parent.mkdir(parents=True, exist_ok=True)
        with log.open("w") as out:  # the child keeps its own copy of the descriptor
            procs.append((subprocess.Popen(cmd, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT), what, log))
    t = time.perf_counter()
    failed = []
    for proc, what, log in procs:
        if proc.wait() != 0:
            failed.append(f"'{what}' (exit {proc.returncode}, see {log})")
        else:
            print(f"=== {what}: {time.perf_counter() - t:.0f} s; last lines of {log}:", flush=True)
            print("\n".join(log.read_text(errors="replace").splitlines()[-8:]), flush=True)
    if failed:
        raise SystemExit(f"demo: {', '.join(failed)} failed; fix it and re-run: finished steps are skipped")


def train_models(cfg: DemoConfig, root: Path) -> None:
    """The detector (both cores), then the refiner (both cores), or the coarse model and the refiner
    side by side (one core each)."""
    todo = []
    for model in trained_models(cfg):
        if (cfg.runs / model / "DONE").is_file():
            print(f"=== train {model}: done before ({cfg.runs / model})")
        else:
            todo.append(model)
    if "detector" in todo:
        _run(train_command(cfg, root, "detector"), f"train detector ({cfg.train_minutes['detector']:g} min budget)",
             env={"OMP_NUM_THREADS": "1"})
        _mark_done(cfg, "detector")
    pose = [m for m in todo if m != "detector"]
    if pose == ["refiner"] and "coarse" not in trained_models(cfg):
        _run(train_command(cfg, root, "refiner"), f"train refiner ({cfg.train_minutes['refiner']:g} min budget)",
             env={"OMP_NUM_THREADS": "1"})
        _mark_done(cfg, "refiner")
    elif pose:
        _run_parallel([train_command(cfg, root, m) for m in pose],
                      [f"train {m} ({cfg.train_minutes[m]:g} min budget)" for m in pose],
                      [cfg.runs / f"{m}.log" for m in pose])
        for m in pose:
            _mark_done(cfg, m)


def _mark_done(cfg: DemoConfig, model: str) -> None:
    run_dir = cfg.runs / model
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "DONE").write_text("trained by cosy-lite demo\n")


def infer_and_eval(cfg: DemoConfig, root: Path) -> list[tuple[InferRun, dict]]:
    """The unfinished ``infer.py`` runs side by side (``cfg.threads`` shared between them: much of a
    run is single-threaded rendering, ICP and template matching), then every evaluation."""
    todo = []
    for run in infer_runs(cfg):
        csv = _csv(cfg, run.method)
        wanted = [csv] + ([_csv(cfg, run.before_icp[0])] if run.before_icp is not None else [])
        if not all(p.is_file() for p in wanted):
            todo.append(run)
    threads = max(1, cfg.threads // max(1, len(todo)))
    cmds, whats = [], []
    for run in todo:
        csv = _csv(cfg, run.method)
        start = (["--coarse", str(cfg.runs / "coarse" / "checkpoint.pt")] if cfg.start == "coarse"
                 else ["--start", "templates", "--candidates", str(cfg.n_candidates),
                       "--templates-cache", str(cfg.runs / "templates")])
        cmds.append(_py("infer.py", "--dataset", str(root), *start,
                        "--refiner", str(cfg.runs / "refiner" / "checkpoint.pt"), "--n-refiner-iters",
                        str(cfg.n_refiner_iters), "--threads", str(threads), "--method", run.method,
                        "--out", str(csv.parent), *(["--no-progress"] if len(todo) > 1 else []), *run.args))
        whats.append(f"infer: {run.label}" + (f" (and {run.before_icp[1]})" if run.before_icp else ""))
    if len(cmds) == 1:
        _run(cmds[0], whats[0])
    elif cmds:
        _run_parallel(cmds, whats, [cfg.out / "logs" / f"infer_{run.method}.log" for run in todo])
    results = []
    for run in scored_runs(cfg):
        csv = _csv(cfg, run.method)
        scores = csv.parent / f"{csv.stem}_eval" / "scores.json"
        if not scores.is_file():
            _run(_py("-m", "cosy_lite.cli", "eval", "--dataset", str(root), "--results", str(csv), "--out", str(scores.parent)),
                 f"evaluate: {run.label}")
        results.append((run, json.loads(scores.read_text())))
    return results


def _metric(scores: dict, column: str) -> float:
    return float(scores[METRICS[column]])


def summary_table(results: list[tuple[InferRun, dict]]) -> str:
    lines = ["| pipeline | " + " | ".join(METRICS) + " |", "| --- |" + " --- |" * len(METRICS)]
    for run, scores in results:
        lines.append(f"| {run.label} | " + " | ".join(f"{_metric(scores, m):.3f}" for m in METRICS) + " |")
    return "\n".join(lines)


def plot_summary(results: list[tuple[InferRun, dict]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(8, 3.6))
    x = np.arange(len(METRICS))
    w = 0.8 / len(results)
    for i, (run, scores) in enumerate(results):
        ax.bar(x + i * w - 0.4 + w / 2, [_metric(scores, m) for m in METRICS], w, label=run.label)
    ax.set_xticks(x, list(METRICS))
    ax.set_ylim(0, 1)
    ax.set_ylabel("recall")
    ax.legend(fontsize=7)
    ax.set_title("cosy-lite demo: test split, demo-profile models trained on the CPU")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dataset", default=DemoConfig.dataset, help="synthetic dataset name (generated if absent)")
    p.add_argument("--data-root", type=Path, default=DemoConfig.data_root)
    p.add_argument("--runs", type=Path, default=DemoConfig.runs, help="run folders of the three models")
    p.add_argument("--out", type=Path, default=DemoConfig.out, help="CSVs, scores, overlays, summary")
    p.add_argument("--minutes", type=float, nargs=3, metavar=("DET", "COARSE", "REF"), default=None,
                   help="training budget per model (default 16 9.5 9.5)")
    p.add_argument("--start", choices=["templates", "coarse"], default=DemoConfig.start,
                   help="start poses: silhouette templates (default; the coarse network is not trained) or the "
                        "trained coarse network (CosyPose)")
    p.add_argument("--candidates", type=int, default=DemoConfig.n_candidates, metavar="K",
                   help=f"--start templates: templates tried per detection (default {DemoConfig.n_candidates})")


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    from cosy_lite.bop.params import RENAMED_DATASETS, renamed_dataset_message
    from cosy_lite.errors import BopFormatError

    if args.dataset in RENAMED_DATASETS:
        raise BopFormatError(args.data_root / args.dataset, "--dataset", renamed_dataset_message(args.dataset)
                             + f": use --dataset {RENAMED_DATASETS[args.dataset]}")
    cfg = DemoConfig(dataset=args.dataset, data_root=args.data_root, runs=args.runs, out=args.out,
                     start=args.start, n_candidates=args.candidates)
    if args.minutes:
        cfg.train_minutes = dict(zip(MODELS, args.minutes))
    t0 = time.perf_counter()
    root = prepare_dataset(cfg)
    train_models(cfg, root)
    results = infer_and_eval(cfg, root)
    cfg.out.mkdir(parents=True, exist_ok=True)
    table = summary_table(results)
    plot_summary(results, cfg.out / "demo_ar.png")
    (cfg.out / "demo_summary.md").write_text(table + "\n")
    print("\n" + table)
    print(f"\noverlays (estimates over the test images, GT in another colour): {cfg.out / 'results' / 'vis'}")
    print(f"AR plot: {cfg.out / 'demo_ar.png'}; recall curves: {cfg.out / 'results'}/*_eval/recall_curves.png")
    print(f"demo wall time: {(time.perf_counter() - t0) / 60:.1f} min")
    return 0
