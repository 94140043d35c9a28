"""The pose network shared by the coarse model and the refiner: tensor in, tensor out.

Input: the image crop and the rendered crop stacked on channels, ``[B, 6, H, W]`` in ``[0, 1]``
(normalised inside, so ONNX users feed plain ``[0, 1]`` images). Output: the pose update
``delta [B, 9]`` applied by :func:`cosy_lite.models.pose_update.apply_pose_update`:

- ``delta[:, 0:6]``: 6D rotation residual, added to the identity 6D (rotation in the camera frame);
- ``delta[:, 6:8]``: ``(vx, vy)`` shift of the projected object centre [crop pixels];
- ``delta[:, 8]``: ``log vz`` (the depth is multiplied by ``vz``).

The head is a zero-initialised Linear, so an untrained network outputs the identity update.
Rendering and the refinement loop live outside this module.
"""

from __future__ import annotations

import torch
from torch import nn

from cosy_lite.models.backbones import Backbone

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
N_OUT = 9  # 6D rotation + (vx, vy) + log vz


def _per_channel(values: tuple[float, ...], n: int) -> torch.Tensor:
    """``values`` repeated over ``n`` channels (RGB, RGB, ...), shaped ``[1, n, 1, 1]``."""
    v = torch.tensor(values, dtype=torch.float32)
    return v.repeat((n + len(values) - 1) // len(values))[:n].view(1, n, 1, 1)


class PoseNet(nn.Module):
    """Backbone + zero-initialised linear head.

    Args:
        backbone: key of :data:`cosy_lite.models.backbones.BACKBONES` (e.g. ``"resnet34"``).
        in_channels: input channels (6: image crop + rendered crop, each RGB).
        n_out: outputs of the head (9 for the update described in the module docstring).
        norm: ``"batch"`` or ``"group"`` normalisation in the backbone.
    """

    def __init__(self, backbone: str = "resnet34", in_channels: int = 6, n_out: int = N_OUT, norm: str = "batch"):
        super().__init__()
        self.backbone = Backbone(backbone, in_channels, norm)
        self.in_channels = in_channels
        self.head = nn.Linear(self.backbone.out_features, n_out)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        self.register_buffer("mean", _per_channel(IMAGENET_MEAN, in_channels), persistent=False)
        self.register_buffer("std", _per_channel(IMAGENET_STD, in_channels), persistent=False)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """``images [B, in_channels, H, W]`` float in ``[0, 1]`` -> ``delta [B, n_out]``."""
        if images.ndim != 4 or images.shape[1] != self.in_channels:
            raise ValueError(f"PoseNet expects images [B,{self.in_channels},H,W], got {tuple(images.shape)}")
        x = (images - self.mean) / self.std
        return self.head(self.backbone(x))
