"""A split's images and visible masks decoded once into memory (the pose networks' loader).

Every pose-training item needs its full image and the "any object" mask of that image: decoded
from PNG per item that is one RGB file and ~9 mask files, ~40 ms, which on the 2-core CPU
starved the network (about 300 PNG decodes per second for 30 crops/s). Decoded once, the
default 1000-image split holds 1.2 GB (RGB uint8 + a uint8 label map) and an item costs a copy.

The label map holds, per pixel, ``1 + gt_idx`` of the visible instance there, 0 where no annotated
object is visible. Visible masks are disjoint up to the 15 mm visibility tolerance; where two
overlap, the later instance's index is kept (the union, which the augmentation uses, is exact).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.data.instances import InstanceTable, load_masks, load_rgb
from cosy_lite.errors import BopFormatError

MAX_INSTANCES = 255  # label maps are uint8


@dataclass
class ImageCache:
    """rgb [M,H,W,3] uint8 and labels [M,H,W] uint8 for the M images (rows) of an InstanceTable."""

    rgb: np.ndarray
    labels: np.ndarray

    @classmethod
    def load(cls, dataset: BopDataset, table: InstanceTable, rows: np.ndarray | None = None,
             progress: bool = True) -> "ImageCache":
        """Decode the images ``rows`` of ``table`` (None: all); other rows stay empty (zeros)."""
        from tqdm import tqdm

        rows = np.arange(len(table.im_ids)) if rows is None else np.unique(rows)
        if len(rows) == 0:
            raise ValueError("ImageCache: no image to load")
        first = load_rgb(dataset, table.split, int(table.scene_ids[rows[0]]), int(table.im_ids[rows[0]]))
        H, W = first.shape[:2]
        rgb = np.zeros((len(table.im_ids), H, W, 3), dtype=np.uint8)
        labels = np.zeros((len(table.im_ids), H, W), dtype=np.uint8)
        for r in tqdm(rows, desc=f"decode {table.split} images", unit="img", disable=None if progress else True, leave=False):
            scene_id, im_id, n = int(table.scene_ids[r]), int(table.im_ids[r]), int(table.n_gt[r])
            if n > MAX_INSTANCES:
                raise BopFormatError(dataset.scene_dir(table.split, scene_id) / "scene_gt.json", str(im_id),
                                     f"{n} instances; the image cache holds at most {MAX_INSTANCES}")
            image = load_rgb(dataset, table.split, scene_id, im_id)
            if image.shape[:2] != (H, W):
                raise BopFormatError(dataset.rgb_path(table.split, scene_id, im_id), "shape",
                                     f"{image.shape[1]}x{image.shape[0]}, the split's first image is {W}x{H}")
            rgb[r] = image
            for k, m in enumerate(load_masks(dataset, table.split, scene_id, im_id, list(range(n)), (H, W))):
                labels[r][m] = k + 1
        return cls(rgb, labels)

    def image(self, row: int) -> np.ndarray:
        return self.rgb[row]

    def instance_mask(self, row: int, gt_idx: int) -> np.ndarray:
        return self.labels[row] == gt_idx + 1

    def any_mask(self, row: int) -> np.ndarray:
        return self.labels[row] > 0
