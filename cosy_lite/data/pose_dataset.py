"""Training data for the pose networks: one item per annotated object INSTANCE of a BOP split.

A plain reader: it returns the full image, the camera, the GT pose and masks. Crops, renderings and
(usually) the augmentation are done by the training loop on batches, on the device; pass
``augmentation`` to run it here instead (in DataLoader workers, one image at a time).

The "any object" mask used by background replacement is the union of the ``mask_visib`` files of
all GT instances of the image (whatever their object id or visibility): pixels showing an annotated
object. Unannotated things (distractors) count as background, as in CosyPose.
"""

from __future__ import annotations

import copy
import hashlib
from typing import cast

import numpy as np
import torch
from torch.utils.data import Dataset

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.data.augmentation import StrongAugmentation
from cosy_lite.data.image_cache import ImageCache
from cosy_lite.data.instances import check_obj_ids, load_masks, load_rgb, scan_split, split_train_val
from cosy_lite.structures import PoseBatch, PoseSample

__all__ = ["PoseDataset", "split_train_val", "collate_poses"]


class PoseDataset(Dataset):
    """Object instances of ``split`` with ``visib_fract >= min_visib_fract`` and at least ``min_px``
    visible pixels, restricted to ``obj_ids`` (None: all objects of the dataset).

    Args:
        dataset: the BOP dataset.
        split: e.g. ``"train_pbr"``.
        obj_ids: objects to keep (checked against ``models_info.json``).
        min_visib_fract: minimum visible fraction (``scene_gt_info.json``).
        min_px: minimum number of visible pixels (``px_count_visib``).
        scene_ids: scenes to read (None: all scenes of the split).
        augmentation: applied to each item's image (uint8 stays uint8) if given.

    The index is built at construction from the scene JSON files only (no image is read).
    """

    def __init__(self, dataset: BopDataset, split: str = "train_pbr", obj_ids: list[int] | None = None,
                 min_visib_fract: float = 0.1, min_px: int = 50, scene_ids: list[int] | None = None,
                 augmentation: StrongAugmentation | None = None):
        self.dataset = dataset
        self.split = split
        self.obj_ids = check_obj_ids(dataset, obj_ids)
        self.min_visib_fract = min_visib_fract
        self.min_px = min_px
        self.augmentation = augmentation
        self.table = scan_split(dataset, split, scene_ids)
        self.index = np.nonzero(self.table.select(self.obj_ids, min_visib_fract, min_px))[0]  # rows of the table
        self.cache: ImageCache | None = None

    def __len__(self) -> int:
        return len(self.index)

    def image_keys(self) -> list[tuple[int, int]]:
        """(scene_id, im_id) of the images that have at least one item."""
        rows = np.unique(self.table.image_idx[self.index])
        return list(zip(self.table.scene_ids[rows].tolist(), self.table.im_ids[rows].tolist()))

    def select_images(self, keys: set[tuple[int, int]]) -> "PoseDataset":
        """A copy holding only the items of the images ``keys`` (the table is shared)."""
        t = self.table
        wanted = {(int(s), int(i)) for s, i in keys}
        image_rows = np.array([k in wanted for k in zip(t.scene_ids.tolist(), t.im_ids.tolist())], dtype=bool)
        return self._restricted(image_rows)

    def select_scenes(self, scene_ids: set[int]) -> "PoseDataset":
        """A copy holding only the items of the scenes ``scene_ids`` (the table is shared)."""
        return self._restricted(np.isin(self.table.scene_ids, np.asarray(sorted(scene_ids), dtype=np.int64)))

    def _restricted(self, image_rows: np.ndarray) -> "PoseDataset":
        """A copy keeping the items whose image row is True in ``image_rows`` [M], in their order."""
        out = copy.copy(self)
        out.index = self.index[image_rows[self.table.image_idx[self.index]]]
        return out

    def fingerprint(self) -> str:
        """A short sha256 of the items, in order: scene, image, GT index, object and pose of each (what
        a cache of per-item work must match: scenes added, removed or regenerated change it)."""
        t, rows = self.table, self.table.image_idx[self.index]
        h = hashlib.sha256()
        for a in (t.scene_ids[rows], t.im_ids[rows], t.gt_idx[self.index], t.obj_ids[self.index], t.TCO[self.index]):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()[:20]

    def instance_counts(self) -> dict[int, int]:
        """obj_id -> number of items."""
        ids, counts = np.unique(self.table.obj_ids[self.index], return_counts=True)
        return dict(zip(ids.tolist(), counts.tolist()))

    def cache_images(self, progress: bool = True) -> None:
        """Decode this dataset's images and masks once into memory (:class:`ImageCache`); items are
        then read from it (the same values as from the files)."""
        self.cache = ImageCache.load(self.dataset, self.table, self.table.image_idx[self.index], progress)

    def __getitem__(self, i: int) -> PoseSample:
        t = self.table
        n = int(self.index[i])
        row = int(t.image_idx[n])
        scene_id, im_id, gt_idx = int(t.scene_ids[row]), int(t.im_ids[row]), int(t.gt_idx[n])
        if self.cache is not None:
            rgb, mask, any_mask = self.cache.image(row), self.cache.instance_mask(row, gt_idx), self.cache.any_mask(row)
        else:
            rgb = load_rgb(self.dataset, self.split, scene_id, im_id)
            masks = load_masks(self.dataset, self.split, scene_id, im_id, list(range(int(t.n_gt[row]))), rgb.shape[:2])
            mask, any_mask = masks[gt_idx], cast(np.ndarray, masks.any(axis=0))  # [H,W] bool: axis given, never a scalar
        rgb_t = torch.from_numpy(rgb).permute(2, 0, 1).contiguous()
        mask_any = torch.from_numpy(any_mask)
        if self.augmentation is not None:
            rgb_t = self.augmentation(rgb_t[None], mask_any[None])[0]
        return PoseSample(
            rgb=rgb_t,
            K=torch.from_numpy(t.K[row].copy()),
            TCO=torch.from_numpy(t.TCO[n].copy()),
            obj_id=int(t.obj_ids[n]),
            bbox_visib=torch.from_numpy(t.bbox_visib[n].copy()),
            mask=torch.from_numpy(mask.copy()),
            mask_any=mask_any,
            scene_id=scene_id,
            im_id=im_id,
            gt_idx=gt_idx,
            visib_fract=float(t.visib_fract[n]),
        )


def collate_poses(samples: list[PoseSample]) -> PoseBatch:
    """DataLoader ``collate_fn``: stack into a :class:`PoseBatch`."""
    return PoseBatch.collate(samples)
