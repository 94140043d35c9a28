# max |difference| of R and t (m) per row of two BOP19 CSVs (rows matched by scene, image, object, score)
import csv, sys, numpy as np
def load(f):
    return {(r["scene_id"], r["im_id"], r["obj_id"], r["score"]): (np.array(r["R"].split(), float), np.array(r["t"].split(), float)) for r in csv.DictReader(open(f))}
a, b = load(sys.argv[1]), load(sys.argv[2])
d = sorted(max(np.abs(a[k][0]-b[k][0]).max(), np.abs(a[k][1]-b[k][1]).max()/1000) for k in a if k in b)
d = np.array(d)
print("n", len(d), "exact", (d == 0).sum(), "<1e-6", (d < 1e-6).sum(), "<1e-3", (d < 1e-3).sum(), ">1e-2", (d > 1e-2).sum())
