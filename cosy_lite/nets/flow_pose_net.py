"""The flow refiner network: where is each rendered surface point in the image crop?

Input as every pose network here: the image crop and the rendering stacked on channels,
``[B, 6, H, W]`` in ``[0, 1]``. Output: a dense displacement field on the stride-8 (or 4) grid,
``[B, 3, H/s, W/s]`` (``s`` = 8 or 4) = (dx, dy) in crop pixels from each rendering cell to the matching image
position, and a confidence in ``[0, 1]``. The pose update is then geometry, not learning: the
rendering's depth makes every cell a 2D-3D correspondence and
:func:`cosy_lite.nets.flow_pose_solver.pose_from_flow` fits the pose to them.

Why (bench/RESULTS.md, 2026-12-01): a network regressing the 9 update numbers from the pair learns
from one number-vector per crop and did not halve the refiner errors in 62,000 crops; the flow
target gives a supervised displacement for every visible rendered cell (hundreds per crop), which
the GT pose provides for free (:mod:`cosy_lite.nets.flow_targets`).

Layers: one ImageNet-pretrained EfficientNet-Lite trunk (:mod:`cosy_lite.nets.pretrained`) on the
crop and the rendering separately (stride 8 and 16 maps; the stride-16 one upsampled for context) ->
a small trainable descriptor head -> unit descriptors -> the local correlation (cost volume) of each
rendering cell with the image cells within ``+-radius`` cells, divided by a learnt temperature ->
softmax -> expected displacement (soft-argmax) and the peak probability as confidence.

Stride 4 (``stride=4``): the stride-8 descriptors, upsampled to the stride-4 grid, plus a residual
read from the trunk's stride-4 map and them (the ``fine`` module, its last layer zero at the start,
so published stride-8 weights fine-tune from their own descriptors, upsampled). Four times the
cells, each a quarter of the area: the flow's scale, which is the depth, over finer cells. The
radius stays in cells (``radius=8`` at stride 4 reaches the +-32 px of ``radius=4`` at stride 8).

Depth (``depth_head=True``): the flow fixes depth only through the scale of the displacement
field, a pixel or two across the object, and the refiner drifted in depth by ~1 cm per iteration
from a perfect start (bench/RESULTS.md). The depth head reads both descriptors and the cost
volume's probabilities of each cell and says, per rendered cell, the log ratio of the object's new
depth to the current one (CosyPose's ``v_z``); the solver takes their confidence-weighted mean
(:func:`cosy_lite.nets.flow_pose_solver.pose_from_flow`). Its output is a fourth channel.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from cosy_lite.nets.flow_pose_solver import FLOW_STRIDE, FLOW_STRIDES
from cosy_lite.nets.pose_net import IMAGENET_MEAN, IMAGENET_STD

TRUNK_LEVELS = {8: (2, 3), 4: (1, 2, 3)}  # timm feature indices per flow stride: strides (4,) 8 and 16
FLOW_CHANNELS = 3  # dx, dy (crop px), confidence
DEPTH_CHANNELS = 4  # with a depth head: + log(new depth / current depth) of the object, per cell


def local_cost_volume(a: torch.Tensor, b: torch.Tensor, radius: int) -> torch.Tensor:
    """``[B, (2r+1)^2, H, W]``: ``<a(p), b(p + d)>`` summed over channels for ``d = (dx, dy)``,
    ``|dx|, |dy| <= radius``, row-major in ``(dy, dx)``; ``b`` is 0 outside the map."""
    _, _, H, W = a.shape
    padded = F.pad(b, (radius, radius, radius, radius))
    n = 2 * radius + 1
    return torch.stack([(a * padded[:, :, dy:dy + H, dx:dx + W]).sum(1) for dy in range(n) for dx in range(n)], dim=1)


def flow_from_cost(logits: torch.Tensor, radius: int, stride: int) -> torch.Tensor:
    """``[B, 3, H, W]`` (dx, dy in pixels, confidence) from cost-volume logits ``[B, (2r+1)^2, H, W]``."""
    B, _, H, W = logits.shape
    n = 2 * radius + 1
    p = logits.softmax(dim=1).view(B, n, n, H, W)
    d = torch.arange(n, dtype=p.dtype, device=p.device) - radius
    dy = (p.sum(2) * d.view(1, n, 1, 1)).sum(1)
    dx = (p.sum(1) * d.view(1, n, 1, 1)).sum(1)
    confidence = p.flatten(1, 2).amax(dim=1)
    return torch.stack([dx * stride, dy * stride, confidence], dim=1)


def _conv_bn_relu(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, 1, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


def _zero_conv(c_in: int, c_out: int) -> nn.Conv2d:
    """A 1x1 convolution that starts at zero: the module it ends adds nothing until trained."""
    conv = nn.Conv2d(c_in, c_out, 1)
    for p in conv.parameters():
        nn.init.zeros_(p)
    return conv


def _resized(f: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return F.interpolate(f, size=like.shape[-2:], mode="bilinear", align_corners=False)


class FlowPoseNet(nn.Module):
    """Pretrained siamese trunk -> descriptors -> local cost volume -> flow and confidence.

    Args:
        trunk: a key of :data:`cosy_lite.nets.pretrained.WEIGHTS` (``"efficientnet_lite0"``).
        pretrained: ImageNet weights for the trunk (False: random, for tests and ablations).
        load_weights: False builds the same network without reading the weights file (the
            weights then come from a checkpoint).
        radius: displacements of the cost volume, in cells (``stride`` px each).
        descriptor: channels of the matching descriptors.
        temperature: initial softmax temperature of the cosine similarities (learnt).
        depth_head: a fourth output channel, the log depth ratio (see the module doc); its last
            layer starts at zero (depth kept), so published weights without it fine-tune from
            the network they were.
        stride: crop pixels per flow cell, 8 or 4 (see the module doc; the ``fine`` module).
    """

    # buffers (register_buffer), declared for type checkers
    mean: torch.Tensor  # [1, 3, 1, 1] ImageNet mean
    std: torch.Tensor  # [1, 3, 1, 1]

    output = "flow"  # what forward returns: the render-and-compare loop solves the pose from it

    def __init__(self, trunk: str = "efficientnet_lite0", pretrained: bool = True, load_weights: bool = True,
                 radius: int = 4, descriptor: int = 64, temperature: float = 0.05, depth_head: bool = False,
                 stride: int = FLOW_STRIDE):
        super().__init__()
        from cosy_lite.nets.pretrained import lite_features

        if radius < 1:
            raise ValueError(f"radius must be >= 1 cell, got {radius}")
        if stride not in FLOW_STRIDES:
            raise ValueError(f"stride must be one of {FLOW_STRIDES} px, got {stride}")
        self.in_channels = 6
        self.radius = int(radius)
        self.stride = int(stride)
        self.trunk = lite_features(trunk, TRUNK_LEVELS[self.stride], pretrained=pretrained and load_weights)
        *c4, c8, c16 = self.trunk.feature_info.channels()
        self.descriptor = nn.Sequential(_conv_bn_relu(c8 + c16, 2 * descriptor), _conv_bn_relu(2 * descriptor, descriptor),
                                        nn.Conv2d(descriptor, descriptor, 1))
        self.fine: nn.Sequential | None = None
        if self.stride == 4:
            self.fine = nn.Sequential(_conv_bn_relu(c4[0] + descriptor, descriptor), _zero_conv(descriptor, descriptor))
        self.log_temperature = nn.Parameter(torch.tensor(math.log(temperature)))
        self.depth_head: nn.Sequential | None = None
        if depth_head:
            last = _zero_conv(descriptor, 1)
            self.depth_head = nn.Sequential(_conv_bn_relu(2 * descriptor + (2 * radius + 1) ** 2, descriptor),
                                            _conv_bn_relu(descriptor, descriptor), last)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def descriptors(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Unit descriptors of the image crops and of the renderings, each ``[B, C, H/s, W/s]`` (``s``: the stride)."""
        if images.ndim != 4 or images.shape[1] != 6:
            raise ValueError(f"FlowPoseNet expects images [B,6,H,W], got {tuple(images.shape)}")
        if images.shape[2] % 16 or images.shape[3] % 16:
            raise ValueError(f"FlowPoseNet needs crops divisible by 16, got {images.shape[2]}x{images.shape[3]}")
        B = images.shape[0]
        x = (torch.cat([images[:, :3], images[:, 3:]], dim=0) - self.mean) / self.std
        *f4, f8, f16 = self.trunk(x)
        f = self.descriptor(torch.cat([f8, _resized(f16, f8)], dim=1))
        if self.fine is not None:
            f = _resized(f, f4[0])
            f = f + self.fine(torch.cat([f4[0], f], dim=1))
        f = F.normalize(f, dim=1)
        return f[:B], f[B:]

    @property
    def new_modules(self) -> tuple[str, ...]:
        """Modules that published weights of a network without them may lack (``train.py --init``)."""
        return tuple(name for name in ("fine", "depth_head") if getattr(self, name) is not None)

    @property
    def channels(self) -> int:
        """Channels of the output: :data:`FLOW_CHANNELS`, or :data:`DEPTH_CHANNELS` with a depth head."""
        return FLOW_CHANNELS if self.depth_head is None else DEPTH_CHANNELS

    def cost_volume(self, images: torch.Tensor) -> torch.Tensor:
        """Logits ``[B, (2r+1)^2, H/s, W/s]`` (rendering cell vs the image cells around it), followed
        with a depth head by its log depth ratios ``[B, 1, H/s, W/s]``."""
        image, rendering = self.descriptors(images)
        logits = local_cost_volume(rendering, image, self.radius) / self.log_temperature.exp()
        if self.depth_head is None:
            return logits
        depth = self.depth_head(torch.cat([rendering, image, logits.softmax(dim=1)], dim=1))
        return torch.cat([logits, depth], dim=1)

    def forward(self, images: torch.Tensor, cost_volume: bool = False) -> torch.Tensor:
        """``images [B, 6, H, W]`` (crop, rendering) -> ``[B, C, H/s, W/s]`` (dx, dy px, confidence[,
        log depth ratio]); ``cost_volume=True``: :meth:`cost_volume` instead (training; through forward
        so that DDP sees the call)."""
        raw = self.cost_volume(images)
        if cost_volume:
            return raw
        n = (2 * self.radius + 1) ** 2
        flow = flow_from_cost(raw[:, :n], self.radius, self.stride)
        return flow if self.depth_head is None else torch.cat([flow, raw[:, n:]], dim=1)
