"""Interrupted and misconfigured training: kill -9 at ten moments of a real run (before and after
the first checkpoint, during a checkpoint write, outside kills at random steps), each resumed;
the final weights and log equal an uninterrupted run's, no step is logged twice, no temporary
file is left. Broken logs, stale temporary files and settings that would train nothing."""

from __future__ import annotations

import dataclasses
import json
import random
import signal
from pathlib import Path

import pytest
import torch
from toy_task import ToyTask

from cosy_lite.errors import ConfigError
from cosy_lite.train.loop import LoopConfig, train
from cosy_lite.train.run_log import read_log
from cosy_lite.train.schedule import OptimConfig
from cosy_lite.weights.checkpoint import CheckpointError, load_checkpoint

VOLATILE = ("items_per_s", "elapsed_s")  # wall-clock values: differ between runs
# Each run is a real process (SIGKILL ends it as kill -9 does), forked by a forkserver that has
# imported torch once: ~0.3 s per run instead of ~3 s for a fresh interpreter.
PRELOAD = ["torch", "torch._dynamo", "torch.optim", "matplotlib.pyplot", "cosy_lite.train.loop", "toy_task",
           "toy_kill_run"]


class _Run:
    """A toy training run in a child process; ``steps`` are the steps it reported starting."""

    def __init__(self, ctx, out: Path, resume: bool = False, kill: str | None = None, step_sleep: float = 0.0):
        import toy_kill_run

        self.conn, child = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(target=toy_kill_run.run_in_child, args=(child, str(out), resume, kill, step_sleep))
        self.proc.start()
        child.close()
        self.steps: list[int] = []
        self.finished = False

    def messages(self):
        while True:
            try:
                msg = self.conn.recv()
            except EOFError:  # the child is gone
                return
            if msg == "finished":
                self.finished = True
            else:
                self.steps.append(int(msg.split()[2]))
            yield msg

    def wait(self) -> int:
        for _ in self.messages():
            pass
        self.proc.join(timeout=120)
        return self.proc.exitcode


@pytest.fixture(scope="module")
def ctx():
    import multiprocessing

    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(PRELOAD)
    return context


def _ckpt_step(out: Path) -> int:
    path = out / "checkpoint.pt"
    return load_checkpoint(path).step if path.is_file() else 0


def _stable(records: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in VOLATILE} for r in records]


def test_kill_9_at_ten_moments_then_resume_equals_the_uninterrupted_run(tmp_path, ctx):
    reference = _Run(ctx, tmp_path / "reference")
    assert reference.wait() == 0 and reference.finished
    out = tmp_path / "killed"
    # (kill spec, checkpoint step expected after the kill)
    planned = [("step:3", 0),  # before the first checkpoint (log has step 2)
               ("log:8", 5),  # a half-written log line
               ("ckpt-write:10", 5),  # half a checkpoint in its temporary file
               ("ckpt-replace:10", 5),  # the whole temporary file, not moved into place
               ("ckpt-done:15", 15)]  # just after a checkpoint
    for k, (spec, after) in enumerate(planned):
        start = _ckpt_step(out)
        run = _Run(ctx, out, resume=k > 0, kill=spec)
        assert run.wait() == -signal.SIGKILL, spec
        assert run.steps[0] == start, f"{spec}: resumed at {run.steps[0]}, the checkpoint was at {start}"
        assert _ckpt_step(out) == after, spec
        if spec in ("ckpt-write:10", "ckpt-replace:10"):
            assert list(out.glob(".checkpoint.pt.tmp*")), "the killed write left its temporary file"
    rng = random.Random(14)
    for _ in range(5):  # from outside, at a random step of what is left
        start = _ckpt_step(out)
        target = rng.randrange(start, 29)
        run = _Run(ctx, out, resume=True, step_sleep=0.01)
        for _msg in run.messages():
            if run.steps and run.steps[-1] >= target:
                run.proc.kill()  # SIGKILL
                break
        assert run.wait() == -signal.SIGKILL and not run.finished
        assert run.steps[0] == start, f"resumed at {run.steps[0]}, the checkpoint was at {start}"
    start = _ckpt_step(out)
    final = _Run(ctx, out, resume=True)
    assert final.wait() == 0 and final.finished and final.steps[0] == start

    a = load_checkpoint(tmp_path / "reference" / "checkpoint.pt", kind="toy")
    b = load_checkpoint(out / "checkpoint.pt", kind="toy")
    assert a.step == b.step == 30
    for key in a.model:
        torch.testing.assert_close(b.model[key], a.model[key], rtol=0, atol=0)
    log_a, log_b = read_log(tmp_path / "reference" / "log.jsonl"), read_log(out / "log.jsonl")
    keys = [(r["type"], r["step"]) for r in log_b]
    assert len(keys) == len(set(keys)), "a step logged twice"
    assert _stable(log_b) == _stable(log_a)  # the same losses, lrs and validations, in the same order
    elapsed = [r["elapsed_s"] for r in log_b if r["type"] == "train"]
    assert elapsed == sorted(elapsed), "elapsed time restarted at a resume"
    assert (out / "log.jsonl").read_text().endswith("}\n")
    assert not [p.name for p in out.iterdir() if ".tmp" in p.name], "temporary files left"


# ----------------------------------------------------------------------------- in-process cases


