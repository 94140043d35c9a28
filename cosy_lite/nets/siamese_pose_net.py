"""The pose network with an ImageNet-pretrained siamese trunk and a displacement layer.

Same contract as :class:`~cosy_lite.nets.pose_net.PoseNet` (tensor in, tensor out): input the
image crop and the rendered crop stacked on channels, ``[B, 6, H, W]`` in ``[0, 1]``; output the
pose update ``delta [B, 9]`` of :mod:`cosy_lite.nets.pose_update`, from a zero-initialised head
(identity update untrained) scaled by ``output_scale`` (see ``pose_net``).

Why not a 6-channel early-fusion CNN (``PoseNet``): on the 2-core CPU it does not learn real
crops within tens of thousands of samples (bench/RESULTS.md). This network builds in what the
task needs instead of learning it:

* one **pretrained EfficientNet-Lite** trunk (``cosy_lite.nets.pretrained``) applied to the image
  crop and to the rendering separately, so both are described by ImageNet features whatever the
  renderer's flat shading (template matching with those features alone finds the shift of the
  object to ~2 px at stride 4);
* a **local correlation** (cost volume) of the two stride-8 feature maps over displacements of
  ``+-corr_radius`` cells, the optical-flow networks' layer: the shift between rendering and image
  is then a peak position, not something to discover;
* **spatial soft-argmax** pooling (expected x, y of each channel's spatial softmax) next to the
  average pooling, so positions in the crop reach the linear head linearly;
* optionally (``flat_channels > 0``) the stride-16 map itself, reduced to ``flat_channels`` by a 1x1
  convolution and flattened into the head: a rotation shows as a displacement field whose
  pattern over the crop (not its average) tells the axis, and a linear head can read a pattern.

Fusion: [image s8, rendering s8, correlation] -> conv (stride 2) -> + [image s16, rendering s16]
-> 3 convs (one with stride 2 unless ``flat_channels``) -> pooling (+ flattened map) -> Linear(9).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from cosy_lite.geometry.crops import CROP_RESOLUTION
from cosy_lite.nets.pose_net import IMAGENET_MEAN, IMAGENET_STD, N_OUT, output_scale_vector

TRUNK_LEVELS = (2, 3)  # timm feature indices: strides 8 and 16
CORRELATION_GAIN = 10.0  # the mean-over-channels dot products are ~0.1: brought to order 1


def local_correlation(a: torch.Tensor, b: torch.Tensor, radius: int) -> torch.Tensor:
    """``[B, (2r+1)^2, H, W]``: channel mean of ``a(p) * b(p + d)`` for the displacements
    ``d = (dx, dy)``, ``|dx|, |dy| <= radius``, row-major in ``(dy, dx)``; ``b`` is 0 outside."""
    _, _, H, W = a.shape
    padded = F.pad(b, (radius, radius, radius, radius))
    n = 2 * radius + 1
    return torch.cat([(a * padded[:, :, dy:dy + H, dx:dx + W]).mean(1, keepdim=True)
                      for dy in range(n) for dx in range(n)], dim=1)


def spatial_soft_argmax(x: torch.Tensor) -> torch.Tensor:
    """``[B, C, H, W] -> [B, 2C]``: per channel the expected ``(x, y)`` in ``[-1, 1]`` of its spatial softmax."""
    B, C, H, W = x.shape
    p = x.flatten(2).softmax(-1).view(B, C, H, W)
    xs = torch.linspace(-1.0, 1.0, W, dtype=x.dtype, device=x.device)
    ys = torch.linspace(-1.0, 1.0, H, dtype=x.dtype, device=x.device)
    return torch.cat([(p.sum(2) * xs).sum(-1), (p.sum(3) * ys).sum(-1)], dim=1)


def _conv_bn_relu(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


def _drop_removed_trunk_blocks(module: SiamesePoseNet, state_dict: dict[str, torch.Tensor], prefix: str,
                               *args: object) -> None:
    """Load hook: checkpoints written before the trunk lost its unused last blocks (2026-12-02) still
    carry their weights; they are left out."""
    head, kept = prefix + "trunk.blocks.", len(module.trunk.blocks)
    for key in [k for k in state_dict if k.startswith(head) and int(k[len(head):].split(".")[0]) >= kept]:
        del state_dict[key]


class SiamesePoseNet(nn.Module):
    """Pretrained siamese trunk + correlation + soft-argmax pooling + zero-initialised head.

    Args:
        trunk: a key of :data:`cosy_lite.nets.pretrained.WEIGHTS` (``"efficientnet_lite0"``).
        pretrained: ImageNet weights for the trunk (False: random, for tests and ablations).
        load_weights: False builds the same network without reading the weights file (the
            weights then come from a checkpoint).
        corr_radius: displacements of the cost volume, in stride-8 cells (0: no correlation).
        width: channels of the fusion layers (the last ones have ``2 * width``).
        output_scale: as :class:`~cosy_lite.nets.pose_net.PoseNet`.
        crop_resolution: (h, w) of the input crops (multiples of 16 with ``flat_channels``).
        flat_channels: channels of the flattened stride-16 map fed to the head (0: none).
    """

    # buffers (register_buffer), declared for type checkers
    mean: torch.Tensor  # [1, 3, 1, 1] ImageNet mean
    std: torch.Tensor  # [1, 3, 1, 1]
    output_scale: torch.Tensor  # [1, 9] head multipliers

    def __init__(self, trunk: str = "efficientnet_lite0", pretrained: bool = True, load_weights: bool = True,
                 corr_radius: int = 3, width: int = 128, output_scale: tuple[float, float, float] = (0.25, 0.04, 0.06),
                 crop_resolution: tuple[int, int] = CROP_RESOLUTION, flat_channels: int = 0):
        super().__init__()
        from cosy_lite.nets.pretrained import lite_features

        self.in_channels = 6
        self.trunk = lite_features(trunk, TRUNK_LEVELS, pretrained=pretrained and load_weights)
        self.register_load_state_dict_pre_hook(_drop_removed_trunk_blocks)
        c8, c16 = self.trunk.feature_info.channels()
        self.corr_radius = int(corr_radius)
        n_corr = (2 * self.corr_radius + 1) ** 2 if self.corr_radius > 0 else 0
        self.fuse8 = _conv_bn_relu(2 * c8 + n_corr, width, stride=2)
        h, w = (int(v) for v in crop_resolution)
        self.flat_channels = int(flat_channels)
        if self.flat_channels and (h % 16 or w % 16):
            raise ValueError(f"flat_channels needs a crop resolution divisible by 16, got {h}x{w}")
        self.fuse16 = nn.Sequential(_conv_bn_relu(width + 2 * c16, 2 * width),
                                    _conv_bn_relu(2 * width, 2 * width, 1 if self.flat_channels else 2),
                                    _conv_bn_relu(2 * width, 2 * width))
        n_features = 3 * 2 * width  # average pooling + (x, y) per channel
        self.flat = None
        if self.flat_channels:
            self.flat = nn.Sequential(nn.Conv2d(2 * width, self.flat_channels, 1), nn.ReLU(inplace=True))
            n_features += self.flat_channels * (h // 16) * (w // 16)
        self.head = nn.Linear(n_features, N_OUT)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("output_scale", output_scale_vector(output_scale, w), persistent=False)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """``images [B, 6, H, W]`` float in ``[0, 1]`` (crop, rendering) -> ``delta [B, 9]``."""
        if images.ndim != 4 or images.shape[1] != 6:
            raise ValueError(f"SiamesePoseNet expects images [B,6,H,W], got {tuple(images.shape)}")
        B = images.shape[0]
        x = (torch.cat([images[:, :3], images[:, 3:]], dim=0) - self.mean) / self.std
        f8, f16 = self.trunk(x)
        parts = [f8[:B], f8[B:]]
        if self.corr_radius > 0:
            parts.append(local_correlation(f8[B:], f8[:B], self.corr_radius) * CORRELATION_GAIN)
        y = self.fuse8(torch.cat(parts, dim=1))
        y = self.fuse16(torch.cat([y, f16[:B], f16[B:]], dim=1))
        features = [y.mean(dim=(2, 3)), spatial_soft_argmax(y)]
        if self.flat is not None:
            features.append(self.flat(y).flatten(1))
        return self.head(torch.cat(features, dim=1)) * self.output_scale
