"""``cosy-lite demo``: the whole job end to end on the embedded default data (the README's main command).

Steps, each a separate process (the commands a user would type), each skipped when its output
is already there, so an interrupted demo continues where it stopped. By default (a dataset with
shipped reference models, :mod:`cosy_lite.weights.reference_models`):

1. generate the dataset's ``test`` split and a small part of ``train_pbr``
   (:attr:`DemoConfig.short_train_images`) if absent, and validate it;
2. infer on the test split with the reference models (``cosy-lite infer --pretrained NAME``: detector ->
   silhouette templates -> refiner -> depth ICP), and the same with oracle (ground-truth) masks, so
   detector and pose errors can be told apart; each run also writes its poses before ICP (the
   RGB-only results: ``--also-before-icp``); the two runs side by side, one core each;
3. evaluate every CSV (``cosy-lite eval``; the detector's boxes too: ``--task 2d-detection``);
4. a short training run of each network from its ImageNet start (:attr:`DemoConfig.short_minutes`,
   ``loop.val_at_start``): the detector on both cores, then coarse and refiner side by side; the
   loss falls and the held-out error moves (``OUT/demo_training.png``, a table);
5. print the AR table (also ``OUT/demo_summary.md``, ``OUT/demo_ar.png``) and the training table.

With ``train=True`` (``cosy-lite demo --train``, ``make train``; datasets without reference
models) step 4 is the demo profile's full from-scratch training instead (the whole dataset is
generated; detector, then refiner on both cores, :attr:`DemoConfig.train_minutes`; with
``start="coarse"`` the coarse network beside the refiner) and step 2 uses those networks.

With ``quick=True`` (``cosy-lite demo --quick``) every step runs at toy size (:data:`QUICK`: two test
images, a few training images, two training steps per network, validation on two images), into
folders of its own (``data/quick``, ``runs/demo-quick``, ``outputs/quick``): a smoke test of an
installation (a few minutes on 2 cores) whose numbers mean nothing.

Each step runs ``python -m cosy_lite.cli COMMAND`` with this interpreter (``torchrun -m cosy_lite.cli
train`` for DDP): the demo needs the installed package only, not a source checkout, and works in any
folder (relative paths are the current folder's).
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
from typing import TypedDict

from cosy_lite.inference.starts import STARTS, TEMPLATE_STARTS

MODELS = ("detector", "coarse", "refiner")
# --train, template starts: the templates tried per detection by the from-scratch refiner (its confidence
# picks one; the reference sets say their own in pipeline.json)
TRAIN_CANDIDATES = 5
METRICS = {"AR": "ar", "AR_VSD": "ar_vsd", "AR_MSSD": "ar_mssd", "AR_MSPD": "ar_mspd"}  # column -> scores.json key
MSSD_RECALL = "MSSD recall 0.1 d"
# short runs: model -> (held-out key of its log, what it is), validated before and after training
SHORT_VAL = {"detector": ("val/ap50", "validation AP50"),
             "coarse": ("val/iter1/rot_err_deg_median", "validation rotation error after 1 iteration (deg)"),
             "refiner": ("val/iter1/rot_err_deg_median", "validation rotation error after 1 iteration (deg)")}
# short warm-up (the profiles' 50-200 steps would take the whole run), validation only before and
# after (val_every beyond the run's steps: a validation of the refiner costs ~20 s on one core)
SHORT_OVERRIDES = {"detector": ["optim.warmup_steps=10", "loop.val_every=1000", "data.val_images=10"],
                   "coarse": ["optim.warmup_steps=10", "loop.val_every=1000", "data.val_images=10", "data.val_instances=32"],
                   "refiner": ["optim.warmup_steps=10", "loop.val_every=1000", "data.val_images=10", "data.val_instances=32",
                               "val_iterations=1"]}


class QuickSettings(TypedDict):
    """Type of :data:`QUICK`: its folders and sizes."""

    data_root: Path
    runs: Path
    out: Path
    short_train_images: int
    vis: int


# --quick (a smoke test: its numbers say nothing about the method): its own folders, 2 test images and
# 8 training images of 4 objects each (one layout per split), overlays of 1 image, and ...
QUICK: QuickSettings = {"data_root": Path("data") / "quick", "runs": Path("runs") / "demo-quick",
                        "out": Path("outputs") / "quick", "short_train_images": 8, "vis": 1}
QUICK_GENERATE = ["test.n_images=2", "test.views_per_layout=2", f"train.views_per_layout={QUICK['short_train_images']}",
                  "objects_per_layout=[4,4]", "distractors_per_layout=[0,1]"]
# ... 2 training steps of batch 2 per network, validated on 2 images (after the demo's own overrides: these win)
QUICK_TRAIN = ["loop.steps=2", "loop.batch_size=2", "loop.log_every=1", "data.val_images=2"]
QUICK_OVERRIDES = {"detector": QUICK_TRAIN, "coarse": [*QUICK_TRAIN, "data.val_instances=4"],
                   "refiner": [*QUICK_TRAIN, "data.val_instances=4"]}
CLI = ("-m", "cosy_lite.cli")  # how the demo runs each step: this interpreter, the installed package


@dataclass
class InferRun:
    """One ``cosy-lite infer`` run of the demo: its method name (CSV prefix) and extra arguments;
    before_icp: (method, label) of the same run's poses before ICP (``--also-before-icp``)."""

    method: str
    label: str
    args: list[str]
    before_icp: tuple[str, str] | None = None