def _run(out: Path, resume: bool = False, task: ToyTask | None = None, **loop_kw):
    kw = dict(steps=10, batch_size=8, num_workers=0, log_every=5, val_every=0, checkpoint_every=5, device="cpu")
    loop = LoopConfig(**{**kw, **loop_kw})
    optim = OptimConfig(lr=3e-2, warmup_steps=5)
    cfg = {"loop": dataclasses.asdict(loop), "optim": dataclasses.asdict(optim)}
    return train(task or ToyTask(), loop, optim, out, config=cfg, resume=resume, progress=False)


@pytest.mark.parametrize("key, value", [
    ("steps", 0), ("steps", -5), ("batch_size", 0), ("log_every", 0), ("checkpoint_every", 0),
    ("val_every", -1), ("num_workers", -1), ("max_minutes", -1.0), ("max_minutes", float("nan")), ("device", "gpu"),
], ids=lambda v: str(v))
def test_a_loop_setting_that_cannot_train_is_an_error(tmp_path, key, value):
    with pytest.raises(ConfigError, match=rf"\[loop\.{key}\].*expected"):
        _run(tmp_path, **{key: value})
    assert not (tmp_path / "checkpoint.pt").exists()


def test_resume_with_fewer_steps_than_the_checkpoint_is_an_error(tmp_path):
    _run(tmp_path, steps=10)
    with pytest.raises(ConfigError, match=r"checkpoint\.pt \[loop\.steps\]: 5: the checkpoint is at step 10"):
        _run(tmp_path, resume=True, steps=5)
    assert _run(tmp_path, resume=True, steps=10).steps_done == 10  # a finished run resumes to nothing


def test_rerun_after_a_kill_before_the_first_checkpoint_does_not_duplicate_steps(tmp_path):
    (tmp_path / "log.jsonl").write_text(json.dumps({"type": "train", "step": 5, "lr": 0.1}) + "\n")  # killed run
    _run(tmp_path, steps=10, checkpoint_every=100)
    assert [r["step"] for r in read_log(tmp_path / "log.jsonl")] == [5, 10]


def test_half_written_last_log_line_is_dropped_on_resume(tmp_path):
    _run(tmp_path, steps=5)
    with open(tmp_path / "log.jsonl", "a") as f:
        f.write('{"type": "train", "step": 10, "lr": 0.0')  # cut by a kill
    _run(tmp_path, resume=True, steps=10)
    assert [r["step"] for r in read_log(tmp_path / "log.jsonl")] == [5, 10]


def test_broken_log_line_in_the_middle_names_the_file_and_line(tmp_path):
    _run(tmp_path, steps=5)
    log = tmp_path / "log.jsonl"
    log.write_text("not json\n" + log.read_text())
    with pytest.raises(CheckpointError, match=r"log\.jsonl: line 1: not a JSON record"):
        _run(tmp_path, resume=True, steps=10)
    log.write_text('{"type": "train", "step": "five"}\n')
    with pytest.raises(CheckpointError, match=r"log\.jsonl: line 1: record without an integer 'step'"):
        _run(tmp_path, resume=True, steps=10)


def test_stale_temporary_checkpoints_are_removed_on_start(tmp_path, capsys):
    stale = [tmp_path / ".checkpoint.pt.tmp999999", tmp_path / ".checkpoint.pt.tmp1"]
    for p in stale:
        p.write_bytes(b"x" * 1000)
    _run(tmp_path, steps=5)
    assert not any(p.exists() for p in stale) and "removed 2 temporary checkpoint file(s)" in capsys.readouterr().out


def test_empty_training_set_is_an_error(tmp_path):
    task = ToyTask(n=256)
    task.train_dataset = lambda: torch.utils.data.TensorDataset(torch.zeros(0, 8), torch.zeros(0, 3))
    with pytest.raises(ValueError, match="training set is empty"):
        _run(tmp_path, task=task)


def test_non_finite_loss_is_an_expected_error_naming_the_run(tmp_path):
    from cosy_lite.train.loop import DivergedError

    task = ToyTask()
    task.compute_losses = lambda model, batch, step, device: {"total": model(batch[0]).sum() * float("nan")}
    with pytest.raises(DivergedError, match=r"step 0: non-finite loss \{.total.: nan\}; expected finite losses"):
        _run(tmp_path, task=task)


def test_resume_from_a_checkpoint_of_another_model_names_the_file(tmp_path):
    from cosy_lite.weights.checkpoint import Checkpoint, save_checkpoint

    _run(tmp_path, steps=5)
    ck = load_checkpoint(tmp_path / "checkpoint.pt")
    save_checkpoint(tmp_path / "checkpoint.pt", Checkpoint(ck.kind, {"w": torch.ones(3)}, ck.config, ck.step,
                                                           ck.train_state))
    with pytest.raises(CheckpointError, match=r"checkpoint\.pt: does not fit this model/optimiser \(RuntimeError"):
        _run(tmp_path, resume=True, steps=10)
    save_checkpoint(tmp_path / "checkpoint.pt", Checkpoint(ck.kind, ck.model, ck.config, ck.step, {}))
    with pytest.raises(CheckpointError, match=r"field 'train_state' lacks \['optimizer'\]"):
        _run(tmp_path, resume=True, steps=10)
