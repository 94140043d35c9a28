"""Training data for the detector: one item per IMAGE of a BOP split, in torchvision's format.

Targets: ``boxes`` from ``bbox_visib`` (xyxy, float), ``labels`` from a label map (obj_id ->
contiguous label >= 1; 0 is torchvision's background), ``masks`` from ``mask_visib`` (uint8).
Instances below the visibility/pixel thresholds, with an empty box, or of objects outside the label map, are dropped
from the target (their pixels stay in the image, as in CosyPose). Images left with no instance are
valid items with empty targets (``boxes`` [0,4]).

The augmentation, when given, is the shared :class:`~cosy_lite.data.augmentation.StrongAugmentation`;
its background replacement keeps the union of the ``mask_visib`` of ALL GT instances of the image.
"""

from __future__ import annotations

import copy

import numpy as np
import torch
from torch.utils.data import Dataset

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.data.augmentation import StrongAugmentation
from cosy_lite.data.instances import check_obj_ids, load_masks, load_rgb, scan_split, split_train_val
from cosy_lite.structures import DetectionBatch, DetectionSample

__all__ = ["DetectionDataset", "make_label_map", "collate_detections", "split_train_val"]


def make_label_map(obj_ids: list[int]) -> dict[int, int]:
    """obj_id -> label 1..n in increasing obj_id order (0 is the background)."""
    return {int(o): i + 1 for i, o in enumerate(sorted(set(obj_ids)))}


class DetectionDataset(Dataset):
    """Images of ``split`` with their kept instances.

    Args:
        dataset: the BOP dataset.
        split: e.g. ``"train_pbr"``.
        label_map: obj_id -> contiguous label >= 1 (see :func:`make_label_map`); objects not in it are
            not annotated. None: :func:`make_label_map` of ``obj_ids`` or of all dataset objects.
        obj_ids: objects to annotate (default: the keys of ``label_map``).
        min_visib_fract: instances with a smaller visible fraction are dropped.
        min_area_px: instances with fewer visible pixels (``px_count_visib``) are dropped.
        scene_ids: scenes to read (None: all).
        augmentation: applied to each image if given.
    """

    def __init__(self, dataset: BopDataset, split: str = "train_pbr", label_map: dict[int, int] | None = None,
                 obj_ids: list[int] | None = None, min_visib_fract: float = 0.1, min_area_px: int = 50,
                 scene_ids: list[int] | None = None, augmentation: StrongAugmentation | None = None):
        self.dataset = dataset
        self.split = split
        if label_map is None:
            label_map = make_label_map(obj_ids if obj_ids is not None else dataset.obj_ids)
        labels = sorted(label_map.values())
        if labels and (labels[0] < 1 or len(set(labels)) != len(labels)):
            raise ValueError(f"DetectionDataset: labels must be distinct and >= 1 (0 is the background), got {label_map}")
        self.label_map = {int(k): int(v) for k, v in label_map.items()}
        check_obj_ids(dataset, list(self.label_map))
        self.obj_ids = check_obj_ids(dataset, obj_ids if obj_ids is not None else list(self.label_map))
        missing = sorted(set(self.obj_ids) - set(self.label_map))
        if missing:
            raise ValueError(f"DetectionDataset: obj_ids {missing} have no label in label_map {self.label_map}")
        self.min_visib_fract = min_visib_fract
        self.min_area_px = min_area_px
        self.augmentation = augmentation
        self.table = scan_split(dataset, split, scene_ids)
        b = self.table.bbox_visib
        non_empty = (b[:, 2] > b[:, 0]) & (b[:, 3] > b[:, 1])  # torchvision rejects empty boxes
        self.keep = self.table.select(self.obj_ids, min_visib_fract, min_area_px) & non_empty  # [N] over the table
        self.rows = np.arange(len(self.table.scene_ids))  # images of this dataset (rows of the table)
        # Instances of each image, in scene_gt order: table rows sorted by image.
        order = np.argsort(self.table.image_idx, kind="stable")
        starts = np.searchsorted(self.table.image_idx[order], np.arange(len(self.rows) + 1))
        self._inst = [order[starts[r]:starts[r + 1]] for r in range(len(self.rows))]

    def __len__(self) -> int:
        return len(self.rows)

    def image_keys(self) -> list[tuple[int, int]]:
        t = self.table
        return list(zip(t.scene_ids[self.rows].tolist(), t.im_ids[self.rows].tolist()))

    def select_images(self, keys: set[tuple[int, int]]) -> "DetectionDataset":
        """A copy holding only the images ``keys`` (the table is shared)."""
        out = copy.copy(self)
        out.rows = np.array([r for r, k in zip(self.rows, self.image_keys()) if k in keys], dtype=np.int64)
        return out

    def num_instances(self) -> int:
        """Number of kept instances over the images of this dataset."""
        return int(sum(self.keep[self._inst[r]].sum() for r in self.rows))

    def __getitem__(self, i: int) -> DetectionSample:
        t = self.table
        row = int(self.rows[i])
        scene_id, im_id = int(t.scene_ids[row]), int(t.im_ids[row])
        inst = self._inst[row]
        kept = inst[self.keep[inst]]
        rgb = load_rgb(self.dataset, self.split, scene_id, im_id)
        image = torch.from_numpy(rgb).permute(2, 0, 1).contiguous()
        if self.augmentation is not None and self.augmentation.cfg.enabled and self.augmentation.cfg.p_background > 0:
            all_masks = load_masks(self.dataset, self.split, scene_id, im_id, t.gt_idx[inst].tolist(), rgb.shape[:2])
            masks = all_masks[self.keep[inst]]
            image = self.augmentation(image[None], torch.from_numpy(all_masks.any(axis=0))[None])[0]
        else:
            masks = load_masks(self.dataset, self.split, scene_id, im_id, t.gt_idx[kept].tolist(), rgb.shape[:2])
            if self.augmentation is not None:
                image = self.augmentation(image[None], None)[0]
        obj_ids = t.obj_ids[kept]
        return DetectionSample(
            image=image.float() / 255.0,
            boxes=torch.from_numpy(t.bbox_visib[kept].copy()).reshape(-1, 4),
            labels=torch.tensor([self.label_map[int(o)] for o in obj_ids], dtype=torch.int64),
            masks=torch.from_numpy(masks.astype(np.uint8)),
            obj_ids=torch.from_numpy(obj_ids.copy()),
            scene_id=scene_id,
            im_id=im_id,
        )


def collate_detections(samples: list[DetectionSample]) -> DetectionBatch:
    """DataLoader ``collate_fn``: lists of images and target dicts (torchvision detection API)."""
    return DetectionBatch.collate(samples)
