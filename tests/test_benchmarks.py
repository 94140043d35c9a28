"""Every benchmark under bench/ runs, at toy size, and prints its table: the scripts that reproduce
the numbers of README and bench/RESULTS.md cannot rot (an API change breaks them here, not on the
day someone needs the number)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
REFERENCE = REPO / "models" / "ycbvsynth"

# script -> (arguments at toy size; {data}: the tiny dataset, {tmp}: a scratch folder; a line the output must hold)
TOY_RUNS = {
    "bench_synth.py": (["--images", "2", "--workers", "1", "--objects", "2", "3", "--views", "2"], "| 1 | 2 |"),
    "bench_eval.py": (["{data}", "--estimates", "10", "--repeat", "1", "--variants", "bop19"], "| 10 | bop19 |"),
    "bench_eval_toolkit.py": (["{data}", "--noisy", "10", "--workers", "1"], "| cosy-lite eval --workers 1 |"),
    "bench_icp.py": (["--objects", "1", "--repeats", "1"], "| 1 |"),
    "bench_score_threshold.py": (["{data}", "oracle", "--thresholds", "0", "0.5", "--top-k", "0", "1"], "| 0.5 | 1 |"),
    "bench_render.py": (["--meshes", "{data}/models", "--objects", "1", "2", "--batches", "2", "--resolutions", "60x80",
                         "--calls", "1"], "| 60x80 | 2 | rgb+depth |"),
    "bench_inference.py": (["--dataset", "{data}", "--objects", "1", "--repeats", "1", "--warmup", "0", "--threads", "1",
                            "--profiles", "demo", "--precisions", "fp32"], "| demo (resnet18"),
    "bench_onnx.py": (["--dataset", "{data}", "--threads", "1", "--repeat", "1", "--warmup", "0", "--profiles", "demo",
                       "--batches", "1", "--objects", "1", "--no-int8", "--no-detector"], "| onnx fp32 | 1 |"),
    "bench_pose.py": (["--dataset", "{data}", "--refiner", str(REFERENCE / "refiner.safetensors"), "--max-instances", "4",
                       "--threads", "1", "--iterations", "1"], "refiner x1"),
    "bench_pose_training.py": (["{data}", "--steps", "1", "--threads", "1", "loop.batch_size=2", "data.val_images=1",
                                "data.val_instances=2"], "crops/s"),
    "bench_reference_pipeline.py": (["--dataset", "{data}", "--images", "1", "--repeats", "1", "--threads", "1",
                                     "--templates-cache", "{tmp}/templates", "--variant", "one", "n_candidates=1",
                                     "--variant", "two", "n_candidates=2", "candidate_choice=start", "vivo_candidates=2",
                                     "--targets"],
                                    "| torch | + ICP | two |"),
    "bench_detector.py": (["--checkpoint", str(REFERENCE / "detector-00001-of-00004.safetensors"), "--dataset", "{data}",
                           "--threads", "1", "--out-dir", "{tmp}"], "| lite0_fpn |"),
}


def test_every_benchmark_has_a_toy_run():
    assert sorted(p.name for p in (REPO / "bench").glob("*.py")) == sorted(TOY_RUNS)
    assert not [p for p in (REPO / "bench").rglob("*") if p.suffix in (".py", ".sh") and p.parent != REPO / "bench"]


@pytest.mark.slow
@pytest.mark.parametrize("script", sorted(TOY_RUNS))
def test_benchmark_runs_at_toy_size(script, tiny_synth_root, tmp_path):
    args, expected = TOY_RUNS[script]
    argv = [a.format(data=tiny_synth_root, tmp=tmp_path) for a in args]
    env = {**os.environ, "PYOPENGL_PLATFORM": "egl", "OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE"}
    r = subprocess.run([sys.executable, str(REPO / "bench" / script), *argv], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
    assert expected in r.stdout, r.stdout[-3000:]
