"""Benchmark of the BOP19 evaluator: end-to-end time (load, render, score) per number of estimates.

Usage: python bench/bench_eval.py DATASET_DIR [--estimates 34 1000]
Builds, for the test split of DATASET_DIR (e.g. data/ycbv-synth from `make demo`), a results CSV
from the GT poses perturbed by a fixed noise (1 estimate per target instance, in image order,
truncated to N), evaluates it and prints a table. Copy the table into bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def noisy_estimates(ds, n: int, seed: int = 0):
    from cosy_lite.bop.results import PoseEstimate
    from cosy_lite.geometry.transforms import rotation_about_axis

    rng = np.random.default_rng(seed)
    wanted = {(t.scene_id, t.im_id, t.obj_id) for t in ds.test_targets()}
    out = []
    for rec in ds.images("test"):
        for g in rec.gt:
            if (rec.scene_id, rec.im_id, g.obj_id) not in wanted:
                continue
            T = g.TCO.copy()
            T[:3, :3] = rotation_about_axis(rng.normal(size=3), np.deg2rad(rng.uniform(0, 10))) @ T[:3, :3]
            T[:3, 3] += rng.normal(scale=0.005, size=3)
            out.append(PoseEstimate(rec.scene_id, rec.im_id, g.obj_id, float(rng.random()), T, 0.1))
            if len(out) == n:
                return out
    return out


def main(argv: list[str] | None = None) -> int:
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.results import results_filename, write_results_csv
    from cosy_lite.eval.evaluator import evaluate

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--estimates", type=int, nargs="+", default=[34, 1000])
    args = ap.parse_args(argv)
    ds = BopDataset(args.dataset)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.estimates:
            ests = noisy_estimates(ds, n)
            images = {(e.scene_id, e.im_id) for e in ests}
            # Evaluate only the images that hold these estimates: a targets file restricted to them.
            from cosy_lite.bop import io

            sub = Path(tmp) / f"ds{n}"
            sub.mkdir()
            for p in args.dataset.iterdir():
                if p.name != "test_targets_bop19.json":
                    (sub / p.name).symlink_to(p.resolve())
            io.save_json(sub / "test_targets_bop19.json", io.targets_to_json(
                [t for t in ds.test_targets() if (t.scene_id, t.im_id) in images]))
            csv = Path(tmp) / results_filename("bench", ds.name, "test")
            write_results_csv(csv, ests)
            t0 = time.perf_counter()
            res = evaluate(sub, csv, name=ds.name, progress=False)
            dt = time.perf_counter() - t0
            rows.append((len(ests), len(images), dt, 1000 * dt / len(ests), res.scores.ar_vsd, res.scores.ar_mssd, res.scores.ar_mspd))
    print(f"dataset {args.dataset} (test split); GT + noise (<=10 deg, 5 mm sigma), 1 estimate per target")
    print("| estimates | images | seconds | ms/estimate | AR_VSD | AR_MSSD | AR_MSPD |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]:.2f} | {r[3]:.1f} | {r[4]:.3f} | {r[5]:.3f} | {r[6]:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
