"""One render-and-compare iteration, shared by training, inference and validation.

Per item: crop box from the current pose (projected model points, centred on the projected origin,
4:3, margin 1.4), the image crop (``roi_align``) and its ``K_crop``, the object rendered alone at
the current pose with ``K_crop``, the 6-channel input (crop, rendering) -> network -> update.
The network itself stays tensor in / tensor out (:class:`~cosy_lite.models.pose_net.PoseNet`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import torch
from torch import Tensor

from cosy_lite.geometry.crops import crop_boxes, crop_images, crop_intrinsics
from cosy_lite.models.pose_update import apply_pose_update
from cosy_lite.render.renderer import Renderer

Size = tuple[int, int]


@dataclass
class NetInputs:
    """images [B,6,h,w] float in [0,1] (image crop, rendering); K_crop [B,3,3]; boxes [B,4] xyxy px."""

    images: Tensor
    K_crop: Tensor
    boxes: Tensor


def make_inputs(images: Tensor, K: Tensor, TCO: Tensor, obj_ids: Sequence[int], points: Tensor,
                renderer: Renderer, crop_resolution: Size,
                crop_transform: Callable[[Tensor, Tensor], Tensor] | None = None) -> NetInputs:
    """Network inputs for objects at poses ``TCO [B,4,4]`` (m) in ``images [B,3,H,W]`` (float, [0,1]).

    ``K [B,3,3]`` full-image intrinsics; ``points [B,N,3]`` model points (m) that set the crop size.
    ``crop_transform(crops, boxes)`` (training augmentation) is applied to the image crops only.
    """
    TCO = TCO.detach()
    boxes = crop_boxes(TCO, K, points, crop_resolution=crop_resolution)
    crops = crop_images(images, boxes, crop_resolution)
    if crop_transform is not None:
        crops = crop_transform(crops, boxes)
    K_crop = crop_intrinsics(K, boxes, crop_resolution)
    rendered, _ = renderer.render_tensors([int(i) for i in obj_ids], TCO.double().cpu().numpy(),
                                          K_crop.double().cpu().numpy(), tuple(crop_resolution), device=images.device)
    return NetInputs(torch.cat([crops, rendered.to(crops.dtype)], dim=1), K_crop, boxes)


def iterate_poses(net: Callable[[Tensor], Tensor], images: Tensor, K: Tensor, TCO_init: Tensor, obj_ids: Sequence[int],
                  points: Tensor, renderer: Renderer, n_iterations: int, crop_resolution: Size,
                  batch_size: int = 32) -> list[Tensor]:
    """Run ``n_iterations`` render-and-compare updates from ``TCO_init [B,4,4]``; returns the poses
    after each iteration (``n_iterations`` tensors ``[B,4,4]``). ``net`` maps [b,6,h,w] -> [b,9]."""
    poses, TCO = [], TCO_init
    for _ in range(n_iterations):
        out = []
        for s in range(0, len(TCO), batch_size):
            sl = slice(s, s + batch_size)
            inp = make_inputs(images[sl], K[sl], TCO[sl], obj_ids[sl], points[sl], renderer, crop_resolution)
            delta = net(inp.images)
            out.append(apply_pose_update(TCO[sl], inp.K_crop, delta.to(TCO.dtype)))
        TCO = torch.cat(out) if out else TCO
        poses.append(TCO)
    return poses
