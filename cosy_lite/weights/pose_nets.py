"""The pose networks (coarse and refiner) a config describes: :class:`PoseNetConfig` ->
:func:`build_pose_net`.

A checkpoint stores the config as ``meta["net"]`` (a dict), so the same function builds the
network to train (:class:`~cosy_lite.train.pose_task.PoseTask`) and the one its weights are loaded
into (:func:`~cosy_lite.weights.loaders.load_pose_model`, export).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, cast

import torch

from cosy_lite.errors import ConfigError
from cosy_lite.geometry.crops import CROP_RESOLUTION
from cosy_lite.nets.pose_net import OUTPUT_SCALES, PoseNet

POSE_ARCHS = ("early", "siamese", "flow")
PRETRAINED_ARCHS = ("siamese", "flow")  # trunks from cosy_lite.nets.pretrained


@dataclass
class PoseNetConfig:
    """``arch``: ``"early"`` (:class:`PoseNet`: a torchvision backbone on the 6 stacked channels),
    ``"siamese"`` (:class:`SiamesePoseNet`: pretrained trunk on each image + correlation -> 9 numbers)
    or ``"flow"`` (:class:`FlowPoseNet`: pretrained trunk -> descriptors -> cost volume -> dense
    flow, the pose solved from it; refiner only)."""

    arch: str = "early"
    backbone: str = "resnet34"  # early: a key of backbones.BACKBONES; siamese, flow: of pretrained.WEIGHTS
    crop_resolution: list[int] = field(default_factory=lambda: list(CROP_RESOLUTION))  # (h, w), 4:3
    norm: str = "batch"  # early only
    pretrained: bool = True  # siamese, flow: ImageNet weights for the trunk
    corr_radius: int = 3  # siamese, flow: cost-volume displacements in stride-8 cells
    width: int = 128  # siamese: fusion channels; flow: descriptor channels
    flat_channels: int = 0  # siamese: channels of the flattened stride-16 map in the head (0: none)
    # how the object is rendered for the network: "headlight" (shaded: 3D shape cues) or "flat"
    # (colours only); inference renders as the checkpoint says
    render_shading: str = "headlight"
    # head units -> (6D residual, xy shift as a fraction of the crop width, log depth); see PoseNet.
    # None: the model kind's default (pose_net.OUTPUT_SCALES)
    output_scale: list[float] | None = None
    # flow: a depth head (log ratio of the new depth to the current one, a 4th output channel) instead
    # of the depth the flow's scale implies
    depth_head: bool = False
    # flow: crop pixels per flow cell, 8 or 4 (stride-8 descriptors upsampled plus a residual from the
    # trunk's stride-4 map); corr_radius counts cells of this size
    flow_stride: int = 8


def check_net_config(cfg: PoseNetConfig) -> None:
    """ConfigError naming the field when ``net.arch`` / ``net.backbone`` / ``net.render_shading`` do not fit."""
    from cosy_lite.nets.backbones import BACKBONES
    from cosy_lite.nets.flow_pose_solver import FLOW_STRIDE, FLOW_STRIDES
    from cosy_lite.nets.pretrained import WEIGHTS
    from cosy_lite.render.renderer import SHADINGS

    if cfg.arch not in POSE_ARCHS:
        raise ConfigError("network config", "net.arch", f"expected one of {list(POSE_ARCHS)}, got {cfg.arch!r}")
    if cfg.arch in PRETRAINED_ARCHS and cfg.backbone not in WEIGHTS:
        raise ConfigError("network config", "net.backbone", f"net.arch={cfg.arch} needs a pretrained trunk, one of "
                          f"{sorted(WEIGHTS)}; got {cfg.backbone!r} (torchvision backbones: net.arch=early)")
    if cfg.arch == "flow" and (cfg.crop_resolution[0] % 16 or cfg.crop_resolution[1] % 16):
        raise ConfigError("network config", "net.crop_resolution", f"net.arch=flow needs crops divisible by 16, "
                          f"got {list(cfg.crop_resolution)}")
    if cfg.depth_head and cfg.arch != "flow":
        raise ConfigError("network config", "net.depth_head", f"a depth head belongs to net.arch=flow, not {cfg.arch!r}")
    if cfg.flow_stride != FLOW_STRIDE and (cfg.arch != "flow" or cfg.flow_stride not in FLOW_STRIDES):
        raise ConfigError("network config", "net.flow_stride", f"expected {FLOW_STRIDE}, or one of {list(FLOW_STRIDES)} "
                          f"with net.arch=flow; got {cfg.flow_stride!r} with net.arch={cfg.arch}")
    if cfg.arch == "flow" and cfg.corr_radius < 1:
        raise ConfigError("network config", "net.corr_radius", f"net.arch=flow needs >= 1 cell, got {cfg.corr_radius}")
    if cfg.arch == "early" and cfg.backbone not in BACKBONES:
        raise ConfigError("network config", "net.backbone", f"net.arch=early needs one of {sorted(BACKBONES)}, "
                          f"got {cfg.backbone!r} (pretrained trunks: net.arch=siamese)")
    if cfg.render_shading not in SHADINGS:
        raise ConfigError("network config", "net.render_shading", f"expected one of {list(SHADINGS)}, got {cfg.render_shading!r}")


def build_pose_net(net_cfg: PoseNetConfig | dict[str, Any], kind: str = "refiner",
                   load_weights: bool = True) -> torch.nn.Module:
    """The ``kind`` ("coarse" | "refiner") network of ``net_cfg`` (the kind only picks the default
    output scale). ``load_weights=False``: do not read pretrained weights (a checkpoint's follow)."""
    cfg = net_cfg if isinstance(net_cfg, PoseNetConfig) else PoseNetConfig(**net_cfg)
    if kind not in OUTPUT_SCALES:
        raise ValueError(f"model kind must be one of {sorted(OUTPUT_SCALES)}, got {kind!r}")
    check_net_config(cfg)
    # (lengths: the networks unpack 3 scales and an (h, w) crop resolution, raising otherwise)
    scale = cast(tuple[float, float, float], tuple(OUTPUT_SCALES[kind] if cfg.output_scale is None else cfg.output_scale))
    if cfg.arch == "flow":
        from cosy_lite.nets.flow_pose_net import FlowPoseNet

        return FlowPoseNet(cfg.backbone, pretrained=cfg.pretrained, load_weights=load_weights,
                           radius=cfg.corr_radius, descriptor=cfg.width, depth_head=cfg.depth_head,
                           stride=cfg.flow_stride)
    if cfg.arch == "siamese":
        from cosy_lite.nets.siamese_pose_net import SiamesePoseNet

        return SiamesePoseNet(cfg.backbone, pretrained=cfg.pretrained, load_weights=load_weights,
                              corr_radius=cfg.corr_radius, width=cfg.width, output_scale=scale,
                              crop_resolution=cast(tuple[int, int], tuple(cfg.crop_resolution)),
                              flat_channels=cfg.flat_channels)
    return PoseNet(backbone=cfg.backbone, in_channels=6, norm=cfg.norm, output_scale=scale,
                   crop_width=int(cfg.crop_resolution[1]))
