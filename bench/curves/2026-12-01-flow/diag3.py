import sys, torch, numpy as np
netpath = sys.argv[1]; extra = sys.argv[2:]
sys.argv = ["x", "--out", "/tmp/x"]
sys.path.insert(0, "/work/exp")
import flowpnp as fp
from torch import nn
from pathlib import Path
from ramdata import RamBatcher, load_split, make_split
from cosy_lite.models.object_table import ObjectTable
from cosy_lite.render.renderer import PyrenderRenderer
from cosy_lite.models.initial_pose import add_pose_noise
from cosy_lite.train.pose_task import pose_errors
torch.set_num_threads(1)
root = Path("/work/main/data/ycbvsynth")
ds, full, rgb, lab = load_split(root, "train_pbr", Path("/work/cache"))
tr, va = make_split(full); val = RamBatcher(full, va, rgb, lab)
objects = ObjectTable.from_dataset(ds, None, 2000, 64)
renderer = PyrenderRenderer.from_dataset(ds, shading="headlight")
g = torch.Generator().manual_seed(12345)
vidx = torch.randperm(len(val), generator=g)[:64].numpy()
b = val.get(vidx); rows = objects.index(b["obj"]); pts = objects.points[rows]
res = (192, 256)
images = b["rgb"].float() / 255
net = fp.FlowNet(4, 2, 64, 0.05).eval()
if "dust" in extra: net.dustbin = nn.Parameter(torch.tensor(0.0))
net.load_state_dict(torch.load(netpath))
for e in extra:
    if e.startswith("k="): net.local_k = int(e[2:])
    if e.startswith("erode="): net.erode = int(e[6:])
syms, sm = objects.symmetries[rows], objects.sym_mask[rows]; dd = objects.diameters[rows]
def summ(T, tag):
    T = T.float()
    s = pose_errors(T, b["TCO"], pts, syms, sm).summary(dd, "")
    dz = (T[:, 2, 3] - b["TCO"][:, 2, 3]).median().item() * 100
    adz = (T[:, 2, 3] - b["TCO"][:, 2, 3]).abs().median().item() * 100
    dxy = (T[:, :2, 3] - b["TCO"][:, :2, 3]).norm(dim=-1).median().item() * 100
    print(f"{tag:28s}", {k[:12]: round(v, 3) for k, v in s.items() if "median" in k or "mssd" in k}, f"dxy {dxy:.2f} |dz| {adz:.2f} signed dz {dz:.2f}", flush=True)
for name, rot, tr_ in [("GT start", 0.0, (0, 0, 0)), ("full noise", 15.0, (0.01, 0.01, 0.05))]:
    T = add_pose_noise(b["TCO"].double(), rot, tr_, generator=torch.Generator().manual_seed(1)).float() if rot > 0 else b["TCO"].clone()
    summ(T, name + " init")
    with torch.no_grad():
        for k in range(4):
            T = torch.cat([fp.refine_step(net, images[s:s+32], b["K"][s:s+32], T[s:s+32], b["obj"][s:s+32].tolist(), pts[s:s+32], renderer, res) for s in range(0, 64, 32)])
            summ(T, f"  it{k+1}")
