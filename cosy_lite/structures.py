"""Typed records passed between modules: dataset items and the batches built from them.

Conventions: images are ``[3,H,W]`` (channels first), ``uint8`` when read from disk; boxes are
``[x0, y0, x1, y1]`` in pixels (``x1 = x0 + w`` of a BOP ``[x, y, w, h]`` box, i.e. exclusive);
poses ``TCO`` are object-to-camera ``[4,4]`` in metres, float32; ``K`` is ``[3,3]`` float32.
Every batch has ``.to(device)`` (returns a new batch) and ``.pin_memory()`` (for DataLoaders).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor


def _map_tensors(obj: Any, fn) -> Any:
    """A copy of the dataclass ``obj`` with ``fn`` applied to every tensor field (lists of tensors too)."""
    changes = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if isinstance(v, Tensor):
            changes[f.name] = fn(v)
        elif isinstance(v, list) and v and isinstance(v[0], (Tensor, dict)):
            changes[f.name] = [
                {k: fn(x) for k, x in e.items()} if isinstance(e, dict) else fn(e) for e in v
            ]
    return dataclasses.replace(obj, **changes)


class _Movable:
    """``.to(device)`` and ``.pin_memory()`` for dataclasses holding tensors."""

    def to(self, device: torch.device | str, non_blocking: bool = False):
        return _map_tensors(self, lambda t: t.to(device, non_blocking=non_blocking))

    def pin_memory(self):
        return _map_tensors(self, lambda t: t.pin_memory())


# ----------------------------------------------------------------------------- pose


@dataclass
class PoseSample(_Movable):
    """One object instance of one BOP image (an item of :class:`cosy_lite.data.pose_dataset.PoseDataset`).

    The image is the full frame (no crop): crops are made on batches by the training loop.
    """

    rgb: Tensor  # [3,H,W] uint8 (augmented or not)
    K: Tensor  # [3,3] float32 camera intrinsics of the full image
    TCO: Tensor  # [4,4] float32 object-to-camera ground truth [m]
    obj_id: int
    bbox_visib: Tensor  # [4] float32 xyxy [px] of the visible part
    mask: Tensor  # [H,W] bool: visible pixels of this instance (mask_visib)
    mask_any: Tensor  # [H,W] bool: visible pixels of any annotated instance of the image
    scene_id: int
    im_id: int
    gt_idx: int  # index of the instance in scene_gt.json
    visib_fract: float


@dataclass
class PoseBatch(_Movable):
    """B stacked :class:`PoseSample` (same image size)."""

    rgb: Tensor  # [B,3,H,W] uint8 or float
    K: Tensor  # [B,3,3] float32
    TCO: Tensor  # [B,4,4] float32 [m]
    obj_ids: Tensor  # [B] int64
    bboxes: Tensor  # [B,4] float32 xyxy [px]
    masks: Tensor  # [B,H,W] bool
    masks_any: Tensor  # [B,H,W] bool
    scene_ids: Tensor  # [B] int64
    im_ids: Tensor  # [B] int64
    gt_idx: Tensor  # [B] int64
    visib_fract: Tensor  # [B] float32

    def __len__(self) -> int:
        return int(self.TCO.shape[0])

    @classmethod
    def collate(cls, samples: list[PoseSample]) -> "PoseBatch":
        """Stack samples; all images must have the same size (ValueError naming the first mismatch)."""
        if not samples:
            raise ValueError("PoseBatch.collate: empty list of samples")
        shape = samples[0].rgb.shape
        for s in samples:
            if s.rgb.shape != shape:
                raise ValueError(
                    f"PoseBatch.collate: image of scene {s.scene_id} im {s.im_id} has shape "
                    f"{tuple(s.rgb.shape)}, expected {tuple(shape)} like the first sample"
                )

        def ints(name: str) -> Tensor:
            return torch.tensor([getattr(s, name) for s in samples], dtype=torch.int64)

        return cls(
            rgb=torch.stack([s.rgb for s in samples]),
            K=torch.stack([s.K for s in samples]),
            TCO=torch.stack([s.TCO for s in samples]),
            obj_ids=ints("obj_id"),
            bboxes=torch.stack([s.bbox_visib for s in samples]),
            masks=torch.stack([s.mask for s in samples]),
            masks_any=torch.stack([s.mask_any for s in samples]),
            scene_ids=ints("scene_id"),
            im_ids=ints("im_id"),
            gt_idx=ints("gt_idx"),
            visib_fract=torch.tensor([s.visib_fract for s in samples], dtype=torch.float32),
        )


# ----------------------------------------------------------------------------- detection


@dataclass
class DetectionSample(_Movable):
    """One image with its annotated instances, for a torchvision detector.

    Instances below the dataset's visibility/area thresholds are already dropped; N may be 0.
    """

    image: Tensor  # [3,H,W] float32 in [0,1]
    boxes: Tensor  # [N,4] float32 xyxy [px] (bbox_visib)
    labels: Tensor  # [N] int64 contiguous labels (1..n_classes; 0 is the background)
    masks: Tensor  # [N,H,W] uint8 in {0,1} (mask_visib)
    obj_ids: Tensor  # [N] int64 BOP object ids
    scene_id: int
    im_id: int

    def target(self) -> dict[str, Tensor]:
        """The torchvision detection target: ``boxes``, ``labels``, ``masks``."""
        return {"boxes": self.boxes, "labels": self.labels, "masks": self.masks}


@dataclass
class DetectionBatch(_Movable):
    """Lists, as the torchvision detection API takes them (images may differ in size)."""

    images: list[Tensor]  # B x [3,H,W] float32 in [0,1]
    targets: list[dict[str, Tensor]]  # B x {"boxes", "labels", "masks"}
    scene_ids: list[int]
    im_ids: list[int]

    def __len__(self) -> int:
        return len(self.images)

    @classmethod
    def collate(cls, samples: list[DetectionSample]) -> "DetectionBatch":
        return cls(
            images=[s.image for s in samples],
            targets=[s.target() for s in samples],
            scene_ids=[s.scene_id for s in samples],
            im_ids=[s.im_id for s in samples],
        )
