"""Mask R-CNN detector (torchvision) with object ids as classes.

Backbones come from a table (:data:`DETECTORS`): ``maskrcnn_resnet50_fpn`` (the CosyPose
reference, for GPUs), ``maskrcnn_resnet18_fpn`` and ``maskrcnn_mobilenet_v3_large_fpn`` (light,
for CPUs). All are built with ``weights=None`` (no pretrained weights ship in a registry package)
and with *trainable* normalisation layers: torchvision's detection backbones default to
FrozenBatchNorm, which without pretrained statistics lets activations blow up (zero detections).

Classes are contiguous labels ``1..n`` (0 is background); :class:`LabelMap` maps them to BOP
``obj_id`` and is stored in checkpoints (:meth:`Detector.meta`).

Training: ``losses = detector_losses(model, batch.images, batch.targets)`` (a
:class:`cosy_lite.structures.DetectionBatch`); ``losses["total"]`` is the sum to back-propagate.
Inference: ``detect(model, images) -> list[Detections]``. Images are lists of
``[3, H, W]`` float tensors in ``[0, 1]`` (sizes may differ); torchvision resizes them so the
short side is ``min_size`` (capped by ``max_size``) and normalises them inside the model. The
module exported to ONNX is :attr:`Detector.net` (outputs contiguous labels, not obj_ids).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any, Callable, cast

import torch
from torch import nn
from torchvision import models as tvm
from torchvision.models.detection import MaskRCNN
from torchvision.models.detection.anchor_utils import AnchorGenerator
from torchvision.models.detection.backbone_utils import BackboneWithFPN
from torchvision.models.detection.faster_rcnn import FastRCNNPredictor, TwoMLPHead
from torchvision.models.detection.mask_rcnn import MaskRCNNHeads, MaskRCNNPredictor
from torchvision.ops.feature_pyramid_network import FeaturePyramidNetwork, LastLevelMaxPool

from cosy_lite.bop.detections import Detections
from cosy_lite.nets.backbones import norm_layer
from cosy_lite.nets.detection_masks import MASK_THRESHOLD, binary_masks

if TYPE_CHECKING:
    from timm.models.efficientnet import EfficientNetFeatures

BOX_POOL = 7  # torchvision's box RoIAlign output size


# ----------------------------------------------------------------------------- labels


@dataclass(frozen=True)
class LabelMap:
    """BOP ``obj_id`` <-> contiguous class label (``label = index in obj_ids + 1``; 0 = background).

    Args:
        obj_ids: the dataset's object ids, strictly increasing positive integers.
    """

    obj_ids: tuple[int, ...]

    def __post_init__(self) -> None:
        ids = tuple(int(i) for i in self.obj_ids)
        if not ids or any(i <= 0 for i in ids) or any(a >= b for a, b in zip(ids, ids[1:])):
            raise ValueError(f"LabelMap obj_ids must be strictly increasing positive ints, got {list(self.obj_ids)}")
        object.__setattr__(self, "obj_ids", ids)

    @property
    def n_classes(self) -> int:
        """Classes including background."""
        return len(self.obj_ids) + 1

    def label(self, obj_id: int) -> int:
        try:
            return self.obj_ids.index(int(obj_id)) + 1
        except ValueError:
            raise ValueError(f"obj_id {obj_id} not in the label map {list(self.obj_ids)}") from None

    def obj_id(self, label: int) -> int:
        if not 1 <= int(label) <= len(self.obj_ids):
            raise ValueError(f"label {label} outside 1..{len(self.obj_ids)}")
        return self.obj_ids[int(label) - 1]

    def labels(self, obj_ids: torch.Tensor) -> torch.Tensor:
        """``obj_ids [N]`` int -> labels ``[N]`` int64 (ValueError on an unknown id)."""
        table = torch.zeros(max(self.obj_ids) + 1, dtype=torch.int64, device=obj_ids.device)
        table[list(self.obj_ids)] = torch.arange(1, len(self.obj_ids) + 1, device=obj_ids.device)
        ids = obj_ids.long()
        bad = (ids < 0) | (ids >= len(table))
        if bad.any() or (table[ids.clamp(0, len(table) - 1)] == 0).any():
            unknown = sorted(set(ids.tolist()) - set(self.obj_ids))
            raise ValueError(f"obj_ids {unknown} not in the label map {list(self.obj_ids)}")
        return table[ids]

    def obj_ids_of(self, labels: torch.Tensor) -> torch.Tensor:
        """Labels ``[N]`` (1..n) -> obj_ids ``[N]`` int64."""
        table = torch.tensor((0,) + self.obj_ids, dtype=torch.int64, device=labels.device)
        return table[labels.long()]

    def to_dict(self) -> dict[str, Any]:
        return {"obj_ids": list(self.obj_ids)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "LabelMap":
        if not isinstance(d, dict) or not isinstance(d.get("obj_ids"), (list, tuple)):
            raise ValueError(f"label map: expected {{'obj_ids': [...]}}, got {d!r}")
        return cls(tuple(d["obj_ids"]))


# ----------------------------------------------------------------------------- config and builders


@dataclass
class DetectorConfig:
    """Model-side detector settings (torchvision names where they exist).

    The defaults are torchvision's Mask R-CNN ResNet-50 FPN (the CosyPose detector) at 640x480.
    A CPU profile measured on this project's 2-core machine: ``name=maskrcnn_mobilenet_v3_large_fpn,
    fpn_channels=128, mask_head_channels=128, box_head_size=512``.
    """

    name: str = "maskrcnn_resnet50_fpn"  # key of DETECTORS
    norm: str = "batch"  # "batch" | "group" (trainable in both cases)
    fpn_channels: int = 256  # FPN width
    mask_head_channels: int = 256  # width of the 4 mask-head convolutions (torchvision: 256)
    box_head_size: int = 1024  # width of the two box-head MLP layers (torchvision: 1024)
    min_size: int = 480  # short side after torchvision's resize (480: 640x480 kept as is)
    max_size: int = 640
    rpn_pre_nms_top_n_train: int = 2000
    rpn_post_nms_top_n_train: int = 2000
    rpn_pre_nms_top_n_test: int = 1000
    rpn_post_nms_top_n_test: int = 1000
    box_batch_size_per_image: int = 512
    box_score_thresh: float = 0.05
    box_nms_thresh: float = 0.5
    box_detections_per_img: int = 100
    anchor_sizes: list[int] = field(default_factory=lambda: [32, 64, 128, 256, 512])  # px, one per FPN level (first n used)
    pretrained: bool = True  # ImageNet weights for the backbones that have them (maskrcnn_lite*_fpn)

    def maskrcnn_kwargs(self) -> dict[str, Any]:
        keys = ("min_size", "max_size", "rpn_pre_nms_top_n_train", "rpn_post_nms_top_n_train",
                "rpn_pre_nms_top_n_test", "rpn_post_nms_top_n_test", "box_batch_size_per_image",
                "box_score_thresh", "box_nms_thresh", "box_detections_per_img")
        return {k: getattr(self, k) for k in keys}


def _norm(cfg: DetectorConfig) -> Callable[[int], nn.Module]:
    return norm_layer(cfg.norm) or nn.BatchNorm2d


def _resnet_fpn(ctor: Callable[..., nn.Module], cfg: DetectorConfig, load_weights: bool = True) -> BackboneWithFPN:
    """ResNet C2..C5 + FPN (+ max-pool level): 5 levels, strides 4..64."""
    net = cast(tvm.ResNet, ctor(weights=None, norm_layer=_norm(cfg)))
    layers = ("layer1", "layer2", "layer3", "layer4")
    c5 = net.fc.in_features  # channels double at each stage: C2..C5 = c5/8, c5/4, c5/2, c5
    in_channels = [c5 // 8, c5 // 4, c5 // 2, c5]
    return BackboneWithFPN(net, {name: str(i) for i, name in enumerate(layers)}, in_channels,
                           cfg.fpn_channels, extra_blocks=LastLevelMaxPool())


def _mobilenet_fpn(ctor: Callable[..., nn.Module], cfg: DetectorConfig, load_weights: bool = True) -> BackboneWithFPN:
    """MobileNetV3 stages at strides 8, 16, 32 + FPN (+ max-pool level): 4 levels."""
    features = cast(tvm.MobileNetV3, ctor(weights=None, norm_layer=_norm(cfg))).features
    # Last block of each resolution (torchvision marks the blocks that end a stage with _is_cn).
    ends = [i for i, b in enumerate(features) if getattr(b, "_is_cn", False)] + [len(features) - 1]
    if len(ends) < 4:
        raise RuntimeError(f"{ctor.__name__}: torchvision no longer marks its stages (_is_cn); update _mobilenet_fpn")
    picked = ends[-4:-3] + ends[-3:-2] + ends[-1:]  # strides 8, 16, 32
    in_channels = [cast(int, features[i].out_channels) for i in picked]  # InvertedResidual, Conv2dNormActivation
    return BackboneWithFPN(features, {str(i): str(k) for k, i in enumerate(picked)}, in_channels,
                           cfg.fpn_channels, extra_blocks=LastLevelMaxPool())


class LiteFPN(nn.Module):
    """ImageNet-pretrained EfficientNet-Lite (strides 4, 8, 16, 32) + FPN (+ max-pool level): 5 levels.

    The trunk's BatchNorm layers are frozen (pretrained statistics; detection batches of 1-2 images
    are too small to re-estimate them) and its stem and first ``frozen_blocks`` blocks get no
    gradient (as torchvision's ``trainable_backbone_layers``).
    """

    def __init__(self, trunk: str, fpn_channels: int, pretrained: bool, frozen_blocks: int = 1,
                 load_weights: bool = True):
        super().__init__()
        from cosy_lite.nets.pretrained import freeze_batchnorm, lite_features

        # load_weights=False: the same (frozen) structure, weights to come from a checkpoint
        body = lite_features(trunk, (1, 2, 3, 4), pretrained=pretrained and load_weights)
        if pretrained:
            body = cast("EfficientNetFeatures", freeze_batchnorm(body))  # frozen in place: the same module
            for module in [body.conv_stem, body.bn1, *list(body.blocks)[:frozen_blocks]]:
                for p in module.parameters():
                    p.requires_grad_(False)
        self.body = body
        self.fpn = FeaturePyramidNetwork(list(body.feature_info.channels()), fpn_channels,
                                         extra_blocks=LastLevelMaxPool())
        self.out_channels = fpn_channels

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.fpn({str(i): f for i, f in enumerate(self.body(x))})


def _lite_fpn(trunk: str, cfg: DetectorConfig, load_weights: bool = True) -> LiteFPN:
    return LiteFPN(trunk, cfg.fpn_channels, cfg.pretrained, load_weights=load_weights)


@dataclass(frozen=True)
class DetectorSpec:
    """A backbone builder and the torchvision classifier it wraps."""

    backbone: Callable[[Any, DetectorConfig, bool], BackboneWithFPN | LiteFPN]  # (ctor, config, load_weights)
    ctor: Any  # torchvision classifier constructor, or the timm trunk name
    n_levels: int  # FPN outputs incl. the max-pool level (one anchor size per level)


DETECTORS: dict[str, DetectorSpec] = {
    "maskrcnn_resnet50_fpn": DetectorSpec(_resnet_fpn, tvm.resnet50, 5),
    "maskrcnn_resnet18_fpn": DetectorSpec(_resnet_fpn, tvm.resnet18, 5),
    "maskrcnn_mobilenet_v3_large_fpn": DetectorSpec(_mobilenet_fpn, tvm.mobilenet_v3_large, 4),
    "maskrcnn_lite0_fpn": DetectorSpec(_lite_fpn, "efficientnet_lite0", 5),  # ImageNet-pretrained (cfg.pretrained)
}


def build_maskrcnn(cfg: DetectorConfig, n_classes: int, load_weights: bool = True) -> MaskRCNN:
    """A torchvision MaskRCNN, randomly initialised except a pretrained trunk (``cfg.pretrained`` and a
    ``maskrcnn_lite*`` backbone; ``load_weights=False`` skips reading those weights, for a model whose
    weights come from a checkpoint). Scratch backbones have trainable BatchNorm (not torchvision's frozen)."""
    if cfg.name not in DETECTORS:
        raise ValueError(f"detector {cfg.name!r} unknown; available: {sorted(DETECTORS)}")
    spec = DETECTORS[cfg.name]
    sizes = list(cfg.anchor_sizes)[: spec.n_levels]
    if len(sizes) != spec.n_levels:
        raise ValueError(f"{cfg.name} needs {spec.n_levels} anchor_sizes (one per FPN level), got {cfg.anchor_sizes}")
    anchors = AnchorGenerator(tuple((s,) for s in sizes), ((0.5, 1.0, 2.0),) * spec.n_levels)
    backbone = spec.backbone(spec.ctor, cfg, load_weights)  # load_weights: only pretrained trunks read a file
    c, m = backbone.out_channels, cfg.mask_head_channels
    box_head = TwoMLPHead(c * BOX_POOL**2, cfg.box_head_size)
    return MaskRCNN(backbone, num_classes=None, rpn_anchor_generator=anchors,  # classes set by the predictors
                    box_head=box_head, box_predictor=FastRCNNPredictor(cfg.box_head_size, n_classes),
                    mask_head=MaskRCNNHeads(c, [m] * 4, 1), mask_predictor=MaskRCNNPredictor(m, m, n_classes),
                    **cfg.maskrcnn_kwargs())


# ----------------------------------------------------------------------------- the module


class Detector(nn.Module):
    """torchvision Mask R-CNN + the obj_id label map.

    ``forward(images, targets)`` in training mode returns the loss dict, in eval mode a list of
    :class:`Detections`; prefer :func:`detector_losses` and :func:`detect`.

    Args:
        label_map: obj_id <-> label.
        config: backbone name, image size and torchvision settings.
    """

    def __init__(self, label_map: LabelMap, config: DetectorConfig | None = None, load_weights: bool = True):
        super().__init__()
        self.label_map = label_map
        self.config = config or DetectorConfig()
        self.net = build_maskrcnn(self.config, label_map.n_classes, load_weights)

    def meta(self) -> dict[str, Any]:
        """What a checkpoint needs to rebuild the module (config + label map + initial weights)."""
        return {"detector_config": asdict(self.config), "label_map": self.label_map.to_dict(),
                "initialised_from": self.initialised_from()}

    def initialised_from(self) -> str:
        """The pretrained weights that initialised the trunk, or ``"scratch"``."""
        from cosy_lite.nets.pretrained import pretrained_source

        trunk = DETECTORS[self.config.name].ctor
        if self.config.pretrained and isinstance(trunk, str):
            return pretrained_source(trunk)
        return "scratch"

    @classmethod
    def from_meta(cls, meta: dict[str, Any]) -> "Detector":
        """The module of a checkpoint's ``meta``, to receive the checkpoint's weights."""
        return cls(LabelMap.from_dict(meta["label_map"]), DetectorConfig(**meta["detector_config"]), load_weights=False)

    def _check_targets(self, images: list[torch.Tensor], targets: list[dict[str, torch.Tensor]]) -> None:
        if len(targets) != len(images):
            raise ValueError(f"{len(images)} images but {len(targets)} targets")
        for i, (im, t) in enumerate(zip(images, targets)):
            if not {"boxes", "labels", "masks"} <= set(t):
                raise ValueError(f"target {i}: needs keys boxes, labels, masks; got {sorted(t)}")
            n = len(t["boxes"])
            if t["boxes"].shape != (n, 4) or t["labels"].shape != (n,) or t["masks"].shape != (n, *im.shape[-2:]):
                raise ValueError(f"target {i}: boxes {tuple(t['boxes'].shape)}, labels {tuple(t['labels'].shape)}, "
                                 f"masks {tuple(t['masks'].shape)} do not fit [N,4], [N], [N,{im.shape[-2]},{im.shape[-1]}]")
            if n and (t["labels"].min() < 1 or t["labels"].max() >= self.label_map.n_classes):
                raise ValueError(f"target {i}: labels {t['labels'].tolist()} outside 1..{self.label_map.n_classes - 1} "
                                 "(labels are LabelMap.labels(obj_ids), not obj_ids)")

    def forward(self, images: list[torch.Tensor], targets: list[dict[str, torch.Tensor]] | None = None,
                mask_threshold: float = MASK_THRESHOLD):
        for i, im in enumerate(images):
            if im.ndim != 3 or im.shape[0] != 3 or not im.is_floating_point():
                raise ValueError(f"image {i}: expected float [3,H,W] in [0,1], got {im.dtype} {tuple(im.shape)}")
        if self.training:
            if targets is None:
                raise ValueError("training mode needs targets")
            self._check_targets(images, targets)
            return self.net(images, targets)
        return [self._detections(o, mask_threshold) for o in self.net(images)]

    def _detections(self, out: dict[str, torch.Tensor], mask_threshold: float) -> Detections:
        binary = binary_masks(out["masks"][:, 0].cpu().numpy(), mask_threshold)
        masks = torch.from_numpy(binary).to(out["masks"].device)
        return Detections(boxes=out["boxes"], obj_ids=self.label_map.obj_ids_of(out["labels"]),
                          scores=out["scores"], masks=masks)


def _unwrap(model: nn.Module) -> Detector:
    """The :class:`Detector` inside a DDP wrapper (or the model itself)."""
    inner = getattr(model, "module", model)
    if not isinstance(inner, Detector):
        raise TypeError(f"expected a Detector (possibly DDP-wrapped), got {type(inner).__name__}")
    return inner


def detector_losses(model: nn.Module, images: list[torch.Tensor],
                    targets: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Mask R-CNN training losses; the model must be in training mode (DDP wrapper allowed).

    ``images``: B x ``[3,H,W]`` float in ``[0,1]``. ``targets``: B x torchvision targets as in
    :class:`cosy_lite.structures.DetectionBatch`: ``boxes [N,4]`` float xyxy px (positive width and
    height), ``labels [N]`` int64 = ``LabelMap.labels(obj_ids)``, ``masks [N,H,W]`` uint8/bool.

    Returns torchvision's terms (``loss_classifier``, ``loss_box_reg``, ``loss_mask``,
    ``loss_objectness``, ``loss_rpn_box_reg``) and ``total``, their sum.
    """
    if not _unwrap(model).training:
        raise ValueError("detector_losses needs the model in training mode (model.train())")
    losses = dict(model(images, targets))
    losses["total"] = sum(losses.values())
    return losses


@torch.no_grad()
def detect(model: nn.Module, images: list[torch.Tensor], mask_threshold: float = MASK_THRESHOLD) -> list[Detections]:
    """Detections per image (boxes in the input image's pixels, masks at its size: the mask head's
    probabilities above ``mask_threshold``, :func:`~cosy_lite.nets.detection_masks.binary_masks`).

    Runs in eval mode and restores the previous mode afterwards.
    """
    was_training = model.training
    model.eval()
    try:
        return model(images, mask_threshold=mask_threshold)
    finally:
        model.train(was_training)
