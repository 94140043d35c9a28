"""Scratch harness (session 5): how should the RGB pipeline pick among its K template candidates?
Per oracle detection (GT visible masks, visib_fract >= 0.1) of the first N test images: the K best
templates, one refiner iteration each (flow confidence, as the Predictor), the silhouette IoU of each
refined candidate with the mask (icp.depth_agreement with no depth = IoU), and its MSSD to GT.
Prints MSSD recall at 0.1 d (after that one iteration) of each picking rule, and of the best candidate.
usage: pick_rules.py DATASET REFINER_CKPT TEMPLATES_CACHE N_IMAGES [K]"""
import sys

import numpy as np
import torch

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.bop.detections import oracle_detections
from cosy_lite.eval.pose_errors import mssd
from cosy_lite.geometry.symmetries import symmetry_transforms
from cosy_lite.inference.icp import depth_agreement
from cosy_lite.inference.predictor import Predictor
from cosy_lite.models.render_and_compare import refine_and_score

root, ref, cache, n_images = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
k = int(sys.argv[5]) if len(sys.argv) > 5 else 5
torch.set_num_threads(1)
ds = BopDataset(root)
p = Predictor.from_checkpoints(refiner=ref, dataset=ds, start="templates", n_candidates=k, templates_cache=cache)
info = ds.models_info
syms = {o: symmetry_transforms(info[o]) for o in info}
verts = {}
rows = []  # per detection: conf [k], iou [k], ok [k]
targets = {(t.scene_id, t.im_id) for t in ds.test_targets()}
records = [r for r in ds.images("test") if (r.scene_id, r.im_id) in targets][:n_images]
for n, rec in enumerate(records):
    det = oracle_detections(ds, rec, True, 0.1)
    keep = [j for j, g in enumerate(rec.gt_info) if g.px_count_visib > 0 and g.visib_fract >= 0.1]
    if not keep:
        continue
    K = np.asarray(rec.camera.K, dtype=np.float64)
    cands = p._template_candidates(det, K)  # [N,k,4,4]
    N = len(det)
    flat = torch.from_numpy(cands.reshape(N * k, 4, 4)).float()
    ids = det.obj_ids.repeat_interleave(k).tolist()
    image = torch.from_numpy(ds.load_rgb(rec)).permute(2, 0, 1)[None].float() / 255
    pts = p.objects.points[p.objects.index(ids)]
    with torch.inference_mode():
        refined, conf = refine_and_score(p._nets["refiner"], image.expand(N * k, -1, -1, -1),
                                         torch.from_numpy(K).float().expand(N * k, 3, 3).contiguous(), flat, ids, pts,
                                         p.renderer, p.refiner.crop_resolution, 32)
    refined = refined.double().numpy()
    masks = np.repeat(det.masks.numpy(), k, axis=0)
    iou = depth_agreement(refined, K, np.zeros(masks.shape[1:], np.float32), masks, p.renderer, ids)
    for i, j in enumerate(keep):
        g = rec.gt[j]
        o = int(g.obj_id)
        T_gt = np.asarray(g.TCO, dtype=np.float64)
        if o not in verts:
            verts[o] = np.asarray(p.renderer.mesh(o).vertices, dtype=np.float64)[::7]
        ok = [mssd(refined[i * k + c], T_gt, verts[o], syms[o]) < 0.1 * info[o].diameter for c in range(k)]
        rows.append((conf[i * k:(i + 1) * k].numpy(), iou[i * k:(i + 1) * k], np.array(ok)))
    print(f"image {n + 1}/{len(records)}: {len(rows)} detections", file=sys.stderr, flush=True)
conf, iou, ok = (np.stack(a) for a in zip(*rows))


def recall(pick):
    return float(ok[np.arange(len(ok)), pick].mean())


rules = {
    "first template (best soft IoU of the silhouettes)": np.zeros(len(ok), int),
    "flow confidence (the Predictor today)": conf.argmax(1),
    "silhouette IoU after the iteration": iou.argmax(1),
    "confidence x IoU": (conf * iou).argmax(1),
    "confidence x IoU^2": (conf * iou ** 2).argmax(1),
    "rank sum (confidence, IoU)": (conf.argsort(1).argsort(1) + iou.argsort(1).argsort(1) + 1e-3 * conf).argmax(1),
}
print(f"{len(ok)} detections of {len(records)} images, K={k}; MSSD recall at 0.1 d after one refiner iteration:")
for name, pick in rules.items():
    print(f"  {recall(pick):.3f}  {name}")
print(f"  {ok.any(1).mean():.3f}  best of the K (an oracle pick)")
np.savez_compressed(sys.argv[6] if len(sys.argv) > 6 else "pick_rules.npz", conf=conf, iou=iou, ok=ok)