@dataclass
class DemoConfig:
    dataset: str = "ycbvsynth"
    data_root: Path = Path("data")
    runs: Path = Path("runs") / "demo"
    out: Path = Path("outputs")
    train: bool = False  # train the networks from scratch instead of using the reference models
    pretrained: str | None = None  # reference models (default: the dataset's, when shipped)
    # train=True: the detector's profile's 1200 steps would take 17.5-21 min on the 2-core machine (0.95-1.15
    # steps/s with 2 DDP processes), so the budget, a cap, ends it first (1026 steps in 18 min: validation
    # AP50 0.57); then the refiner, also on both cores (start="coarse": coarse and refiner side by side,
    # one core each). Measured 42 min from a clean clone: setup + generation ~8, detector 16.4, refiner
    # 10.4, inference 6.9, evaluation 0.6
    train_minutes: dict[str, float] = field(default_factory=lambda: {"detector": 16.0, "coarse": 9.5, "refiner": 9.5})
    # the short runs that show each network learning (reference-model mode)
    short_minutes: dict[str, float] = field(default_factory=lambda: {"detector": 1.0, "coarse": 1.0, "refiner": 1.0})
    short_train_images: int = 100  # train_pbr images generated for them when the dataset is absent
    start: str = "templates"  # --train: cosy-lite infer --start: "templates" (no coarse network) or "coarse"
    n_candidates: int | None = None  # --train, template starts: cosy-lite infer --candidates (None: TRAIN_CANDIDATES)
    vis: int = 4
    threads: int = 2
    quick: bool = False  # every step at toy size (QUICK, QUICK_GENERATE, QUICK_OVERRIDES), a smoke test

    @property
    def reference(self) -> str | None:
        """The reference models the demo infers with (None: it trains its own)."""
        from cosy_lite.weights.reference_models import reference_names

        if self.train:
            return None
        name = self.pretrained or self.dataset
        return name if (self.pretrained or name in reference_names()) else None


def trained_models(cfg: DemoConfig) -> tuple[str, ...]:
    """The models the demo trains: all three in its short runs; from scratch, no coarse network when
    the poses start from templates."""
    if cfg.reference is not None or cfg.start == "coarse":
        return MODELS
    return tuple(m for m in MODELS if m != "coarse")


def model_args(cfg: DemoConfig) -> list[str]:
    """cosy-lite infer's networks and start: the reference models, or the demo's trained checkpoints."""
    if cfg.reference is not None:
        return ["--pretrained", cfg.reference, "--templates-cache", str(cfg.runs / "templates")]
    start = (["--coarse", str(cfg.runs / "coarse" / "checkpoint.pt")] if cfg.start == "coarse"
             else ["--start", cfg.start, "--candidates", str(train_candidates(cfg)),
                   "--templates-cache", str(cfg.runs / "templates")])
    return start + ["--refiner", str(cfg.runs / "refiner" / "checkpoint.pt")]


