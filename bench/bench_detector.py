"""Benchmark of trained detectors (``cosy_lite.train.detector_task``): COCO AP and ms per image.

Usage: python bench/bench_detector.py [--checkpoint runs/ycbvsynth-detector/checkpoint.pt ...]
       [--dataset data/ycbvsynth] [--split test] [--threads 2] [--out-dir runs/ycbvsynth-detector]

For each checkpoint (one per backbone): the detector is loaded with ``load_detector``, run on every
image of the split one image at a time (CPU, ``--threads`` torch threads), and scored with COCO
box AP / AP50 / AP75 and mask AP / AP50 against ``bbox_visib`` / ``mask_visib``
(:mod:`cosy_lite.eval.detection`). ms/image is the forward pass of one full 640x480 image
(torchvision resizes it to the checkpoint's ``min_size``; reading the file excluded), median and
mean over the split after one warm-up image. The detections are written as a BOP22 JSON file
(``cosylite-<backbone>_<dataset>-<split>.json`` in ``--out-dir``). The 2 cores of this machine are
shared: the table gives the load average (1 min) before and after next to the timings.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
from pathlib import Path

import numpy as np

DEFAULT_CKPT = Path("runs/ycbvsynth-detector/checkpoint.pt")


def bench_checkpoint(path: Path, root: Path, split: str, out_dir: Path | None) -> dict:
    import torch

    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.detections import write_detections_json
    from cosy_lite.data.instances import load_rgb
    from cosy_lite.nets.detector import detect
    from cosy_lite.train.detector_task import evaluate_detector
    from cosy_lite.weights.checkpoint import load_checkpoint
    from cosy_lite.weights.loaders import load_detector

    model = load_detector(path)
    step = load_checkpoint(path, kind="detector").step
    dataset = BopDataset(root)
    keys = sorted((r.scene_id, r.im_id) for r in dataset.images(split))
    warm = torch.from_numpy(load_rgb(dataset, split, *keys[0])).permute(2, 0, 1).float() / 255.0
    detect(model, [warm])  # warm-up (allocations, oneDNN kernels)
    load0 = os.getloadavg()[0]
    scores, dets = evaluate_detector(model, dataset, split, keys)
    load1 = os.getloadavg()[0]
    ms = np.array([d.time_s for d in dets.values()]) * 1e3
    cfg = model.config
    name = cfg.name.removeprefix("maskrcnn_")
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        write_detections_json(out_dir / f"cosylite-{name.replace('_', '')}_{dataset.name}-{split}.json", dets)
    return dict(backbone=name, size=f"{cfg.min_size}x{cfg.max_size}", step=step, ap=scores.ap, ap50=scores.ap50,
                ap75=scores.ap75, mask_ap=scores.mask_ap, mask_ap50=scores.mask_ap50, ms_med=float(np.median(ms)),
                ms_mean=float(ms.mean()), images=scores.n_images, gt=scores.n_gt, dets=scores.n_detections,
                load=f"{load0:.1f}/{load1:.1f}")


def _fmt(v) -> str:
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.3f}" if abs(v) < 10 else f"{v:.0f}"
    return str(v)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", type=Path, nargs="+", default=[DEFAULT_CKPT])
    ap.add_argument("--dataset", type=Path, default=Path("data/ycbvsynth"))
    ap.add_argument("--split", default="test")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out-dir", type=Path, default=None, help="where the BOP22 JSON goes (default: the checkpoint's folder)")
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
          f"{args.threads} threads; {args.dataset} {args.split}")
    rows = [bench_checkpoint(p, args.dataset, args.split, args.out_dir or p.parent) for p in args.checkpoint]
    cols = list(rows[0])
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(_fmt(r[c]) for c in cols) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
