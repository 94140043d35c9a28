"""Initial poses: the coarse model's starting pose from a 2D box, and GT + noise for the refiner.

Depth from a box. An object of diameter ``d`` at depth ``z`` spans at most ``f d / z`` pixels in
any image direction, and typically a bit less. The estimate is

    ``z = min(fx s / w, fy s / h)``,  ``s = EXTENT_PER_DIAMETER * d``

(the larger side of the box, with its own focal length, measured against a typical extent ``s``).
``EXTENT_PER_DIAMETER = 0.92`` is the median of ``max(w, h) z / (f d)`` over the 21 YCB-V models of
``cosy_lite.synth.objects`` seen from 500 uniformly random rotations each. Share of estimates within
20% of the true depth: 85% over those views; 91% (median ratio 0.985) for the full-object boxes
(``bbox_obj``) of the 8896 train_pbr instances of the default synthetic dataset (objects resting
on a table); 88% for YCB-like boxes and cylinders seen from 20-80 deg elevation (the test). The
misses are objects that look smaller than usual, so their depth is overestimated: thin objects
seen end-on (banana, marker, scissors), tall boxes seen from above. Boxes of the *visible* part
(a detector's) shrink with occlusion: 57% within 20%, median ratio 1.14, 95th percentile 2.9
(same dataset, visib_fract >= 0.1); the coarse model has to correct that.
(Per-object ratios, the median over uniform rotations of each model, raise 85% to 89% for uniform
rotations but not for table views, so one global ratio is kept.) CosyPose's paper setting used a
fixed ``z = 1 m`` (53% within 20% on the same bbox_obj boxes); its BOP 2020 version
(``TCO_init_from_boxes_zup_autodepth``) fits the model's extent at the canonical rotation, which
fails whenever the true rotation differs (40%, median ratio 0.78).

x, y: the box centre back-projected at that depth. Rotation: one of :data:`CANONICAL_ROTATIONS`.
Boxes are ``[x1, y1, x2, y2]`` in image coordinates (pixel ``i`` covers ``[i, i+1)``; see
:mod:`cosy_lite.geometry.crops`).
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from cosy_lite.geometry.rotations import euler_xyz_to_matrix

EXTENT_PER_DIAMETER = 0.92

# Canonical object-to-camera rotations for the coarse model's starting pose.
CANONICAL_ROTATIONS: dict[str, Tensor] = {
    "identity": torch.eye(3, dtype=torch.float64),
    # CosyPose BOP 2020: object z up in the image (-y camera), object x towards the camera (-z),
    # object y to the right (+x): a z-up object seen from the side, upright.
    "z_up": torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]], dtype=torch.float64),
}

# CosyPose's refiner training noise (training/pose_forward_loss.py, input_generator='gt+noise'):
# Euler angles ~ N(0, 15 deg) per axis, translation ~ N(0, (1 cm, 1 cm, 5 cm)).
ROT_STD_DEG = 15.0
TRANS_STD = (0.01, 0.01, 0.05)


def _rigid(R: Tensor, t: Tensor) -> Tensor:
    T = torch.zeros(t.shape[0], 4, 4, dtype=t.dtype, device=t.device)
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    return T


def initial_pose_from_boxes(
    boxes: Tensor,
    K: Tensor,
    diameters: Tensor,
    rotation: str = "z_up",
    extent_per_diameter: float | Tensor = EXTENT_PER_DIAMETER,
) -> Tensor:
    """``TCO [B,4,4]`` (m) starting poses for objects seen in ``boxes [B,4]`` (image coordinates).

    ``K [B,3,3]``; ``diameters [B]`` (m): model diameters; ``rotation``: a key of
    :data:`CANONICAL_ROTATIONS`. Depth ``min(fx s / w, fy s / h)`` with ``s = extent_per_diameter * d``;
    ``extent_per_diameter``: one number, or ``[B]`` (e.g. per-object ratios calibrated on a dataset).
    """
    B = boxes.shape[0]
    if boxes.shape != (B, 4) or K.shape != (B, 3, 3) or diameters.shape != (B,):
        raise ValueError(
            "boxes [B,4], K [B,3,3] and diameters [B] expected, got "
            f"{tuple(boxes.shape)}, {tuple(K.shape)}, {tuple(diameters.shape)}"
        )
    if rotation not in CANONICAL_ROTATIONS:
        raise ValueError(f"rotation must be one of {sorted(CANONICAL_ROTATIONS)}, got {rotation!r}")
    boxes = boxes.to(K.dtype)
    f = torch.stack([K[:, 0, 0], K[:, 1, 1]], dim=-1)
    c = K[:, :2, 2]
    size = (boxes[:, 2:] - boxes[:, :2]).clamp(min=1.0)  # px; a degenerate box counts as 1 px
    ratio = torch.as_tensor(extent_per_diameter, dtype=K.dtype, device=K.device)
    extent = ratio * diameters.to(K.dtype)
    z = (f * extent[:, None] / size).amin(dim=-1, keepdim=True)  # [B,1]
    centre = (boxes[:, :2] + boxes[:, 2:]) / 2
    xy = (centre - c) / f * z
    R = CANONICAL_ROTATIONS[rotation].to(dtype=K.dtype, device=K.device).expand(B, 3, 3)
    return _rigid(R, torch.cat([xy, z], dim=-1))


def _per_axis(x: float | Sequence[float], name: str) -> tuple[float, float, float]:
    v = (float(x),) * 3 if isinstance(x, (int, float)) else tuple(float(a) for a in x)
    if len(v) != 3 or any(a < 0 for a in v):
        raise ValueError(f"{name} must be a non-negative number or 3 of them, got {x!r}")
    return v


def _rotate_camera(R: Tensor, noise: Tensor) -> Tensor:
    return noise @ R


def _rotate_object(R: Tensor, noise: Tensor) -> Tensor:
    return R @ noise


NOISE_FRAMES = {
    "camera": _rotate_camera,  # R' = N R: rotation about the object origin, axes of the camera
    "object": _rotate_object,  # R' = R N: axes of the object (CosyPose's add_noise)
}


def add_pose_noise(
    TCO_gt: Tensor,
    rot_std_deg: float | Sequence[float] = ROT_STD_DEG,
    trans_std: float | Sequence[float] = TRANS_STD,
    generator: torch.Generator | None = None,
    frame: str = "camera",
    scale: Tensor | None = None,
) -> Tensor:
    """``TCO_gt [B,4,4]`` (m) perturbed for refiner training.

    Rotation: Euler angles ~ N(0, ``rot_std_deg``) degrees about x, y, z (``Rz Ry Rx``, as
    transforms3d's ``euler2mat`` in CosyPose), applied in ``frame`` (a key of :data:`NOISE_FRAMES`;
    the object origin stays put). Translation: ``+ N(0, trans_std)`` metres per camera axis.
    ``scale [B]`` (optional) multiplies each item's noise (its angles and its translation).
    Random numbers come from ``generator`` (CPU) in float64, so a seed gives the same noise on any device.
    """
    if TCO_gt.dim() != 3 or TCO_gt.shape[1:] != (4, 4):
        raise ValueError(f"TCO_gt must be [B,4,4], got {tuple(TCO_gt.shape)}")
    if frame not in NOISE_FRAMES:
        raise ValueError(f"frame must be one of {sorted(NOISE_FRAMES)}, got {frame!r}")
    B = TCO_gt.shape[0]
    rot_std = torch.tensor(_per_axis(rot_std_deg, "rot_std_deg"), dtype=torch.float64) * (math.pi / 180.0)
    t_std = torch.tensor(_per_axis(trans_std, "trans_std"), dtype=torch.float64)
    eps = torch.randn(B, 6, generator=generator, dtype=torch.float64)
    if scale is not None:
        if scale.shape != (B,):
            raise ValueError(f"scale must be [{B}], got {tuple(scale.shape)}")
        eps = eps * scale.to(torch.float64).cpu()[:, None]
    noise_R = euler_xyz_to_matrix(eps[:, :3] * rot_std).to(TCO_gt)
    noise_t = (eps[:, 3:] * t_std).to(TCO_gt)
    R = NOISE_FRAMES[frame](TCO_gt[:, :3, :3], noise_R)
    return _rigid(R, TCO_gt[:, :3, 3] + noise_t)
