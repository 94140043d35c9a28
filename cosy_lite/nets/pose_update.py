"""The CosyPose image-space pose update: how the pose network's 9 outputs change a pose (torch).

``delta [B,9]`` (the network output, zero = no change):

* ``delta[:, :6]``: 6D rotation residual; ``dR = rot6d_to_matrix(delta[:, :6] + IDENTITY_6D)`` is
  applied in the camera frame, ``R_new = dR @ R`` (rotation about the object origin).
* ``delta[:, 6:8] = (vx, vy)``: shift of the projected object origin in crop pixels.
* ``delta[:, 8]``: log depth ratio, ``vz = exp(delta[:, 8])``, ``z_new = vz z``.
* ``xy_new = (v_xy / f_xy + xy / z) z_new`` with ``f_xy`` the crop focal lengths ``K_crop[0,0]``,
  ``K_crop[1,1]``.

CosyPose (``cosypose_ops.apply_imagespace_predictions``) uses the raw outputs as the 6D rotation
and as ``vz``; the identity offset and ``exp`` here make a zero output the identity update and
keep ``vz > 0``.
"""

from __future__ import annotations

import functools
from typing import Callable, TypeVar

import torch
from torch import Tensor

from cosy_lite.geometry.rotations import IDENTITY_6D, matrix_to_rot6d, rot6d_to_matrix

POSE_DIM = 9

F = TypeVar("F", bound=Callable)


def full_precision(fn: F) -> F:
    """Run ``fn`` with autocast off (CPU and CUDA): poses and point distances stay in the dtype of
    the poses, never bf16/fp16 (bf16 keeps ~3 significant digits: 2 mm of a 0.5 m translation)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with torch.autocast("cuda", enabled=False), torch.autocast("cpu", enabled=False):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


def _check_inputs(TCO: Tensor, K_crop: Tensor, delta: Tensor | None = None) -> None:
    B = TCO.shape[0] if TCO.dim() == 3 else -1
    if TCO.shape[1:] != (4, 4) or TCO.dim() != 3:
        raise ValueError(f"TCO must be [B,4,4], got {tuple(TCO.shape)}")
    if K_crop.shape != (B, 3, 3):
        raise ValueError(f"K_crop must be [{B},3,3], got {tuple(K_crop.shape)}")
    if delta is not None and delta.shape != (B, POSE_DIM):
        raise ValueError(f"delta must be [{B},{POSE_DIM}], got {tuple(delta.shape)}")


def _compose(R: Tensor, t: Tensor) -> Tensor:
    """[B,3,3] + [B,3] -> [B,4,4] without in-place writes (autograd-friendly)."""
    top = torch.cat([R, t[:, :, None]], dim=2)
    bottom = torch.zeros_like(top[:, :1])
    bottom[:, 0, 3] = 1.0
    return torch.cat([top, bottom], dim=1)


def rotation_update(delta: Tensor) -> Tensor:
    """``dR [B,3,3]`` of the update ``delta [B,9]`` (exactly the identity for zeros)."""
    identity = torch.tensor(IDENTITY_6D, dtype=delta.dtype, device=delta.device)
    return rot6d_to_matrix(delta[:, :6] + identity)


def updated_translation(t: Tensor, K_crop: Tensor, vxvy: Tensor, vz: Tensor) -> Tensor:
    """``t_new [B,3]`` from ``t [B,3]`` (m), the pixel shift ``vxvy [B,2]`` and depth ratio ``vz [B,1]``.

    Written as ``xy vz + (v / f) z_new`` (= CosyPose's ``(v / f + xy / z) z_new``) so that
    ``vxvy = 0, vz = 1`` returns ``t`` bit for bit.
    """
    f = torch.stack([K_crop[:, 0, 0], K_crop[:, 1, 1]], dim=-1)
    z_new = vz * t[:, 2:3]
    xy_new = t[:, :2] * vz + vxvy / f * z_new
    return torch.cat([xy_new, z_new], dim=-1)


@full_precision
def apply_pose_update(TCO: Tensor, K_crop: Tensor, delta: Tensor) -> Tensor:
    """``TCO_new [B,4,4]`` = the pose ``TCO [B,4,4]`` (m) updated by the network output ``delta [B,9]``.

    ``K_crop [B,3,3]``: intrinsics of the crop the network saw (pixel shifts are crop pixels).
    Differentiable in ``delta``; a zero ``delta`` returns ``TCO`` unchanged. Computed in TCO's
    dtype (``delta`` is cast to it) with autocast off.
    """
    _check_inputs(TCO, K_crop, delta)
    delta, K_crop = delta.to(TCO.dtype), K_crop.to(TCO.dtype)
    dR = rotation_update(delta)
    R_new = dR @ TCO[:, :3, :3]
    t_new = updated_translation(TCO[:, :3, 3], K_crop, delta[:, 6:8], torch.exp(delta[:, 8:9]))
    return _compose(R_new, t_new)


@full_precision
def pose_update_targets(TCO_in: Tensor, TCO_gt: Tensor, K_crop: Tensor) -> Tensor:
    """The ``delta* [B,9]`` with ``apply_pose_update(TCO_in, K_crop, delta*) == TCO_gt`` (to rounding).

    ``dR = R_gt R_in^T``, ``vz = z_gt / z_in``, ``v = f (xy_gt / z_gt - xy_in / z_in)``.
    """
    _check_inputs(TCO_in, K_crop)
    if TCO_gt.shape != TCO_in.shape:
        raise ValueError(f"TCO_gt must be {tuple(TCO_in.shape)} like TCO_in, got {tuple(TCO_gt.shape)}")
    TCO_gt, K_crop = TCO_gt.to(TCO_in.dtype), K_crop.to(TCO_in.dtype)
    dR = TCO_gt[:, :3, :3] @ TCO_in[:, :3, :3].transpose(1, 2)
    identity = torch.tensor(IDENTITY_6D, dtype=TCO_in.dtype, device=TCO_in.device)
    t_in, t_gt = TCO_in[:, :3, 3], TCO_gt[:, :3, 3]
    f = torch.stack([K_crop[:, 0, 0], K_crop[:, 1, 1]], dim=-1)
    vxvy = f * (t_gt[:, :2] / t_gt[:, 2:3] - t_in[:, :2] / t_in[:, 2:3])
    log_vz = torch.log(t_gt[:, 2:3] / t_in[:, 2:3])
    return torch.cat([matrix_to_rot6d(dR) - identity, vxvy, log_vz], dim=-1)
