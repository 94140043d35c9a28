"""A toy training run (tests/toy_task.py) that can kill itself with SIGKILL at a chosen moment.

``python tests/toy_kill_run.py OUT [--resume] [--kill WHEN:STEP]`` (or :func:`run_in_child` in a
multiprocessing child) trains :class:`ToyTask` for :data:`STEPS` steps into the run folder OUT and
reports ``at step K`` before each step, so a parent can also kill it from outside at a moment of
its choosing. WHEN:

* ``step``: inside the loss of step STEP (0-based);
* ``log``: half of the train log record of step STEP written (no newline), then killed;
* ``ckpt-write``: half of the checkpoint of step STEP written into its temporary file;
* ``ckpt-replace``: the checkpoint of step STEP fully written, not yet moved into place;
* ``ckpt-done``: right after the checkpoint of step STEP is in place.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import os
import signal
import sys
import time
from pathlib import Path
from typing import Callable

STEPS = 30
# checkpoint_every is not a multiple of log_every: log intervals span checkpoints (and resumes).
LOOP = dict(steps=STEPS, batch_size=8, num_workers=0, log_every=2, val_every=6, checkpoint_every=5, device="cpu")


def _die() -> None:
    sys.stdout.flush()
    os.kill(os.getpid(), signal.SIGKILL)


def _install_kill(when: str, at: int, out: Path) -> None:
    """Patch the moment ``when`` of step ``at`` to SIGKILL this process."""
    import torch

    import cosy_lite.train.loop as loop_module
    import cosy_lite.train.run_log as log_module

    if when == "log":
        class _Json:  # the run log's json module, except that one record is half written
            loads, JSONDecodeError = json.loads, json.JSONDecodeError

            @staticmethod
            def dumps(record, *args, **kwargs):
                text = json.dumps(record, *args, **kwargs)
                if isinstance(record, dict) and record.get("type") == "train" and record.get("step") == at:
                    with open(out / loop_module.LOG_NAME, "a") as f:
                        f.write(text[: len(text) // 2])
                        f.flush()
                        os.fsync(f.fileno())
                    _die()
                return text

        log_module.json = _Json  # type: ignore[assignment]
        return
    real_save, real_replace = torch.save, os.replace
    saving: dict[str, int] = {}

    def save(obj, f, *args, **kwargs):
        step = obj.get("step") if isinstance(obj, dict) else None
        saving["step"] = step
        if when == "ckpt-write" and step == at:
            buf = io.BytesIO()
            real_save(obj, buf, *args, **kwargs)
            f.write(buf.getvalue()[: len(buf.getvalue()) // 2])
            f.flush()
            os.fsync(f.fileno())
            _die()
        return real_save(obj, f, *args, **kwargs)

    def replace(src, dst, *args, **kwargs):
        is_ckpt = ".tmp" in Path(src).name and Path(dst).name == loop_module.CHECKPOINT_NAME
        if is_ckpt and saving.get("step") == at and when == "ckpt-replace":
            _die()
        real_replace(src, dst, *args, **kwargs)
        if is_ckpt and saving.get("step") == at and when == "ckpt-done":
            _die()

    torch.save = save
    os.replace = replace


def run(out: Path, resume: bool = False, kill: str | None = None, step_sleep: float = 0.0,
        report: Callable[[str], None] = lambda msg: print(msg, flush=True)) -> None:
    """Train into ``out``; ``report("at step K")`` before each step and ``report("finished")`` at the end."""
    import torch
    from toy_task import ToyTask

    from cosy_lite.train.loop import LoopConfig, train
    from cosy_lite.train.schedule import OptimConfig

    torch.set_num_threads(1)  # the same arithmetic in every process
    task = ToyTask()
    compute = task.compute_losses
    kill_step = None
    if kill:
        when, at = kill.split(":")
        if when == "step":
            kill_step = int(at)
        else:
            _install_kill(when, int(at), out)

    def losses(model, batch, step, device):
        report(f"at step {step}")
        if step == kill_step:
            _die()
        time.sleep(step_sleep)
        return compute(model, batch, step, device)

    task.compute_losses = losses  # type: ignore[method-assign]
    loop = LoopConfig(**LOOP)
    optim = OptimConfig(lr=3e-2, warmup_steps=5)
    cfg = {"loop": dataclasses.asdict(loop), "optim": dataclasses.asdict(optim)}
    train(task, loop, optim, out, config=cfg, resume=resume, progress=False)
    report("finished")


def run_in_child(conn, out: str, resume: bool, kill: str | None, step_sleep: float) -> None:
    """:func:`run` in a multiprocessing child, reporting through the pipe ``conn``."""
    run(Path(out), resume, kill, step_sleep, report=conn.send)


def main(argv: list[str]) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--kill", default=None, metavar="WHEN:STEP")
    ap.add_argument("--step-sleep", type=float, default=0.0, help="seconds per step (time for outside kills)")
    args = ap.parse_args(argv)
    run(args.out, args.resume, args.kill, args.step_sleep)


if __name__ == "__main__":
    main(sys.argv[1:])
