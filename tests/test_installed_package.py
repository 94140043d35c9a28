"""The package as a user gets it (issue #17): this checkout ``pip install``-ed into a folder outside it,
then ``python -m cosy_lite.cli`` run from another folder with that folder first on ``PYTHONPATH``, so the
installed copy is imported, not the source tree. Its configs and reference models must come with it:
``demo --quick`` (generate, check, pictures, infer with the reference models, eval, short training
runs through torchrun), ``train`` with a packaged profile and ``infer --pretrained``.

Disk: the install (~25 MB), the data (~30 MB) and the runs (~110 MB of checkpoints) are removed at the
end, pass or fail. About 4 minutes on the shared 2-core machine (install 5 s, demo --quick 200 s).
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# what the wheel is built from (configs/: the profiles; models/: the reference models)
BUILD_INPUTS = ("pyproject.toml", "README.md", "cosy_lite", "configs", "models")
SMALL_REFINER = ["loop.steps=2", "loop.batch_size=2", "loop.num_workers=0", "loop.device=cpu", "loop.log_every=1",
                 "data.val_images=1", "data.val_instances=2", "data.n_points=300", "net.arch=early",
                 "net.backbone=resnet18", "net.crop_resolution=[60,80]", "optim.warmup_steps=1"]


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """A folder outside the checkout: ``site/`` (the installed package) and ``cwd/`` (where commands run)."""
    base = tmp_path_factory.mktemp("installed")
    yield base
    for big in (base / "site", base / "cwd" / "data", base / "cwd" / "runs"):  # (CI machines have little disk;
        shutil.rmtree(big, ignore_errors=True)                                #  kept: outputs/ and demo.log)


@pytest.fixture(scope="module")
def site(work: Path) -> Path:
    """``pip install`` of a copy of the checkout's build inputs into ``site/`` (no dependencies: the venv
    has them; no index, no build isolation: nothing is downloaded). Built from a copy so that the
    build's own folders never appear in the checkout."""
    src = work / "src"
    src.mkdir()
    for name in BUILD_INPUTS:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(ROOT / name, src / name)
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-index",
                        "--no-build-isolation", "--target", str(work / "site"), str(src)],
                       capture_output=True, text=True, timeout=600)
    shutil.rmtree(src, ignore_errors=True)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    (work / "cwd").mkdir()
    return work / "site"


def _env(site: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("COSY_LITE_MODELS", "COSY_LITE_DATA", "PYTHONPATH")}
    return {**env, "PYTHONPATH": str(site), "PYOPENGL_PLATFORM": "egl", "OMP_WAIT_POLICY": "PASSIVE"}


