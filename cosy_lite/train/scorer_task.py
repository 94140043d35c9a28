"""Training task of the coarse scorer (:mod:`cosy_lite.nets.appearance_scorer`).

Data: the GT instances of ``data.split`` (visible masks standing in for detections), each described
once by :mod:`cosy_lite.train.start_observations` (crop, silhouette IoU and rotation error of every
template) and cached scene by scene; ``data.val_images`` images held out (never trained on) for
validation. The templates' frozen descriptors come from
:class:`~cosy_lite.nets.appearance_templates.AppearanceTemplates` (the same cache as inference).
Per batch: the crops augmented (:func:`augment_crops`: scale and shift of the square, colour gain,
brightness, gamma, noise, blur, a black occluder) -> the scorer -> scores of all templates of each
instance's object -> :func:`~cosy_lite.nets.appearance_scorer.listwise_loss`.
Validation: the share of held-out instances whose best-scored template is within 30 deg of GT, the
flips (> 150 deg) of the textured objects, the median error.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.data import Dataset

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.geometry.symmetries import FLIPPED_DEG, WITHIN_DEG
from cosy_lite.nets.appearance_scorer import AppearanceScorer, flip_loss, listwise_loss
from cosy_lite.train.loop import LoopConfig
from cosy_lite.train.schedule import OptimConfig
from cosy_lite.train.start_observations import StartObservations, observations_by_scene


@dataclass
class ScorerDataConfig:
    split: str = "train_pbr"
    obj_ids: list[int] = field(default_factory=list)  # empty: every object of the dataset
    min_visib_fract: float = 0.3
    val_images: int = 40  # images of the split held out (never trained on) for validation
    n_templates: int = 2048  # template rotations per object trained against (inference: 2,048)
    positive_deg: float = 15.0  # templates this close to GT are the positives of the listwise loss
    flip_weight: float = 0.0  # weight of flip_loss (the best hypothesis > FLIPPED_DEG off against the closest)
    template_shading: str = "headlight"  # as the refiner renders (the templates of inference)
    cache_dir: str = ""  # observations and template descriptors; "": $COSY_LITE_CACHE or ~/.cache/cosy_lite
    observe_workers: int = 0  # processes describing the instances; 0: the CPU cores / the training processes


@dataclass
class CropAugmentationConfig:
    """Photometric and framing changes of the detection crops (all on ``[B,3,S,S]`` in [0, 1])."""

    scale: list[float] = field(default_factory=lambda: [0.9, 1.1])  # of the square around the box
    shift: float = 0.08  # of the square's side, each axis
    channel_gain: list[float] = field(default_factory=lambda: [0.85, 1.15])
    brightness: list[float] = field(default_factory=lambda: [0.6, 1.4])
    gamma: list[float] = field(default_factory=lambda: [0.7, 1.4])
    noise_std: float = 0.04  # max; each crop draws U(0, noise_std)
    blur_probability: float = 0.3
    occluder_probability: float = 0.3  # a black rectangle of 10-32 px (of 64) over the crop


@dataclass
class ScorerTrainConfig:
    """Everything that defines a coarse-scorer training run."""

    model: str = "scorer"
    dataset: str = "ycbvsynth"
    trunk: str = "efficientnet_lite0"
    data: ScorerDataConfig = field(default_factory=ScorerDataConfig)
    augmentation: CropAugmentationConfig = field(default_factory=CropAugmentationConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)


def augment_crops(x: Tensor, cfg: CropAugmentationConfig) -> Tensor:
    """``[B,3,S,S]`` crops in [0, 1] (black outside the object) changed as ``cfg`` says."""
    B, _, S, _ = x.shape
    u = lambda lo_hi, *shape: torch.empty(*shape).uniform_(*lo_hi)  # noqa: E731
    theta = torch.zeros(B, 2, 3)
    s = u(cfg.scale, B)
    theta[:, 0, 0], theta[:, 1, 1] = s, s
    theta[:, :, 2] = u((-2 * cfg.shift, 2 * cfg.shift), B, 2)  # affine_grid's [-1, 1] spans the side twice
    x = F.grid_sample(x, F.affine_grid(theta, list(x.shape), align_corners=False), align_corners=False)
    inside = (x.amax(dim=1, keepdim=True) > 0.02).float()
    x = x * u(cfg.channel_gain, B, 3, 1, 1) * u(cfg.brightness, B, 1, 1, 1)
    x = x.clamp(0, 1) ** u(cfg.gamma, B, 1, 1, 1)
    x = x + torch.randn_like(x) * u((0.0, cfg.noise_std), B, 1, 1, 1)
    blur = torch.rand(B) < cfg.blur_probability
    if blur.any():
        k = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0])
        k = (k[:, None] * k[None]) / 256
        x[blur] = F.conv2d(F.pad(x[blur], (2, 2, 2, 2), mode="replicate"), k.expand(3, 1, 5, 5).contiguous(), groups=3)
    for i in torch.nonzero(torch.rand(B) < cfg.occluder_probability)[:, 0].tolist():
        h, w = torch.randint(S // 6, S // 2, (2,)).tolist()
        y0, x0 = torch.randint(0, S - h, (1,)).item(), torch.randint(0, S - w, (1,)).item()
        inside[i, :, y0:y0 + h, x0:x0 + w] = 0
    return (x * inside).clamp(0, 1)


class ObservationDataset(Dataset):
    """Items of :class:`StartObservations`: (obj_id, crop uint8, iou, errors_deg)."""

    def __init__(self, obs: StartObservations):
        self.obs = obs

    def __len__(self) -> int:
        return len(self.obs)

    def __getitem__(self, i: int) -> tuple[Tensor, ...]:
        o = self.obs
        return o.obj_ids[i], o.crops[i], o.iou[i], o.errors_deg[i]


class ScorerTask:
    """:class:`~cosy_lite.train.loop.TrainTask` of the coarse scorer."""

    kind = "scorer"

    def __init__(self, cfg: ScorerTrainConfig, dataset_root: str | Path, progress: bool = True):
        from cosy_lite.data.instances import hold_out_images
        from cosy_lite.data.pose_dataset import PoseDataset
        from cosy_lite.nets.appearance_templates import object_templates, textured_obj_ids
        from cosy_lite.nets.object_table import ObjectTable
        from cosy_lite.render.renderer import GlRenderer

        self.cfg = cfg
        self.dataset = BopDataset(Path(dataset_root), cfg.dataset)
        from cosy_lite.bop.folders import default_cache_dir

        cache = Path(cfg.data.cache_dir) if cfg.data.cache_dir else default_cache_dir()
        objects = ObjectTable.from_dataset(self.dataset, cfg.data.obj_ids or None)
        renderer = GlRenderer.from_dataset(self.dataset, shading=cfg.data.template_shading)
        self.obj_ids = list(objects.obj_ids)
        self.templates = object_templates(renderer, self.obj_ids, objects.diameters.detach().cpu().double().tolist(),
                                          self.dataset.models_dir, cache, n_rotations=cfg.data.n_templates)
        self.textured = set(textured_obj_ids(renderer, self.obj_ids))
        self.symmetries = symmetries = {o: objects.symmetries[i][objects.sym_mask[i]][:, :3, :3].double().numpy()
                      for i, o in enumerate(self.obj_ids)}
        full = PoseDataset(self.dataset, cfg.data.split, obj_ids=self.obj_ids, min_visib_fract=cfg.data.min_visib_fract)
        self.train_instances, self.val_instances = hold_out_images(full, cfg.data.val_images, cfg.loop.seed,
                                                                   str(self.dataset.root / cfg.data.split))
        t = self.templates
        key = (self.dataset.root.resolve(), cfg.data.split, self.obj_ids, cfg.data.min_visib_fract, t.n_rotations,
               t.seed, cfg.data.template_shading, sorted(t.model_keys.items()))
        self.train_obs, self.val_obs = observations_by_scene(
            full, [self.train_instances, self.val_instances], self.templates, symmetries, cache, key, progress=progress,
            workers=self._observe_workers())
        self.template_descriptors = {o: t.appearance.descriptors(o) for o in self.obj_ids}
        self._descriptors_device = torch.device("cpu")
        renderer.close()
        self._initialised_from: str | None = None

    def _observe_workers(self) -> int:
        if self.cfg.data.observe_workers > 0:
            return self.cfg.data.observe_workers
        return max(1, (os.cpu_count() or 1) // int(os.environ.get("WORLD_SIZE", "1")))

    # ------------------------------------------------------------------ the TrainTask protocol
    def build_model(self, load_pretrained: bool = True) -> torch.nn.Module:
        self._initialised_from = f"ImageNet {self.cfg.trunk}" if load_pretrained else None
        return AppearanceScorer(self.cfg.trunk, load_pretrained=load_pretrained)

    def train_dataset(self) -> Dataset:
        return ObservationDataset(self.train_obs)

    def collate(self, items: list[tuple[Tensor, ...]]) -> tuple[Tensor, ...]:
        return tuple(torch.stack(col) for col in zip(*items))

    def checkpoint_meta(self) -> dict[str, Any]:
        t = self.templates
        return {"obj_ids": self.obj_ids, "trunk": self.cfg.trunk, "dataset": self.cfg.dataset, "model": "scorer",
                "templates": {"shading": self.cfg.data.template_shading, "n_rotations": t.n_rotations, "seed": t.seed},
                "initialised_from": self._initialised_from}

    def _scores(self, model: torch.nn.Module, crops: Tensor, obj_ids: Tensor, iou: Tensor, device: torch.device) -> Tensor:
        net = cast(AppearanceScorer, model.module if hasattr(model, "module") else model)  # the scorer, DDP-wrapped or not
        if self._descriptors_device != device:  # moved once (a GPU would otherwise copy ~35 MB per object and step)
            self.template_descriptors = {o: d.to(device) for o, d in self.template_descriptors.items()}
            self._descriptors_device = device
        descriptors = model(crops.to(device))
        return net.scores(descriptors, obj_ids.to(device), self.template_descriptors, iou.to(device).float())

    def compute_losses(self, model: torch.nn.Module, batch: tuple[Tensor, ...], step: int,
                       device: torch.device) -> dict[str, Tensor]:
        obj_ids, crops, iou, errors = batch
        x = augment_crops(crops.float() / 255.0, self.cfg.augmentation)
        scores = self._scores(model, x, obj_ids, iou, device)
        net = cast(AppearanceScorer, model.module if hasattr(model, "module") else model)  # the scorer, DDP-wrapped or not
        errors = errors.to(device).float()
        scale = net.log_logit_scale.exp()
        listwise = listwise_loss(scores, errors, scale, self.cfg.data.positive_deg)
        out = {"total": listwise, "iou_weight": net.iou_weight.detach().clone()}
        if self.cfg.data.flip_weight > 0:
            flips = flip_loss(scores, errors, scale, FLIPPED_DEG)
            out.update(total=listwise + self.cfg.data.flip_weight * flips, listwise=listwise.detach(), flip=flips.detach())
        return out

    @torch.no_grad()
    def validate(self, model: torch.nn.Module, device: torch.device) -> dict[str, float]:
        o = self.val_obs  # (the loop puts the model in eval mode around validation)
        chosen = []
        for s in range(0, len(o), 64):
            scores = self._scores(model, o.crops[s:s + 64].float() / 255.0, o.obj_ids[s:s + 64], o.iou[s:s + 64], device)
            chosen.append(o.errors_deg[s:s + 64].float().gather(1, scores.argmax(dim=1, keepdim=True).cpu())[:, 0])
        if not chosen:
            return {}
        err = torch.cat(chosen)
        textured = torch.tensor([int(i) in self.textured for i in o.obj_ids], dtype=torch.bool)
        out = {"within_30deg": float((err < WITHIN_DEG).float().mean()), "median_deg": float(err.median())}
        if textured.any():
            out["flipped_textured"] = float((err[textured] > FLIPPED_DEG).float().mean())
        return out
