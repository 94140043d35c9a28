"""Rigid transforms and pinhole projection (numpy, float64, metres).

Conventions: ``T_AB`` maps points from frame B to frame A (``x_A = T_AB @ x_B``); ``TCO`` is
object-to-camera (OpenCV camera: x right, y down, z forward); ``K`` is the 3x3 intrinsic matrix.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """[3,3] rotation + [3] translation -> [4,4] homogeneous transform."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t).reshape(3)
    return T


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid [...,4,4] transform."""
    R = T[..., :3, :3]
    t = T[..., :3, 3:]
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3:] = -Rt @ t
    Ti[..., 3, 3] = 1.0
    return Ti


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a [4,4] transform to points [N,3]."""
    return pts @ T[:3, :3].T + T[:3, 3]


def project_points(pts_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Project camera-frame points [N,3] (z > 0) to pixel coordinates [N,2] (u right, v down)."""
    z = pts_cam[:, 2:3]
    uv = (pts_cam @ K.T)[:, :2] / z
    return uv


def rotation_about_axis(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: [3,3] rotation by ``angle`` (radians) about unit ``axis``."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * (Kx @ Kx)


def look_at(eye: np.ndarray, target: np.ndarray, up: npt.ArrayLike = (0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera transform ``T_CW`` (OpenCV camera) for a camera at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-8:  # looking straight along `up`: any x orthogonal to z
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_WC = np.stack([x, y, z], axis=1)
    return invert_T(make_T(R_WC, eye))


def is_rotation(R: np.ndarray, atol: float = 1e-4) -> bool:
    """True if R is orthonormal with determinant +1 (within ``atol``)."""
    R = np.asarray(R, dtype=np.float64)
    return (
        R.shape == (3, 3)
        and bool(np.all(np.isfinite(R)))
        and np.allclose(R @ R.T, np.eye(3), atol=atol)
        and abs(np.linalg.det(R) - 1.0) < atol
    )
