"""Benchmark of the synthetic BOP generator: images/s on this machine, 640x480, all masks + GT info.

Usage: python bench/bench_synth.py [--images N] [--workers W ...] [--objects MIN MAX]
Prints a table; copy it with the machine, date and command into bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    from cosy_lite.config import load_config
    from cosy_lite.synth.generator import SynthConfig, generate

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=50)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--objects", type=int, nargs=2, default=[8, 12], help="annotated objects per layout (min max)")
    ap.add_argument("--views", type=int, default=25, help="views per layout")
    args = ap.parse_args(argv)

    rows = []
    for workers in args.workers:
        root = Path(tempfile.mkdtemp(prefix="bench_synth_"))
        try:
            cfg = load_config(SynthConfig, None, [
                f"train.n_images={args.images}", f"train.views_per_layout={args.views}",
                f"objects_per_layout=[{args.objects[0]},{args.objects[1]}]", f"workers={workers}",
            ])
            t0 = time.perf_counter()
            from cosy_lite.synth.objects import write_bop_models
            write_bop_models(cfg.obj_ids, root)
            t_models = time.perf_counter() - t0
            stats = generate(cfg, root, splits=("train_pbr",), progress=False)
            n_inst = sum(1 for _ in (root / "train_pbr/000000/mask_visib").iterdir())
            rows.append((workers, stats["images"], n_inst / max(stats["images"], 1), stats["seconds"],
                         stats["images"] / stats["seconds"], stats["seconds"] / stats["images"], t_models))
        finally:
            shutil.rmtree(root, ignore_errors=True)

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
          f"{args.images} images 640x480, {args.objects[0]}-{args.objects[1]} objects + 2-4 distractors per layout, "
          f"{args.views} views per layout")
    print("| workers | images | annotated objects/image | seconds | images/s | s/image | models (s) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]:.1f} | {r[3]:.1f} | {r[4]:.2f} | {r[5]:.3f} | {r[6]:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
