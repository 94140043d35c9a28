"""The training loop: loss goes down, resume is exact, checkpoints are checked, DDP (gloo) works."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from toy_task import ToyTask

from cosy_lite.train.loop import LoopConfig, train
from cosy_lite.train.sampler import StepBatchSampler
from cosy_lite.train.schedule import OptimConfig, budget_factor, lr_factor
from cosy_lite.weights.checkpoint import Checkpoint, CheckpointError, load_checkpoint, save_checkpoint

ROOT = Path(__file__).resolve().parents[1]


def _run(out: Path, steps: int, resume: bool = False, batch: int = 8, noise: float = 0.01, schedule: str = "step",
         floor: float = 0.05, task: ToyTask | None = None, **loop_kw):
    loop = LoopConfig(**{"steps": steps, "batch_size": batch, "num_workers": 0, "log_every": 5, "val_every": 10,
                         "checkpoint_every": 5, "device": "cpu", **loop_kw})
    optim = OptimConfig(lr=3e-2, warmup_steps=5, schedule=schedule, cosine_floor=floor)
    cfg = {"loop": dataclasses.asdict(loop), "optim": dataclasses.asdict(optim)}
    return train(task or ToyTask(noise=noise), loop, optim, out, config=cfg, resume=resume, progress=False)


class _InterruptedToyTask(ToyTask):
    """The toy task killed when it reaches step ``at`` (after the checkpoint of that step)."""

    def __init__(self, at: int):
        super().__init__(noise=0.01)
        self.at = at

    def compute_losses(self, model, batch, step, device):
        if step == self.at:
            raise KeyboardInterrupt
        return super().compute_losses(model, batch, step, device)


def test_lr_schedule_warmup_then_step_decay():
    cfg = OptimConfig(lr=1.0, warmup_steps=4, decay_steps=[10, 20], decay_factor=0.1)
    assert [lr_factor(s, cfg) for s in (0, 1, 3, 9)] == [0.25, 0.5, 1.0, 1.0]
    assert lr_factor(10, cfg) == pytest.approx(0.1) and lr_factor(25, cfg) == pytest.approx(0.01)


def test_cosine_schedule_over_the_budget():
    cfg = OptimConfig(schedule="cosine", cosine_floor=0.1)
    assert [budget_factor(f, cfg) for f in (-1.0, 0.0, 0.5, 1.0, 2.0)] == pytest.approx([1.0, 1.0, 0.55, 0.1, 0.1])
    assert budget_factor(0.5, OptimConfig()) == 1.0  # "step": no budget factor


def test_cosine_replaces_the_step_decay():
    # a profile's decay_steps left under an optim.schedule=cosine override held the detector at x0.1
    cfg = OptimConfig(lr=1.0, warmup_steps=4, decay_steps=[10, 20], decay_factor=0.1, schedule="cosine")
    assert [lr_factor(s, cfg) for s in (0, 3, 10, 25)] == [0.25, 1.0, 1.0, 1.0]


def test_cosine_run_ends_at_the_floor_and_resumes_exactly(tmp_path):
    _run(tmp_path / "a", steps=20, schedule="cosine", floor=0.1)
    lrs = [json.loads(x)["lr"] for x in (tmp_path / "a" / "log.jsonl").read_text().splitlines()
           if json.loads(x)["type"] == "train"]
    # warm-up to step 5, then the cosine of (step + 1) / 20: the rate logged after step 20 is the floor
    assert lrs[0] == pytest.approx(3e-2 * budget_factor(5 / 20, OptimConfig(schedule="cosine", cosine_floor=0.1)))
    assert lrs[-1] == pytest.approx(3e-3) and lrs == sorted(lrs, reverse=True)
    with pytest.raises(KeyboardInterrupt):
        _run(tmp_path / "b", steps=20, schedule="cosine", floor=0.1, task=_InterruptedToyTask(at=10))
    _run(tmp_path / "b", steps=20, schedule="cosine", floor=0.1, resume=True)
    a = load_checkpoint(tmp_path / "a" / "checkpoint.pt").model
    b = load_checkpoint(tmp_path / "b" / "checkpoint.pt").model
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)


def test_sampler_is_a_function_of_step_and_shards_ranks():
    full = StepBatchSampler(10, 4, seed=3, start_step=0, total_steps=6)
    later = StepBatchSampler(10, 4, seed=3, start_step=4, total_steps=6)
    assert list(full)[4:] == list(later)
    epoch0 = [i for b in list(full)[:2] for i in b] + full.indices_for_step(2)[:2]
    assert sorted(epoch0) == list(range(10))  # each epoch is a permutation
    r0 = StepBatchSampler(10, 2, seed=3, start_step=0, total_steps=3, rank=0, world_size=2)
    r1 = StepBatchSampler(10, 2, seed=3, start_step=0, total_steps=3, rank=1, world_size=2)
    assert [a + b for a, b in zip(r0, r1)] == list(full)[:3]


def test_training_lowers_loss_and_writes_run_folder(tmp_path):
    s = _run(tmp_path, steps=40)
    records = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    train_losses = [r["loss/total"] for r in records if r["type"] == "train"]
    assert len(train_losses) == 8 and train_losses[-1] < 0.5 * train_losses[0]
    assert s.steps_done == 40 and s.last_val["mae"] < 1.0
    assert (tmp_path / "loss.png").stat().st_size > 5000
    ck = load_checkpoint(tmp_path / "checkpoint.pt", kind="toy")
    # the task's meta, and the loop's count of the items behind the weights (40 steps x 8)
    assert ck.step == 40 and ck.meta == {"n_out": 3, "items_seen": 320, "world_size": 1}
    assert ck.config["loop"]["steps"] == 40


def test_validation_at_start_logs_the_untrained_model_once(tmp_path):
    _run(tmp_path, steps=20, val_at_start=True)
    vals = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines() if '"val"' in line]
    assert [v["step"] for v in vals] == [0, 10, 20]
    assert vals[-1]["val/mae"] < 0.5 * vals[0]["val/mae"]  # the held-out error moved
    _run(tmp_path, steps=30, resume=True, val_at_start=True)  # a resumed run does not validate step 0 again
    vals = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines() if '"val"' in line]
    assert [v["step"] for v in vals] == [0, 10, 20, 30]


def test_resume_reproduces_the_uninterrupted_run(tmp_path):
    _run(tmp_path / "a", steps=20)
    _run(tmp_path / "b", steps=10)  # "interrupted" after its checkpoint at step 10
    with pytest.raises(CheckpointError, match="--resume"):
        _run(tmp_path / "b", steps=20)
    _run(tmp_path / "b", steps=20, resume=True)
    a = load_checkpoint(tmp_path / "a" / "checkpoint.pt").model
    b = load_checkpoint(tmp_path / "b" / "checkpoint.pt").model
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)
    la = (tmp_path / "a" / "log.jsonl").read_text().splitlines()
    lb = (tmp_path / "b" / "log.jsonl").read_text().splitlines()
    strip = lambda lines: [{k: v for k, v in json.loads(x).items() if k not in ("items_per_s", "elapsed_s")} for x in lines]
    assert strip(la) == strip(lb)


def test_resume_refuses_a_different_config(tmp_path):
    _run(tmp_path, steps=5)
    with pytest.raises(CheckpointError, match="loop.batch_size"):
        _run(tmp_path, steps=10, resume=True, batch=4)


def test_resume_a_checkpoint_older_than_a_setting(tmp_path):
    _run(tmp_path, steps=5)
    ck = load_checkpoint(tmp_path / "checkpoint.pt")
    for key in ("schedule", "cosine_floor"):  # written before these settings existed
        del ck.config["optim"][key]
    save_checkpoint(tmp_path / "checkpoint.pt", ck)
    assert _run(tmp_path, steps=10, resume=True).steps_done == 10  # the new value that behaves as before
    save_checkpoint(tmp_path / "checkpoint.pt", ck)
    with pytest.raises(CheckpointError, match="optim.schedule: 'step' -> 'cosine'"):
        _run(tmp_path, steps=10, resume=True, schedule="cosine")


def test_time_budget_stops_with_a_checkpoint(tmp_path):
    s = _run(tmp_path, steps=10_000, max_minutes=1e-4)
    assert s.steps_done < 10_000 and load_checkpoint(tmp_path / "checkpoint.pt").step == s.steps_done


def test_time_budget_counts_the_whole_run(tmp_path, capsys):
    first = _run(tmp_path, steps=10_000, max_minutes=1e-4)
    again = _run(tmp_path, steps=10_000, max_minutes=1e-4, resume=True)  # an interrupted run resumed
    assert again.steps_done == first.steps_done and "nothing to do" in capsys.readouterr().out
    more = _run(tmp_path, steps=10_000, max_minutes=1e-2, resume=True)  # a larger budget trains on
    assert more.steps_done > first.steps_done


class _SlowValidationToyTask(ToyTask):
    """The toy task with a validation of ``seconds``."""

    def __init__(self, seconds: float):
        super().__init__(noise=0.01)
        self.seconds = seconds

    def validate(self, model, device):
        import time

        time.sleep(self.seconds)
        return super().validate(model, device)


def test_the_final_validation_fits_inside_the_time_budget(tmp_path):
    """An 8 s budget with a 1.5 s validation: training stops early enough for the final validation and
    checkpoint (they ran after the budget was spent: 9.5 s and more)."""
    s = _run(tmp_path, steps=10_000_000, max_minutes=8 / 60, val_at_start=True, val_every=10_000_000,
             checkpoint_every=100, task=_SlowValidationToyTask(1.5))
    assert s.steps_done < 10_000_000 and "mae" in s.last_val  # stopped by the budget, validated at the end
    assert 6.0 < s.seconds <= 8.0 + 1.0, s.seconds  # (a loaded machine saves a checkpoint in up to ~0.5 s)


def test_bad_checkpoints_name_the_file_and_problem(tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "nope.pt")
    good = tmp_path / "good.pt"
    save_checkpoint(good, Checkpoint(kind="coarse", model={"w": torch.ones(2)}, config={}, step=3))
    with pytest.raises(CheckpointError, match="'kind' is 'coarse'"):
        load_checkpoint(good, kind="refiner")
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[:200])
    with pytest.raises(CheckpointError, match=r"truncated\.pt: not a readable checkpoint"):
        load_checkpoint(truncated)
    torch.save({"model": {}}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="missing field"):
        load_checkpoint(tmp_path / "other.pt")
    assert not list(tmp_path.glob(".*tmp*"))  # atomic writes leave no temporary files


def test_ddp_two_gloo_processes_match_one_process_with_the_global_batch(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT / "tests")}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",  # a free port
           str(ROOT / "tests" / "toy_task.py"), str(tmp_path / "ddp"), "10", "4"]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr[-3000:]
    ck = load_checkpoint(tmp_path / "ddp" / "checkpoint.pt", kind="toy")
    assert ck.step == 10 and len((tmp_path / "ddp" / "log.jsonl").read_text().splitlines()) == 2
    # Averaged gradients of 2 x 4 items = the gradient of one process with the same 8 items.
    _run(tmp_path / "single", steps=10, batch=8, noise=0.0)
    single = load_checkpoint(tmp_path / "single" / "checkpoint.pt").model
    for k in single:
        torch.testing.assert_close(ck.model[k], single[k], rtol=1e-5, atol=1e-6)


def test_the_progress_bar_follows_the_time_budget():
    """With loop.max_minutes the bar counts the budget's seconds (its ETA is the budget's); it counted
    loop.steps ("42/100000 [00:33<58:32:07]" for a run of minutes)."""
    from cosy_lite.train.loop import _progress_bar
    from cosy_lite.train.run_state import RunState

    run = RunState(step=40, elapsed_before=30.0)
    timed = _progress_bar("refiner", LoopConfig(steps=100_000, max_minutes=2.0), run, show=False)
    assert (timed.total, timed.n) == (120.0, 30.0)  # seconds of the budget, those trained before
    by_steps = _progress_bar("refiner", LoopConfig(steps=500, max_minutes=0.0), run, show=False)
    assert (by_steps.total, by_steps.n) == (500, 40)
