"""The pose network shared by the coarse model and the refiner: tensor in, tensor out.

Input: the image crop and the rendered crop stacked on channels, ``[B, 6, H, W]`` in ``[0, 1]``
(normalised inside, so ONNX users feed plain ``[0, 1]`` images). Output: the pose update
``delta [B, 9]`` applied by :func:`cosy_lite.nets.pose_update.apply_pose_update`:

- ``delta[:, 0:6]``: 6D rotation residual, added to the identity 6D (rotation in the camera frame);
- ``delta[:, 6:8]``: ``(vx, vy)`` shift of the projected object centre [crop pixels];
- ``delta[:, 8]``: ``log vz`` (the depth is multiplied by ``vz``).

The head is a zero-initialised Linear, so an untrained network outputs the identity update.
Its outputs are multiplied by ``output_scale`` (rotation, xy, depth) so that every target is of
order 1 in head units: with Adam (per-parameter steps of ~lr) an unscaled head moves ``log vz``
(targets ~0.06) as fast as ``vx, vy`` (targets of several pixels), and the depth output drowns in
its own step noise (measured: no learning in 400 steps; with the scale, the xy loss halves in ~100).
Rendering and the refinement loop live outside this module.
"""

from __future__ import annotations

import torch
from torch import nn

from cosy_lite.nets.backbones import Backbone

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
N_OUT = 9  # 6D rotation + (vx, vy) + log vz
# Head units -> update units: 6D residual, pixel shift as a fraction of the crop width, log depth.
# Refiner: one unit ~ its training noise: 15 deg per axis, ~1 cm at ~0.8 m (~4% of the crop width
# with the 1.4 margin), 5 cm of ~0.8 m. Coarse: from a canonical rotation (6D residual entries up
# to 2) and a depth from the box size (tens of percent off).
OUTPUT_SCALES = {"refiner": (0.25, 0.04, 0.06), "coarse": (1.0, 0.1, 0.2)}
DEFAULT_OUTPUT_SCALE = OUTPUT_SCALES["refiner"]


def output_scale_vector(output_scale: tuple[float, float, float], crop_width: int) -> torch.Tensor:
    """``[1, 9]`` multipliers of the head outputs: (rotation x6, xy x2 in px, log depth)."""
    rot, xy, z = (float(v) for v in output_scale)
    return torch.tensor([[rot] * 6 + [xy * crop_width] * 2 + [z]], dtype=torch.float32)


def _per_channel(values: tuple[float, ...], n: int) -> torch.Tensor:
    """``values`` repeated over ``n`` channels (RGB, RGB, ...), shaped ``[1, n, 1, 1]``."""
    v = torch.tensor(values, dtype=torch.float32)
    return v.repeat((n + len(values) - 1) // len(values))[:n].view(1, n, 1, 1)


class PoseNet(nn.Module):
    """Backbone + zero-initialised linear head.

    Args:
        backbone: key of :data:`cosy_lite.nets.backbones.BACKBONES` (e.g. ``"resnet34"``).
        in_channels: input channels (6: image crop + rendered crop, each RGB).
        n_out: outputs of the head (9 for the update described in the module docstring).
        norm: ``"batch"`` or ``"group"`` normalisation in the backbone.
        output_scale: (rotation, xy as a fraction of the crop width, log depth) multipliers of the
            head (see the module docstring); ``crop_width`` [px] turns the xy fraction into pixels.
    """

    # buffers (register_buffer), declared for type checkers
    mean: torch.Tensor  # [1, in_channels, 1, 1] ImageNet mean, repeated over the channels
    std: torch.Tensor  # [1, in_channels, 1, 1]
    output_scale: torch.Tensor  # [1, n_out] head multipliers

    def __init__(self, backbone: str = "resnet34", in_channels: int = 6, n_out: int = N_OUT, norm: str = "batch",
                 output_scale: tuple[float, float, float] = DEFAULT_OUTPUT_SCALE, crop_width: int = 320):
        super().__init__()
        self.backbone = Backbone(backbone, in_channels, norm)
        self.in_channels = in_channels
        self.head = nn.Linear(self.backbone.out_features, n_out)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        self.register_buffer("mean", _per_channel(IMAGENET_MEAN, in_channels), persistent=False)
        self.register_buffer("std", _per_channel(IMAGENET_STD, in_channels), persistent=False)
        scale = output_scale_vector(output_scale, crop_width) if n_out == N_OUT else torch.ones(1, n_out)
        self.register_buffer("output_scale", scale, persistent=False)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """``images [B, in_channels, H, W]`` float in ``[0, 1]`` -> ``delta [B, n_out]``."""
        if images.ndim != 4 or images.shape[1] != self.in_channels:
            raise ValueError(f"PoseNet expects images [B,{self.in_channels},H,W], got {tuple(images.shape)}")
        x = (images - self.mean) / self.std
        return self.head(self.backbone(x)) * self.output_scale
