"""Training task of the Mask R-CNN detector, on the one training loop (:mod:`cosy_lite.train.loop`).

Data: every image of ``data.split`` (BOP ``train_pbr``) with its instances above the visibility and
area thresholds (:class:`~cosy_lite.data.detection_dataset.DetectionDataset`); ``data.val_images``
images are held out by image (never trained on) for validation. Per batch, on the training device:
the shared strong augmentation (:class:`~cosy_lite.data.augmentation.StrongAugmentation`, the one
the pose networks use) on the full images, background replacement keeping the visible pixels of
every GT instance (also the ones too hidden to be a target), then torchvision's Mask R-CNN losses.
Its random draws come from torch's global RNG, which the loop re-seeds before each step, so a
resumed run repeats the uninterrupted one.

Validation: COCO box AP / AP50 / mask AP (pycocotools, :mod:`cosy_lite.eval.detection`) of the
held-out images. Checkpoints store the detector config and the obj_id label map
(``meta["detector_config"]``, ``meta["label_map"]``);
:func:`cosy_lite.weights.loaders.load_detector` rebuilds the module::

    detector = load_detector("runs/ycbvsynth-detector/checkpoint.pt")  # detector.label_map: obj_ids
    dets = detect(detector, [image])  # image: [3,H,W] float in [0,1]; -> [Detections] (obj_ids, boxes px, masks)
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable, cast

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.bop.detections import Detections, ImageKey
from cosy_lite.data.augmentation import AugmentationConfig, StrongAugmentation
from cosy_lite.data.detection_dataset import DetectionDataset
from cosy_lite.data.instances import hold_out_images, load_masks
from cosy_lite.nets.detector import Detector, DetectorConfig, LabelMap, detect, detector_losses
from cosy_lite.structures import DetectionBatch, DetectionSample
from cosy_lite.train.loop import LoopConfig
from cosy_lite.train.schedule import OptimConfig
from cosy_lite.weights.loaders import DETECTOR_KIND

KIND = DETECTOR_KIND


@dataclass
class DetectorDataConfig:
    split: str = "train_pbr"
    obj_ids: list[int] = field(default_factory=list)  # empty: every object of the dataset
    min_visib_fract: float = 0.1  # instances less visible are not targets (their pixels stay)
    min_area_px: int = 50  # instances with fewer visible pixels are not targets
    val_images: int = 20  # images of the split held out (never trained on) for validation
    val_batch_size: int = 4  # images per forward pass in validation


@dataclass
class CpuSpeedConfig:
    """CPU-only speed-ups (no effect on GPU, where the loop's ``loop.amp`` applies)."""

    bf16: bool = False  # bfloat16 autocast of the forward pass (CPUs with AVX512-BF16 / AMX)
    channels_last: bool = False  # NHWC weights and activations (faster oneDNN convolutions)


@dataclass
class DetectorTrainConfig:
    """Everything that defines a detector training run (YAML in configs/detector/ holds differences)."""

    model: str = "detector"
    dataset: str = "ycbvsynth"
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    data: DetectorDataConfig = field(default_factory=DetectorDataConfig)
    augmentation: AugmentationConfig = field(default_factory=AugmentationConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    cpu: CpuSpeedConfig = field(default_factory=CpuSpeedConfig)


# ----------------------------------------------------------------------------- data


@dataclass
class DetectorTrainBatch:
    """A :class:`DetectionBatch` and, per image, the visible pixels of ALL its GT instances
    (``masks_any``: B x ``[H,W]`` bool), which background replacement keeps."""

    batch: DetectionBatch
    masks_any: list[Tensor]

    def __len__(self) -> int:
        return len(self.batch)

    def to(self, device: torch.device | str) -> "DetectorTrainBatch":
        return DetectorTrainBatch(self.batch.to(device), [m.to(device) for m in self.masks_any])


class MasksAnyDataset(Dataset):
    """Items of a :class:`DetectionDataset` (without augmentation) as ``(sample, mask_any)``.

    ``mask_any [H,W]`` bool is the union of the ``mask_visib`` of every GT instance of the image:
    the sample's own targets plus the instances it dropped (too hidden, too small, other objects).
    """

    def __init__(self, base: DetectionDataset):
        if base.augmentation is not None:
            raise ValueError("MasksAnyDataset: the base dataset must not augment (the task augments batches)")
        self.base = base

    def __len__(self) -> int:
        return len(self.base)

    def image_keys(self) -> list[tuple[int, int]]:
        return self.base.image_keys()

    def __getitem__(self, i: int) -> tuple[DetectionSample, Tensor]:
        sample = self.base[i]
        t = self.base.table
        row = int(self.base.rows[i])
        dropped = np.flatnonzero((t.image_idx == row) & ~self.base.keep)
        mask_any = sample.masks.bool().any(dim=0) if len(sample.masks) else torch.zeros(sample.image.shape[-2:], dtype=torch.bool)
        if len(dropped):
            h, w = sample.image.shape[-2:]
            extra = load_masks(self.base.dataset, self.base.split, sample.scene_id, sample.im_id,
                               t.gt_idx[dropped].tolist(), (h, w))
            mask_any |= torch.from_numpy(extra.any(axis=0))
        return sample, mask_any


def collate_train(items: list[tuple[DetectionSample, Tensor]]) -> DetectorTrainBatch:
    return DetectorTrainBatch(DetectionBatch.collate([s for s, _ in items]), [m for _, m in items])


def augment_images(augment: StrongAugmentation, images: list[Tensor], masks_any: list[Tensor]) -> list[Tensor]:
    """``augment`` applied to B x ``[3,H,W]`` float images (one call per image size, in order)."""
    out: list[Tensor | None] = [None] * len(images)
    by_size: dict[tuple[int, ...], list[int]] = {}
    for i, im in enumerate(images):
        by_size.setdefault(tuple(im.shape), []).append(i)
    for idx in by_size.values():
        aug = augment(torch.stack([images[i] for i in idx]), torch.stack([masks_any[i] for i in idx]))
        for j, i in enumerate(idx):
            out[i] = aug[j]
    return out  # type: ignore[return-value]


# ----------------------------------------------------------------------------- evaluation


def run_detector(model: Detector, dataset: BopDataset, split: str, keys: Iterable[ImageKey], batch_size: int = 1,
                 device: torch.device | str = "cpu") -> dict[ImageKey, Detections]:
    """Detections (on CPU) of the images ``keys`` of ``split``; ``time_s`` = wall time of the
    forward pass per image (the batch time shared equally), image reading excluded."""
    from cosy_lite.data.instances import load_rgb

    keys = list(keys)
    out: dict[ImageKey, Detections] = {}
    for start in range(0, len(keys), batch_size):
        chunk = keys[start:start + batch_size]
        images = [torch.from_numpy(load_rgb(dataset, split, s, i)).permute(2, 0, 1).to(device).float() / 255.0
                  for s, i in chunk]
        t0 = time.perf_counter()
        dets = detect(model, images)
        if torch.device(device).type == "cuda":
            torch.cuda.synchronize()
        dt = (time.perf_counter() - t0) / len(chunk)
        for key, d in zip(chunk, dets):
            d = d.to("cpu")
            d.time_s = dt
            out[key] = d
    return out


def evaluate_detector(model: Detector, dataset: BopDataset, split: str, keys: Iterable[ImageKey] | None = None,
                      batch_size: int = 1, device: torch.device | str = "cpu"):
    """COCO scores (:class:`~cosy_lite.eval.detection.DetectionScores`, modal boxes) of ``model`` on
    the images ``keys`` of ``split`` (None: all), and the detections."""
    from cosy_lite.eval.detection import evaluate_detections

    if keys is None:
        keys = [(r.scene_id, r.im_id) for r in dataset.images(split)]
    keys = sorted(keys)
    dets = run_detector(model, dataset, split, keys, batch_size, device)
    records = [dataset.image(split, s, i) for s, i in keys]
    return evaluate_detections(dataset, records, dets), dets


# ----------------------------------------------------------------------------- the task


class DetectorTask:
    """:class:`~cosy_lite.train.loop.TrainTask` of the Mask R-CNN detector."""

    kind = KIND

    def __init__(self, cfg: DetectorTrainConfig, dataset_root: str | Path):
        if cfg.model != KIND:
            raise ValueError(f"DetectorTask: model must be {KIND!r}, got {cfg.model!r}")
        self.cfg = cfg
        self.dataset = BopDataset(Path(dataset_root), cfg.dataset)
        obj_ids = sorted(set(cfg.data.obj_ids)) if cfg.data.obj_ids else sorted(self.dataset.obj_ids)
        self.label_map = LabelMap(tuple(obj_ids))
        self.augment = StrongAugmentation(cfg.augmentation)
        full = DetectionDataset(self.dataset, cfg.data.split, label_map={o: self.label_map.label(o) for o in obj_ids},
                                min_visib_fract=cfg.data.min_visib_fract, min_area_px=cfg.data.min_area_px)
        train, val = hold_out_images(full, cfg.data.val_images, cfg.loop.seed, str(self.dataset.root / cfg.data.split))
        self._train_set = MasksAnyDataset(train)
        self.val_keys: list[ImageKey] = sorted(val.image_keys())

    def build_model(self, load_pretrained: bool = True) -> torch.nn.Module:
        model = Detector(self.label_map, self.cfg.detector, load_weights=load_pretrained)
        return model.to(memory_format=torch.channels_last) if self.cfg.cpu.channels_last else model

    def train_dataset(self) -> MasksAnyDataset:
        return self._train_set

    def collate(self, items: list[tuple[DetectionSample, Tensor]]) -> DetectorTrainBatch:
        return collate_train(items)

    def checkpoint_meta(self) -> dict[str, Any]:
        """What :func:`~cosy_lite.weights.loaders.load_detector` needs (same keys as
        :meth:`Detector.meta`) + the dataset name."""
        return {"detector_config": asdict(self.cfg.detector), "label_map": self.label_map.to_dict(),
                "dataset": self.cfg.dataset, "split": self.cfg.data.split}

    def compute_losses(self, model: torch.nn.Module, batch: DetectorTrainBatch, step: int,
                       device: torch.device) -> dict[str, Tensor]:
        batch = batch.to(device)
        images = batch.batch.images
        if self.cfg.augmentation.enabled:
            images = augment_images(self.augment, images, batch.masks_any)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.cfg.cpu.bf16 and device.type == "cpu"):
            losses = detector_losses(model, images, batch.batch.targets)
        return {k: (v if k == "total" else v.detach()) for k, v in losses.items()}

    def validate(self, model: torch.nn.Module, device: torch.device) -> dict[str, float]:
        """COCO AP, AP50, AP75, mask AP, mask AP50 on the held-out images (NaN when undefined)."""
        if not self.val_keys:
            return {}
        inner = cast(Detector, getattr(model, "module", model))  # the detector, DDP-wrapped or not
        scores, _ = evaluate_detector(inner, self.dataset, self.cfg.data.split, self.val_keys,
                                      self.cfg.data.val_batch_size, device)
        return {"ap": scores.ap, "ap50": scores.ap50, "ap75": scores.ap75, "mask_ap": scores.mask_ap,
                "mask_ap50": scores.mask_ap50}
