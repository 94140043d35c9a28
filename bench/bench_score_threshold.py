"""How a detection score threshold and a per-object top-k trade recall for precision: what
``cosy-lite predict`` shows a person, one estimate per kept detection.

Usage: python bench/bench_score_threshold.py DATASET_DIR DETECTIONS.json [--thresholds 0 0.3 0.5 ...] [--top-k 0 1 2]
DETECTIONS.json: BOP22 detections of the test split (``cosy-lite infer`` writes the detector's, e.g.
``outputs/results/cosyliteicp_ycbvsynth-test.json`` of ``make demo``); ``oracle``: the GT boxes with
scores drawn at random (a smoke test). A kept detection is right when its box overlaps a not yet
matched GT instance of its object by IoU >= 0.5 (visible boxes, greedy by score, instances under
10 % visible neither count nor are matched); precision = right / kept, recall = right / instances.
A wrong detection is always a wrong estimate, so the precision here bounds the estimates' from
above. Prints one row per (threshold, top-k): kept per image, precision, recall, F1.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

MATCH_IOU = 0.5
MIN_VISIB = 0.1


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[N,M] IoU of xyxy boxes."""
    lo = np.maximum(a[:, None, :2], b[None, :, :2])
    hi = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.clip(hi - lo, 0, None).prod(axis=2)
    area = lambda x: np.clip(x[:, 2:] - x[:, :2], 0, None).prod(axis=1)  # noqa: E731
    union = area(a)[:, None] + area(b)[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def image_rows(ds, detections: dict) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Per test image: detection boxes [N,4], obj_ids [N], scores [N] (by decreasing score), GT boxes [G,4],
    GT obj_ids [G] of the instances at least MIN_VISIB visible."""
    out = []
    for rec in ds.images("test"):
        keep = [k for k, info in enumerate(rec.gt_info or []) if info.visib_fract >= MIN_VISIB]
        xywh = np.asarray([rec.gt_info[k].bbox_visib for k in keep], dtype=np.float64).reshape(-1, 4)
        gt_boxes = np.concatenate([xywh[:, :2], xywh[:, :2] + xywh[:, 2:]], axis=1)
        gt_ids = np.asarray([rec.gt[k].obj_id for k in keep], dtype=np.int64)
        det = detections.get((rec.scene_id, rec.im_id))
        if det is None:
            out.append((np.zeros((0, 4)), np.zeros(0, np.int64), np.zeros(0), np.asarray(gt_boxes), gt_ids))
            continue
        order = np.argsort(-det.scores.numpy(), kind="stable")
        out.append((det.boxes.double().numpy()[order], det.obj_ids.numpy()[order], det.scores.numpy()[order],
                    np.asarray(gt_boxes), gt_ids))
    return out


def score(rows, min_score: float, top_k: int) -> dict[str, float]:
    """Kept per image, precision, recall and F1 with detections of score >= min_score, at most top_k per
    object and image (0: no limit)."""
    kept = right = instances = 0
    for boxes, ids, scores, gt_boxes, gt_ids in rows:
        instances += len(gt_ids)
        take = scores >= min_score
        if top_k > 0:
            seen: dict[int, int] = {}
            for i in np.flatnonzero(take):
                seen[int(ids[i])] = seen.get(int(ids[i]), 0) + 1
                take[i] = seen[int(ids[i])] <= top_k
        idx = np.flatnonzero(take)
        kept += len(idx)
        iou = box_iou(boxes[idx], gt_boxes) if len(idx) and len(gt_boxes) else np.zeros((len(idx), len(gt_boxes)))
        matched = np.zeros(len(gt_boxes), bool)
        for r, i in enumerate(idx):
            cand = np.flatnonzero((gt_ids == ids[i]) & ~matched & (iou[r] >= MATCH_IOU))
            if len(cand):
                matched[cand[np.argmax(iou[r, cand])]] = True
                right += 1
    precision = right / kept if kept else 1.0
    recall = right / instances if instances else 1.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"kept_per_image": kept / max(1, len(rows)), "precision": precision, "recall": recall, "f1": f1}


def _oracle(ds, seed: int = 0) -> dict:
    """The GT boxes as detections, scores drawn at random."""
    import torch

    from cosy_lite.bop.detections import oracle_detections

    rng = np.random.default_rng(seed)
    out = {}
    for rec in ds.images("test"):
        det = oracle_detections(ds, rec, with_masks=False)
        det.scores = torch.from_numpy(rng.random(len(det)).astype(np.float32))
        out[(rec.scene_id, rec.im_id)] = det
    return out


def main() -> None:
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.detections import read_detections_json

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("detections", help="BOP22 detections JSON of the test split, or 'oracle'")
    ap.add_argument("--thresholds", type=float, nargs="+", default=[0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9])
    ap.add_argument("--top-k", type=int, nargs="+", default=[0, 1, 2], help="per object and image (0: no limit)")
    args = ap.parse_args()
    ds = BopDataset(args.dataset)
    dets = _oracle(ds) if args.detections == "oracle" else read_detections_json(args.detections, ds.obj_ids)
    rows = image_rows(ds, dets)
    print(f"{ds.name} test: {len(rows)} images, {sum(len(r[4]) for r in rows)} instances >= {MIN_VISIB:.0%} visible, "
          f"{sum(len(r[1]) for r in rows)} detections ({args.detections})\n")
    print("| min score | top-k per object | kept / image | precision | recall | F1 |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: |")
    best = max(((t, k, score(rows, t, k)) for t in args.thresholds for k in args.top_k), key=lambda x: x[2]["f1"])
    for t in args.thresholds:
        for k in args.top_k:
            s = score(rows, t, k)
            mark = "**" if (t, k) == best[:2] else ""
            print(f"| {t:g} | {k or 'all'} | {s['kept_per_image']:.1f} | {s['precision']:.3f} | {s['recall']:.3f} | "
                  f"{mark}{s['f1']:.3f}{mark} |")
    print(f"\nbest F1: min score {best[0]:g}, top-k {best[1] or 'all'}")


if __name__ == "__main__":
    main()
