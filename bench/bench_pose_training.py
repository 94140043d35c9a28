"""Training throughput of the pose networks: crops/s and where a step's time goes.

    python bench/bench_pose_training.py data/ycbvsynth [--model refiner] [--profile demo] [--steps 30]
        [--threads 1] [key=value ...]

Runs ``--steps`` real training steps of the profile (the task's own ``compute_losses``, Adam, the
loop's gradient clipping) after 3 warm-up steps and prints per step: loading (dataset items +
collate, from the in-memory image cache or, with ``data.cache_images=false``, from the PNG files),
crop + render, augmentation, network forward + loss, backward + optimiser step; and crops/s.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--model", default="refiner", choices=["coarse", "refiner"])
    ap.add_argument("--profile", default="demo")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_intermixed_args()

    import numpy as np
    import torch

    from cosy_lite.config import load_config
    from cosy_lite.train.command import default_config_path
    from cosy_lite.train.pose_task import PoseTask, PoseTrainConfig
    from cosy_lite.train.schedule import build_optimizer

    torch.set_num_threads(args.threads)
    torch.set_flush_denormal(True)
    cfg = load_config(PoseTrainConfig(), default_config_path(args.model, args.profile),
                      [*args.overrides, f"model={args.model}", f"dataset={args.dataset.name}"])
    t = time.perf_counter()
    task = PoseTask(cfg, args.dataset)
    setup_s = time.perf_counter() - t
    model = task.build_model().train()
    optimizer = build_optimizer(model.parameters(), cfg.optim)
    dataset = task.train_dataset()
    rng = np.random.default_rng(0)
    B = cfg.loop.batch_size
    times = {"loading": 0.0, "backward+step": 0.0}
    n_steps = args.steps + 3
    t_all = 0.0
    for step in range(n_steps):
        if step == 3:
            task.stage_seconds = {k: 0.0 for k in task.stage_seconds}
            times = {k: 0.0 for k in times}
            t_all = time.perf_counter()
        t0 = time.perf_counter()
        batch = task.collate([dataset[int(i)] for i in rng.integers(0, len(dataset), B)])
        t1 = time.perf_counter()
        losses = task.compute_losses(model, batch, step, torch.device("cpu"))
        t2 = time.perf_counter()
        optimizer.zero_grad(set_to_none=True)
        losses["total"].backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.optim.clip_grad_norm)
        optimizer.step()
        times["loading"] += t1 - t0
        times["backward+step"] += time.perf_counter() - t2
    wall = time.perf_counter() - t_all
    stages = {"loading": times["loading"], **task.stage_seconds, "backward+step": times["backward+step"]}
    print(f"# {args.model} profile {args.profile} {' '.join(args.overrides)}: {cfg.net.arch} {cfg.net.backbone} "
          f"{cfg.net.crop_resolution[0]}x{cfg.net.crop_resolution[1]}, batch {B}, {args.threads} thread(s), "
          f"cache_images={cfg.data.cache_images}")
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}; "
          f"task set-up {setup_s:.1f} s")
    print("| stage | ms / step | share |")
    print("| --- | ---: | ---: |")
    for k, v in stages.items():
        print(f"| {k} | {1000 * v / args.steps:.0f} | {100 * v / wall:.0f} % |")
    print(f"| **all** | {1000 * wall / args.steps:.0f} | crops/s **{B * args.steps / wall:.1f}** |")


if __name__ == "__main__":
    main()
