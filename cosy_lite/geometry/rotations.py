"""Rotation representations (torch, batched).

The 6D representation (Zhou et al., CVPR 2019) is the first two columns of the rotation matrix,
``[r11, r21, r31, r12, r22, r32]``; :func:`rot6d_to_matrix` turns any 6 numbers into a rotation by
Gram-Schmidt. Quaternions are ``(w, x, y, z)`` and go through kornia.
"""

from __future__ import annotations

import math

import kornia.geometry.conversions as kc
import torch
import torch.nn.functional as F

IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


def rot6d_to_matrix(rot6d: torch.Tensor) -> torch.Tensor:
    """``[..., 6]`` -> ``[..., 3, 3]`` rotation; columns are the Gram-Schmidt of the two 3-vectors."""
    a1, a2 = rot6d[..., 0:3], rot6d[..., 3:6]
    x = F.normalize(a1, dim=-1)
    z = F.normalize(torch.cross(x, a2, dim=-1), dim=-1)
    y = torch.cross(z, x, dim=-1)
    return torch.stack([x, y, z], dim=-1)


def matrix_to_rot6d(R: torch.Tensor) -> torch.Tensor:
    """``[..., 3, 3]`` -> ``[..., 6]``: the first two columns, column after column."""
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)


def quaternion_to_matrix(q_wxyz: torch.Tensor) -> torch.Tensor:
    """``[..., 4]`` quaternion ``(w, x, y, z)`` (normalised here) -> ``[..., 3, 3]``."""
    return kc.quaternion_to_rotation_matrix(F.normalize(q_wxyz, dim=-1))


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """``[B, 3]`` rotation vectors (radians) -> ``[B, 3, 3]``."""
    return kc.axis_angle_to_rotation_matrix(axis_angle)


def euler_xyz_to_matrix(angles: torch.Tensor) -> torch.Tensor:
    """``[B, 3]`` angles (radians) about x then y then z (extrinsic) -> ``[B, 3, 3]`` = Rz @ Ry @ Rx."""
    cx, cy, cz = torch.cos(angles).unbind(-1)
    sx, sy, sz = torch.sin(angles).unbind(-1)
    one, zero = torch.ones_like(cx), torch.zeros_like(cx)
    Rx = torch.stack([one, zero, zero, zero, cx, -sx, zero, sx, cx], -1).view(-1, 3, 3)
    Ry = torch.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], -1).view(-1, 3, 3)
    Rz = torch.stack([cz, -sz, zero, sz, cz, zero, zero, zero, one], -1).view(-1, 3, 3)
    return Rz @ Ry @ Rx


def rotation_angle_deg(R_a: torch.Tensor, R_b: torch.Tensor) -> torch.Tensor:
    """Geodesic angle (degrees) between ``[..., 3, 3]`` rotations."""
    trace = (R_a.transpose(-1, -2) @ R_b).diagonal(dim1=-2, dim2=-1).sum(-1)
    return torch.rad2deg(torch.acos(((trace - 1) / 2).clamp(-1.0, 1.0)))


def random_rotations(n: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """``[n, 3, 3]`` rotations uniform on SO(3) (normalised Gaussian quaternions)."""
    q = torch.randn(n, 4, generator=generator, dtype=torch.float64)
    return quaternion_to_matrix(q)


DEG = math.pi / 180.0
