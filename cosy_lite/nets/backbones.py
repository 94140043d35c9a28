"""Classification backbones from torchvision used as feature extractors (image -> pooled vector).

Every backbone is built with ``weights=None``: torchvision downloads pretrained weights at run
time and no registry package ships them, so all networks here train from scratch. The first
convolution is replaced when ``in_channels != 3`` (the pose nets see 6 channels: image crop +
rendered crop) and the classifier is dropped, so ``forward`` returns ``[B, out_features]``.

Normalisation layers are trainable: ``"batch"`` (torchvision's BatchNorm defaults) or ``"group"``
(GroupNorm, for small per-device batches).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, cast

import torch
from torch import nn
from torchvision import models as tvm

NORM_LAYERS = ("batch", "group")
GROUPS = 32  # GroupNorm groups (fewer when the channel count is not divisible)
Pair = tuple[int, int]  # nn.Conv2d's 2D kernel size, stride, padding, dilation (typed there as tuple[int, ...])


def group_norm(num_channels: int) -> nn.GroupNorm:
    """GroupNorm with gcd(32, C) groups, usable as a torchvision ``norm_layer``."""
    return nn.GroupNorm(math.gcd(GROUPS, num_channels), num_channels)


def norm_layer(norm: str) -> Callable[[int], nn.Module] | None:
    """``"batch"`` -> None (keep torchvision's trainable BatchNorm defaults), ``"group"`` -> GroupNorm."""
    if norm not in NORM_LAYERS:
        raise ValueError(f"norm {norm!r} unknown; use one of {NORM_LAYERS}")
    return group_norm if norm == "group" else None


def _replace_conv_input(conv: nn.Conv2d, in_channels: int) -> nn.Conv2d:
    """A copy of ``conv`` taking ``in_channels`` inputs (fresh weights)."""
    if in_channels == conv.in_channels:
        return conv
    padding = conv.padding if isinstance(conv.padding, str) else cast(Pair, conv.padding)
    return nn.Conv2d(in_channels, conv.out_channels, cast(Pair, conv.kernel_size), cast(Pair, conv.stride), padding,
                     cast(Pair, conv.dilation), conv.groups, conv.bias is not None)


def _norm_kwargs(norm: str) -> dict[str, Callable[[int], nn.Module]]:
    layer = norm_layer(norm)
    return {} if layer is None else {"norm_layer": layer}


def _resnet(ctor: Callable[..., nn.Module], in_channels: int, norm: str) -> tuple[nn.Module, int]:
    net = ctor(weights=None, **_norm_kwargs(norm))
    net.conv1 = _replace_conv_input(cast(nn.Conv2d, net.conv1), in_channels)
    n = cast(nn.Linear, net.fc).in_features
    net.fc = nn.Identity()
    return net, n


def _replace_first_conv(net: nn.Module, in_channels: int) -> None:
    """``net.features[0][0]`` (the stem convolution of EfficientNet, MobileNetV3) for ``in_channels`` inputs."""
    stem = cast(nn.Sequential, cast(nn.Sequential, net.features)[0])
    stem[0] = _replace_conv_input(cast(nn.Conv2d, stem[0]), in_channels)


def _efficientnet(ctor: Callable[..., nn.Module], in_channels: int, norm: str) -> tuple[nn.Module, int]:
    net = ctor(weights=None, **_norm_kwargs(norm))
    _replace_first_conv(net, in_channels)
    n = cast(nn.Linear, cast(nn.Sequential, net.classifier)[-1]).in_features
    net.classifier = nn.Identity()
    return net, n


def _mobilenet_v3(ctor: Callable[..., nn.Module], in_channels: int, norm: str) -> tuple[nn.Module, int]:
    net = ctor(weights=None, **_norm_kwargs(norm))
    _replace_first_conv(net, in_channels)
    # pooled last conv (the Linear-Hardswish head is dropped)
    n = cast(nn.Linear, cast(nn.Sequential, net.classifier)[0]).in_features
    net.classifier = nn.Identity()
    return net, n


@dataclass(frozen=True)
class BackboneSpec:
    """How to build one backbone: a family adapter and the torchvision constructor."""

    adapter: Callable[[Callable[..., nn.Module], int, str], tuple[nn.Module, int]]
    ctor: Callable[..., nn.Module]

    def build(self, in_channels: int, norm: str) -> tuple[nn.Module, int]:
        return self.adapter(self.ctor, in_channels, norm)


BACKBONES: dict[str, BackboneSpec] = {
    "resnet18": BackboneSpec(_resnet, tvm.resnet18),
    "resnet34": BackboneSpec(_resnet, tvm.resnet34),
    "resnet50": BackboneSpec(_resnet, tvm.resnet50),
    "efficientnet_b0": BackboneSpec(_efficientnet, tvm.efficientnet_b0),
    "efficientnet_b3": BackboneSpec(_efficientnet, tvm.efficientnet_b3),
    "mobilenet_v3_small": BackboneSpec(_mobilenet_v3, tvm.mobilenet_v3_small),
    "mobilenet_v3_large": BackboneSpec(_mobilenet_v3, tvm.mobilenet_v3_large),
}


class Backbone(nn.Module):
    """A torchvision classifier without its classifier: ``[B,C,H,W] -> [B, out_features]``.

    Args:
        name: key of :data:`BACKBONES`.
        in_channels: input channels (the first convolution is rebuilt if not 3).
        norm: ``"batch"`` or ``"group"``.
    """

    def __init__(self, name: str, in_channels: int = 3, norm: str = "batch"):
        super().__init__()
        if name not in BACKBONES:
            raise ValueError(f"backbone {name!r} unknown; available: {sorted(BACKBONES)}")
        if in_channels < 1:
            raise ValueError(f"in_channels must be >= 1, got {in_channels}")
        self.name = name
        self.in_channels = in_channels
        self.net, self.out_features = BACKBONES[name].build(in_channels, norm)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x [B, in_channels, H, W]`` float -> pooled features ``[B, out_features]``."""
        return self.net(x)