def _cli(site: Path, cwd: Path, *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    r = subprocess.run([sys.executable, "-m", "cosy_lite.cli", *args], cwd=cwd, env=_env(site),
                       capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, f"cosy-lite {' '.join(args)}:\n" + r.stdout[-5000:] + r.stderr[-3000:]
    return r


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def test_the_installed_copy_is_imported_and_carries_its_configs_and_reference_models(site, work):
    code = ("import cosy_lite, json; from cosy_lite.config import packaged_config; "
            "from cosy_lite.train.command import default_config_path; "
            "from cosy_lite.weights.reference_models import reference_models, reference_root; "
            "ref = reference_models('ycbvsynth'); "
            "print(json.dumps({'package': cosy_lite.__file__, 'root': str(reference_root()), "
            "'weights': [str(p) for p in ref.weights.values()], 'tiny': str(packaged_config('synth', 'tiny.yaml')), "
            "'profiles': [str(default_config_path(m, p)) for m in ('detector', 'coarse', 'refiner') "
            "for p in ('demo', 'full')]}))")
    r = subprocess.run([sys.executable, "-c", code], cwd=work / "cwd", env=_env(site), capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    found = json.loads(r.stdout)
    paths = [found["package"], found["root"], *found["weights"], found["tiny"], *found["profiles"]]
    for p in map(Path, paths):
        assert p.is_relative_to(site), f"{p}: not from the installed copy in {site}"
    assert all(Path(p).is_file() for p in [*found["weights"], found["tiny"], *found["profiles"]])
    script = site / "bin" / "cosy-lite"  # the console script pip wrote
    r = subprocess.run([str(script), "--help"], cwd=work / "cwd", env=_env(site), capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and all(c in r.stdout for c in ("train", "infer", "demo", "generate")), r.stdout + r.stderr


@pytest.fixture(scope="module")
def quick_demo(site, work) -> Path:
    """``cosy-lite demo --quick`` run in ``cwd/`` (its default folders: data/quick, runs/demo-quick, outputs/quick)."""
    r = _cli(site, work / "cwd", "demo", "--quick", timeout=900)
    (work / "demo.log").write_text(r.stdout + r.stderr)
    return work / "cwd"


@pytest.mark.slow
def test_demo_quick_runs_every_step_from_the_installed_package(quick_demo):
    out, runs = quick_demo / "outputs" / "quick", quick_demo / "runs" / "demo-quick"
    log = (quick_demo.parent / "demo.log").read_text()
    for step in ("generate the dataset", "validate the dataset", "infer: detector", "infer: GT boxes", "evaluate:",
                 "short run: detector", "short run: refiner"):
        assert f"=== {step}" in log, step
    for method in ("cosylite", "cosyliteicp", "cosyliteoracle", "cosyliteoracleicp"):
        rows = _rows(out / "results" / f"{method}_ycbvsynth-test.csv")
        assert rows and {r["im_id"] for r in rows} <= {"0", "1"}, method
        scores = json.loads((out / "results" / f"{method}_ycbvsynth-test_eval" / "scores.json").read_text())
        assert 0 <= scores["ar"] <= 1
    oracle_icp = json.loads((out / "results" / "cosyliteoracleicp_ycbvsynth-test_eval" / "scores.json").read_text())
    assert oracle_icp["ar"] > 0.2, oracle_icp["ar"]  # the reference models with GT masks and depth: not noise
    summary = (out / "demo_summary.md").read_text()
    assert summary.count("| detector + templates + refiner") == 2 and "| refiner | 2 |" in summary, summary
    for model in ("detector", "coarse", "refiner"):
        assert (runs / "short" / model / "checkpoint.pt").is_file() and (runs / "short" / model / "DONE").is_file()
    assert (out / "demo_ar.png").stat().st_size > 5000 and (out / "demo_training.png").stat().st_size > 5000


@pytest.mark.slow
def test_train_from_the_installed_package_with_a_packaged_profile(site, quick_demo, work):
    run = work / "cwd" / "runs" / "refiner-small"
    dataset = quick_demo / "data" / "quick" / "ycbvsynth"
    r = _cli(site, work / "cwd", "train", "--dataset", str(dataset), "--model", "refiner", "--profile", "demo",
             "--out", str(run), *SMALL_REFINER)
    assert "done: 2 steps" in r.stdout, r.stdout[-3000:]
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    losses = [rec["loss/total"] for rec in records if rec.get("type") == "train"]
    assert len(losses) == 2 and all(0 < x < 1e3 for x in losses), losses
    assert (run / "checkpoint.pt").stat().st_size > 1e5 and (run / "config.yaml").is_file()


@pytest.mark.slow
def test_infer_with_the_packaged_reference_models(site, quick_demo, work):
    out = work / "cwd" / "results-infer"
    dataset = quick_demo / "data" / "quick" / "ycbvsynth"
    _cli(site, work / "cwd", "infer", "--dataset", str(dataset), "--pretrained", "ycbvsynth", "--detections", "oracle",
         "--limit-images", "1", "--templates-cache", str(quick_demo / "runs" / "demo-quick" / "templates"),
         "--no-progress", "--out", str(out))
    rows = _rows(out / "cosylite_ycbvsynth-test.csv")
    assert rows and {r["im_id"] for r in rows} == {"0"}
    for r in rows:
        R, t = [float(v) for v in r["R"].split()], [float(v) for v in r["t"].split()]
        assert len(R) == 9 and len(t) == 3 and 100 < t[2] < 5000, r  # mm, in front of the camera


def test_pyproject_lists_every_package_and_maps_the_reference_models():
    """pyproject.toml names its packages (one of them, the reference models, lives in models/): a new
    package missing from the list would be left out of an install."""
    import tomllib

    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    folders = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "cosy_lite").rglob("__init__.py")}
    assert set(tool["packages"]) == folders | {"cosy_lite.configs", "cosy_lite.reference.weights"}
    assert tool["package-dir"] == {"cosy_lite.configs": "configs", "cosy_lite.reference.weights": "models"}
    assert (ROOT / "models").is_dir() and any((ROOT / "configs").glob("*/*.yaml"))
