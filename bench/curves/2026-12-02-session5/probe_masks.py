"""Scratch probe (session 5): how many of the detector's masks are empty at the 0.5 threshold, and
the mask AP of the test split with the 0.5 threshold vs a fallback for empty masks (pixels at least
half of the mask's peak probability). Usage: probe_masks.py DATASET DETECTOR_CKPT"""
import sys

import numpy as np
import torch

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.bop.detections import Detections
from cosy_lite.eval.detection import evaluate_detections
from cosy_lite.model_files.loaders import load_detector

root, ckpt = sys.argv[1], sys.argv[2]
torch.set_num_threads(1)
ds = BopDataset(root)
det = load_detector(ckpt).eval()
records = list(ds.images("test"))
raw, out = {}, {}
n, n_empty, peaks = 0, 0, []
with torch.inference_mode():
    for rec in records:
        img = torch.from_numpy(ds.load_rgb(rec)).permute(2, 0, 1).float() / 255
        o = det.net([img])[0]
        probs = o["masks"][:, 0].numpy()
        key = (rec.scene_id, rec.im_id)
        ids = det.label_map.obj_ids_of(o["labels"])
        m05 = probs > 0.5
        empty = ~m05.any(axis=(1, 2))
        n += len(probs)
        n_empty += int(empty.sum())
        rel = m05.copy()
        for i in np.flatnonzero(empty):
            pk = probs[i].max()
            peaks.append(float(pk))
            if pk > 0.05:
                rel[i] = probs[i] >= 0.5 * pk
        raw[key] = Detections(o["boxes"], ids, o["scores"], torch.from_numpy(m05))
        out[key] = Detections(o["boxes"], ids, o["scores"], torch.from_numpy(rel))
print(f"{n} detections, {n_empty} empty at 0.5 ({n_empty / max(n, 1):.1%}); peak prob of empty masks: "
      f"median {np.median(peaks) if peaks else float('nan'):.3f}, quartiles {np.percentile(peaks, [25, 75]) if peaks else '-'}")
for name, d in (("threshold 0.5", raw), ("0.5, empty -> >= 0.5 x peak", out)):
    s = evaluate_detections(ds, records, d)
    print(f"{name}: box AP50 {s.ap50:.3f} AP {s.ap:.3f} | mask AP50 {s.mask_ap50:.3f} mask AP {s.mask_ap:.3f}")
