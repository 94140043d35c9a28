"""Scratch: the train_pbr split in RAM (rgb uint8 + visible-instance label maps), cached as .npy."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.data.instances import load_masks, load_rgb
from cosy_lite.data.pose_dataset import PoseDataset
from cosy_lite.data.instances import split_train_val


def load_split(root: Path, split: str, cache_dir: Path):
    ds = BopDataset(root, root.name)
    full = PoseDataset(ds, split, min_visib_fract=0.1)
    t = full.table
    cache_dir.mkdir(parents=True, exist_ok=True)
    f_rgb, f_lab = cache_dir / f"{split}_rgb.npy", cache_dir / f"{split}_lab.npy"
    M = len(t.im_ids)
    if not f_lab.exists():
        rgb = np.lib.format.open_memmap(str(f_rgb) + ".tmp", mode="w+", dtype=np.uint8, shape=(M, 480, 640, 3))
        lab = np.lib.format.open_memmap(str(f_lab) + ".tmp", mode="w+", dtype=np.uint8, shape=(M, 480, 640))
        from tqdm import tqdm
        for r in tqdm(range(M), desc=f"cache {split}"):
            s, i = int(t.scene_ids[r]), int(t.im_ids[r])
            rgb[r] = load_rgb(ds, split, s, i)
            m = load_masks(ds, split, s, i, list(range(int(t.n_gt[r]))), (480, 640))
            for k in range(len(m)):
                lab[r][m[k]] = k + 1
        rgb.flush(); lab.flush(); del rgb, lab
        os.replace(str(f_rgb) + ".tmp", f_rgb); os.replace(str(f_lab) + ".tmp", f_lab)
    rgb = np.load(f_rgb, mmap_mode="r")
    lab = np.load(f_lab, mmap_mode="r")
    rgb = np.ascontiguousarray(rgb); lab = np.ascontiguousarray(lab)
    return ds, full, rgb, lab


class RamBatcher:
    """Batches of instances (index rows of PoseDataset.index) as tensors."""

    def __init__(self, full: PoseDataset, rows: np.ndarray, rgb: np.ndarray, lab: np.ndarray):
        self.full, self.rows, self.rgb, self.lab = full, rows, rgb, lab
        t = full.table
        self.img = t.image_idx[rows]
        self.K = torch.from_numpy(t.K[self.img].copy())
        self.TCO = torch.from_numpy(t.TCO[rows].copy())
        self.obj = torch.from_numpy(t.obj_ids[rows].copy())
        self.box = torch.from_numpy(t.bbox_visib[rows].copy())
        self.gt = t.gt_idx[rows]

    def __len__(self):
        return len(self.rows)

    def get(self, idx):
        idx = np.asarray(idx)
        im = self.img[idx]
        rgb = torch.from_numpy(self.rgb[im]).permute(0, 3, 1, 2)
        lab = torch.from_numpy(self.lab[im])
        return dict(rgb=rgb, lab=lab, gt=torch.from_numpy(self.gt[idx]), K=self.K[idx], TCO=self.TCO[idx],
                    obj=self.obj[idx], box=self.box[idx])


def make_split(full, n_val_images=20, seed=0):
    tr, va = split_train_val(full, n_val_images=n_val_images, seed=seed)
    return tr.index, va.index