def train_candidates(cfg: DemoConfig) -> int:
    return cfg.n_candidates if cfg.n_candidates is not None else TRAIN_CANDIDATES


def inference_start(cfg: DemoConfig) -> str:
    """Where the inference runs start their poses: the reference set's ``pipeline.json``, or ``cfg.start``."""
    if cfg.reference is None:
        return cfg.start
    from cosy_lite.inference.settings import inference_config
    from cosy_lite.weights.reference_models import reference_models

    ref = reference_models(cfg.reference)
    return inference_config(ref.inference, ref.pipeline_path).start


def infer_runs(cfg: DemoConfig) -> list[InferRun]:
    det = [] if cfg.reference is not None else ["--detector", str(cfg.runs / "detector" / "checkpoint.pt")]
    if cfg.reference is not None:
        start, masks = "templates + refiner", "GT boxes + masks"
    else:
        start = ("coarse" if cfg.start == "coarse" else f"templates (top {train_candidates(cfg)})") + " + refiner"
        masks = "GT boxes + masks" if cfg.start in TEMPLATE_STARTS else "GT boxes"
    # each ICP run also writes its poses before ICP: the RGB-only results at no extra cost; the GT masks are exact,
    # so the refined poses are checked and their depth fitted against them (--exact-masks)
    return [
        InferRun("cosyliteicp", f"detector + {start} + depth ICP",
                 det + ["--icp", "--vis", str(cfg.vis), "--also-before-icp", "cosylite"],
                 ("cosylite", f"detector + {start} (RGB)")),
        InferRun("cosyliteoracleicp", f"{masks} (oracle, exact) + {start} + depth ICP",
                 ["--detections", "oracle", "--exact-masks", "--icp", "--also-before-icp", "cosyliteoracle"],
                 ("cosyliteoracle", f"{masks} (oracle, exact) + {start} (RGB)")),
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
    proc = subprocess.run(cmd, env=None if env is None else {**os.environ, **env})
    if proc.returncode != 0:
        raise SystemExit(f"demo: step '{what}' failed (exit {proc.returncode}); fix it and re-run: finished steps are skipped")
    print(f"=== {what}: {time.perf_counter() - t:.0f} s", flush=True)


def _py(*args: str) -> list[str]:
    return [sys.executable, *args]


def _cli(*args: str) -> list[str]:
    """``python -m cosy_lite.cli ARGS``: a cosy-lite command of the package this demo runs from."""
    return _py(*CLI, *args)


def _train_images(root: Path) -> int:
    """Images of the generated ``train_pbr`` scenes (0 without any)."""
    return sum(len(json.loads(p.read_text())) for p in root.glob("train_pbr/*/scene_gt_info.json"))


def _full_train_images(cfg: DemoConfig, synth_cfg: Path) -> int:
    """``train_pbr`` images the from-scratch training wants: the dataset config's (quick: a few)."""
    from cosy_lite.config import load_config
    from cosy_lite.synth.generator import SynthConfig

    if cfg.quick:
        return cfg.short_train_images
    return load_config(SynthConfig, synth_cfg if synth_cfg.is_file() else None).split_config("train_pbr").n_images


def prepare_dataset(cfg: DemoConfig) -> Path:
    """Generate what is missing (the test split; ``train_pbr``: all of it when training from scratch, else
    :attr:`DemoConfig.short_train_images` images, enough for the short runs) and validate the dataset."""
    from cosy_lite.config import packaged_config
    from cosy_lite.synth.ownership import recorded_meshes

    root = cfg.data_root / cfg.dataset
    synth_cfg = packaged_config("synth", f"{cfg.dataset}.yaml")
    extra = ["--config", str(synth_cfg)] if synth_cfg.is_file() else []
    if cfg.quick:
        extra += QUICK_GENERATE
    generate = _cli("generate", "--out", str(root), "--workers", "2", *extra)
    has_test = (root / "test_targets_bop19.json").is_file()
    n_train = _train_images(root)
    if recorded_meshes(root) is not None:
        _check_your_objects(root, has_test, n_train)  # generated from your meshes: used as it is
    elif cfg.reference is None and not (has_test and n_train >= _full_train_images(cfg, synth_cfg)):
        _run(generate + ([f"train.n_images={cfg.short_train_images}"] if cfg.quick else []), "generate the dataset")
    elif not has_test or not n_train:
        splits = (["test"] if not has_test else []) + (["train_pbr"] if not n_train else [])
        _run(generate + [f"train.n_images={cfg.short_train_images}", "--splits", *splits],
             f"generate the dataset ({', '.join(splits)}; train_pbr: {cfg.short_train_images} images for the short runs)")
    _run(_cli("check-dataset", str(root)), "validate the dataset")
    pictures = {"show": (cfg.out / "demo_show_test_000000_000000.png", ["--split", "test", "--scene", "0", "--image", "0"]),
                "contact-sheet": (cfg.out / "demo_contact_sheet.png", ["--split", "train_pbr", "-n", "16"])}
    for command, (png, args) in pictures.items():
        if not png.is_file():
            _run(_cli(command, str(root), *args, "--out", str(png)),
                 f"{command}: GT contours over the data ({png.name})")
    return root


def _check_your_objects(root: Path, has_test: bool, n_train: int) -> None:
    """A dataset of your meshes (``generate --meshes``) is never regenerated with the library's objects:
    the demo trains and infers on what is there, or says what is missing and the command that adds it."""
    from cosy_lite.synth.ownership import meshes_command, recorded_meshes

    missing = (["test"] if not has_test else []) + (["train_pbr"] if not n_train else [])
    if missing:
        command = meshes_command(root, recorded_meshes(root) or {})
        raise SystemExit(f"demo: {root} holds your meshes (models_sources.json) and has no {' and no '.join(missing)} "
                         f"split; add it with its own meshes, then run the demo again:\n  {command} --splits {' '.join(missing)}")
    print(f"demo: {root}: your meshes, {n_train} train_pbr images and the test split: used as they are", flush=True)


def short_runs(cfg: DemoConfig) -> Path:
    return cfg.runs / "short"


def train_command(cfg: DemoConfig, root: Path, model: str, short: bool = False) -> list[str]:
    """``cosy-lite train`` for ``model`` with the demo profile and budget (``short``: the short run's, from
    its ImageNet start, validated before training too; ``cfg.quick``: a few steps); the detector, and the
    refiner trained alone, as two single-threaded DDP processes (torchrun), which train 1.9x faster than
    one two-threaded process on 2 cores."""
    run_dir = (short_runs(cfg) if short else cfg.runs) / model
    args = [*CLI, "train", "--dataset", str(root), "--model", model, "--profile", "demo", "--out", str(run_dir)]
    if (run_dir / "checkpoint.pt").is_file():
        args.append("--resume")
    args.append(f"loop.max_minutes={(cfg.short_minutes if short else cfg.train_minutes)[model]}")
    if short:
        args += ["loop.val_at_start=true", "loop.log_every=5", *SHORT_OVERRIDES[model]]
    if cfg.quick:
        args += QUICK_OVERRIDES[model]
    if model == "detector" or (model == "refiner" and "coarse" not in trained_models(cfg)):
        return _py("-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", *args, "loop.num_workers=0")
    return _py(*args, "loop.num_workers=0") if short else _py(*args)


def _run_parallel(cmds: list[list[str]], whats: list[str], logs: list[Path]) -> None:
    """Run ``cmds`` at the same time, one OpenMP thread each (stdout/stderr to ``logs``); fail if any fails."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    procs = []
    for cmd, what, log in zip(cmds, whats, logs):
        print(f"\n=== {what} (log: {log})\n$ {' '.join(cmd)}", flush=True)
        log.parent.mkdir(parents=True, exist_ok=True)
        with log.open("w") as out:  # the child keeps its own copy of the descriptor
            procs.append((subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT), what, log))
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


def _mark_done(cfg: DemoConfig, model: str, short: bool = False) -> None:
    run_dir = (short_runs(cfg) if short else cfg.runs) / model
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "DONE").write_text("trained by cosy-lite demo\n")


def short_training(cfg: DemoConfig, root: Path) -> dict[str, dict]:
    """The short run of each network (detector on both cores, then coarse and refiner side by side);
    returns model -> its log's train and validation records."""
    runs = short_runs(cfg)
    todo = [m for m in MODELS if not (runs / m / "DONE").is_file()]
    if "detector" in todo:
        _run(train_command(cfg, root, "detector", short=True),
             f"short run: detector ({cfg.short_minutes['detector']:g} min)", env={"OMP_NUM_THREADS": "1"})
        _mark_done(cfg, "detector", short=True)
    pose = [m for m in todo if m != "detector"]
    if pose:
        _run_parallel([train_command(cfg, root, m, short=True) for m in pose],
                      [f"short run: {m} ({cfg.short_minutes[m]:g} min)" for m in pose],
                      [runs / f"{m}.log" for m in pose])
        for m in pose:
            _mark_done(cfg, m, short=True)
    from cosy_lite.train.run_log import read_log

    logs = {}
    for m in MODELS:
        records = read_log(runs / m / "log.jsonl")
        logs[m] = {"train": [r for r in records if r.get("type") == "train"],
                   "val": [r for r in records if r.get("type") == "val" and SHORT_VAL[m][0] in r]}
    return logs


def training_table(logs: dict[str, dict]) -> str:
    """Per short run: steps, training loss at its first and last log, held-out metric before and after."""
    lines = ["| network | steps | loss first -> last | held-out metric | before -> after |", "| --- | ---: | --- | --- | --- |"]
    for m, log in logs.items():
        key, what = SHORT_VAL[m]
        tr, va = log["train"], log["val"]
        loss = f"{tr[0]['loss/total']:.3f} -> {tr[-1]['loss/total']:.3f}" if tr else "-"
        val = f"{va[0][key]:.3f} (step {va[0]['step']}) -> {va[-1][key]:.3f} (step {va[-1]['step']})" if va else "-"
        lines.append(f"| {m} | {tr[-1]['step'] if tr else 0} | {loss} | {what} | {val} |")
    return "\n".join(lines)


def plot_training(logs: dict[str, dict], path: Path) -> None:
    """One panel per short run: training loss per step, the held-out metric on a second axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(logs), figsize=(4.2 * len(logs), 3.4))
    for ax, (m, log) in zip(axes, logs.items()):
        key, what = SHORT_VAL[m]
        ax.plot([r["step"] for r in log["train"]], [r["loss/total"] for r in log["train"]], ".-", color="tab:blue")
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.set(title=m, xlabel="step", ylabel="training loss")
        ax.yaxis.label.set_color("tab:blue")
        right = ax.twinx()
        right.plot([r["step"] for r in log["val"]], [r[key] for r in log["val"]], "o-", color="tab:red")
        right.set_ylabel(what, color="tab:red", fontsize=8)
        right.ticklabel_format(axis="y", useOffset=False)
    fig.suptitle("cosy-lite demo: short training runs from the ImageNet start (loss, held-out metric)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def prepare_templates(cfg: DemoConfig, root: Path) -> None:
    """With silhouette-template starts: the templates of the test targets' objects rendered into the
    runs' cache by ``cosy-lite templates``, half of the objects on each core, before the inference runs
    (side by side, each would render every object itself). Objects already cached are skipped."""
    targets = root / "test_targets_bop19.json"
    if "--templates-cache" not in model_args(cfg) or not targets.is_file():
        return  # (no targets: the inference runs say so themselves)
    start = inference_start(cfg)
    if start not in TEMPLATE_STARTS:
        return
    from cosy_lite.bop import io

    ids = sorted({t.obj_id for t in io.load_test_targets(targets)})
    halves = [ids[0::2], ids[1::2]]
    cache = cfg.runs / "templates"
    cmds = [_cli("templates", "--dataset", str(root), "--cache", str(cache), "--objects", ",".join(map(str, h)),
                 "--start", start) for h in halves if h]
    _run_parallel(cmds, [f"silhouette templates of objects {h}" for h in halves if h],
                  [cfg.out / "logs" / f"templates_{k}.log" for k in range(len(cmds))])


def infer_and_eval(cfg: DemoConfig, root: Path) -> list[tuple[InferRun, dict]]:
    """The unfinished ``cosy-lite infer`` runs side by side (``cfg.threads`` shared between them: much of a
    run is single-threaded rendering, ICP and template matching), then every evaluation."""
    todo = []
    for run in infer_runs(cfg):
        csv = _csv(cfg, run.method)
        wanted = [csv] + ([_csv(cfg, run.before_icp[0])] if run.before_icp is not None else [])
        if not all(p.is_file() for p in wanted):
            todo.append(run)
    threads = max(1, cfg.threads // max(1, len(todo)))
    if len(todo) > 1:
        prepare_templates(cfg, root)
    cmds, whats = [], []
    for run in todo:
        csv = _csv(cfg, run.method)
        cmds.append(_cli("infer", "--dataset", str(root), *model_args(cfg), "--threads", str(threads),
                        "--method", run.method, "--out", str(csv.parent),
                        *(["--no-progress"] if len(todo) > 1 else []), *run.args))
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
            _run(_cli("eval", "--dataset", str(root), "--results", str(csv), "--out", str(scores.parent)),
                 f"evaluate: {run.label}")
        results.append((run, json.loads(scores.read_text())))
    return results


def detector_scores(cfg: DemoConfig, root: Path) -> dict | None:
    """COCO box AP of the detector run's detections on the test split (``cosy-lite eval --task
    2d-detection``, boxes of the visible part, as the detector is trained), None without them."""
    dets = _csv(cfg, infer_runs(cfg)[0].method).with_suffix(".json")
    out = dets.parent / f"{dets.stem}_eval"
    scores = out / "scores_bop22_coco_bbox_modal.json"
    if not dets.is_file():
        return None
    if not scores.is_file():
        _run(_cli("eval", "--dataset", str(root), "--results", str(dets), "--task", "2d-detection",
                 "--bbox-type", "modal", "--out", str(out)), "evaluate: the detector's boxes")
    return json.loads(scores.read_text())


def _metric(scores: dict, column: str) -> float:
    if column == MSSD_RECALL:  # recall at the second MSSD threshold, 0.1 x the diameter
        return float(scores["recall_mssd"][scores["thresholds"]["mssd_x_diameter"].index(0.1)])
    return float(scores[METRICS[column]])


def summary_table(results: list[tuple[InferRun, dict]]) -> str:
    columns = [*METRICS, MSSD_RECALL]
    lines = ["| pipeline | " + " | ".join(columns) + " |", "| --- |" + " --- |" * len(columns)]
    for run, scores in results:
        lines.append(f"| {run.label} | " + " | ".join(f"{_metric(scores, m):.3f}" for m in columns) + " |")
    return "\n".join(lines)


def plot_summary(results: list[tuple[InferRun, dict]], path: Path, title: str = "") -> None:
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
    ax.set_title(title or "cosy-lite demo: test split")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dataset", default=DemoConfig.dataset, help="synthetic dataset name (generated if absent)")
    p.add_argument("--data-root", type=Path, default=None,
                   help=f"datasets folder (default {DemoConfig.data_root}/; --quick: {QUICK['data_root']}/)")
    p.add_argument("--runs", type=Path, default=None,
                   help=f"run folders of the three models (default {DemoConfig.runs}/; --quick: {QUICK['runs']}/)")
    p.add_argument("--out", type=Path, default=None,
                   help=f"CSVs, scores, overlays, summary (default {DemoConfig.out}/, --quick: {QUICK['out']}/; "
                        "with --train: its train/ subfolder)")
    p.add_argument("--train", action="store_true",
                   help="train the networks from scratch (demo profiles, ~40 min) instead of inferring with the shipped "
                        "reference models (the default for datasets that have them)")
    p.add_argument("--pretrained", default=None, metavar="NAME",
                   help="reference models to infer with (default: the dataset's, when shipped)")
    p.add_argument("--minutes", type=float, nargs=3, metavar=("DET", "COARSE", "REF"), default=None,
                   help="training budget per model (--train: default 16 9.5 9.5; else the short runs: 1 1 1)")
    p.add_argument("--start", choices=STARTS, default=DemoConfig.start,
                   help="--train: start poses from silhouette templates (default; the coarse network is not trained) "
                        "or the trained coarse network (CosyPose)")
    p.add_argument("--candidates", type=int, default=None, metavar="K",
                   help=f"--train --start templates: templates tried per detection (default {TRAIN_CANDIDATES})")
    p.add_argument("--quick", action="store_true",
                   help=f"every step at toy size, a smoke test of the installation (a few minutes; the numbers mean "
                        f"nothing): 2 test images and {QUICK['short_train_images']} training images generated, 2 training "
                        f"steps per network, validation on 2 images; own folders (defaults {QUICK['data_root']}/, "
                        f"{QUICK['runs']}/, {QUICK['out']}/)")


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    from cosy_lite.bop.params import RENAMED_DATASETS, renamed_dataset_message
    from cosy_lite.errors import BopFormatError
    from cosy_lite.weights.reference_models import reference_models

    if args.dataset in RENAMED_DATASETS:
        raise BopFormatError((args.data_root or DemoConfig.data_root) / args.dataset, "--dataset",
                             renamed_dataset_message(args.dataset) + f": use --dataset {RENAMED_DATASETS[args.dataset]}")
    defaults: dict[str, Path] = ({"data_root": QUICK["data_root"], "runs": QUICK["runs"], "out": QUICK["out"]} if args.quick
                                 else {"data_root": DemoConfig.data_root, "runs": DemoConfig.runs, "out": DemoConfig.out})
    data_root = args.data_root if args.data_root is not None else defaults["data_root"]
    runs = args.runs if args.runs is not None else defaults["runs"]
    out = args.out if args.out is not None else defaults["out"]
    if args.train and args.out is None:
        out = out / "train"  # apart from the reference results
    cfg = DemoConfig(dataset=args.dataset, data_root=data_root, runs=runs, out=out, train=args.train,
                     pretrained=args.pretrained, start=args.start, n_candidates=args.candidates)
    if args.quick:
        cfg.quick, cfg.short_train_images, cfg.vis = True, QUICK["short_train_images"], QUICK["vis"]
    if cfg.reference is not None:
        reference_models(cfg.reference)  # an unknown --pretrained name fails here, before any work
    if args.minutes:
        setattr(cfg, "train_minutes" if cfg.reference is None else "short_minutes", dict(zip(MODELS, args.minutes)))
    t0 = time.perf_counter()
    root = prepare_dataset(cfg)
    if cfg.reference is None:
        train_models(cfg, root)
    results = infer_and_eval(cfg, root)
    det = detector_scores(cfg, root)
    logs = short_training(cfg, root) if cfg.reference is not None else None
    cfg.out.mkdir(parents=True, exist_ok=True)
    where = (f"reference models {cfg.reference!r}" if cfg.reference is not None
             else "demo-profile models trained on the CPU")
    table = summary_table(results)
    lines = [f"Test split of {cfg.dataset}, {where}:", "", table]
    if det is not None:
        lines += ["", f"Detector boxes (visible part), COCO AP50 {det['AP50']:.3f}, AP {det['AP']:.3f}"]
    if logs is not None:
        plot_training(logs, cfg.out / "demo_training.png")
        lines += ["", "Short training runs (from the ImageNet start; plot: demo_training.png):", "", training_table(logs)]
    plot_summary(results, cfg.out / "demo_ar.png", f"cosy-lite demo: test split, {where}")
    (cfg.out / "demo_summary.md").write_text("\n".join(lines) + "\n")
    print("\n" + "\n".join(lines))
    print(f"\noverlays (estimates over the test images, GT in another colour): {cfg.out / 'results' / 'vis'}")
    print(f"AR plot: {cfg.out / 'demo_ar.png'}; recall curves: {cfg.out / 'results'}/*_eval/recall_curves.png")
    print(f"demo wall time: {(time.perf_counter() - t0) / 60:.1f} min")
    return 0
