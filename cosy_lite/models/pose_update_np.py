"""The CosyPose image-space pose update in numpy: the onnxruntime path's twin of :mod:`.pose_update`.

Same convention (read :mod:`cosy_lite.models.pose_update`): ``delta [B,9]`` = 6D rotation residual
(``dR = rot6d_to_matrix(delta[:, :6] + IDENTITY_6D)``, ``R_new = dR R``), crop-pixel shift of the
projected origin ``delta[:, 6:8]``, log depth ratio ``delta[:, 8]``; a zero ``delta`` leaves the pose
unchanged bit for bit. Computed in float64 (``tests/test_numpy_geometry.py``: equal to the torch
functions to 1e-9 in float64). Imports numpy only.
"""

from __future__ import annotations

import numpy as np

POSE_DIM = 9
IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)  # as cosy_lite.geometry.rotations.IDENTITY_6D
NORMALIZE_EPS = 1e-12  # as torch.nn.functional.normalize


def _normalize(v: np.ndarray) -> np.ndarray:
    """``v [..., 3]`` / its norm, the norm clamped to >= :data:`NORMALIZE_EPS` (as ``F.normalize``)."""
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), NORMALIZE_EPS)


def rot6d_to_matrix(rot6d: np.ndarray) -> np.ndarray:
    """``[..., 6]`` -> ``[..., 3, 3]`` rotation: columns are the Gram-Schmidt of the two 3-vectors
    (as :func:`cosy_lite.geometry.rotations.rot6d_to_matrix`)."""
    x = _normalize(rot6d[..., 0:3])
    z = _normalize(np.cross(x, rot6d[..., 3:6]))
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def rotation_update(delta: np.ndarray) -> np.ndarray:
    """``dR [B,3,3]`` of the update ``delta [B,9]`` (exactly the identity for zeros)."""
    return rot6d_to_matrix(delta[:, :6] + np.asarray(IDENTITY_6D, dtype=delta.dtype))


def updated_translation(t: np.ndarray, K_crop: np.ndarray, vxvy: np.ndarray, vz: np.ndarray) -> np.ndarray:
    """``t_new [B,3]`` from ``t [B,3]`` (m), the crop-pixel shift ``vxvy [B,2]`` and depth ratio ``vz [B,1]``:
    ``z_new = vz z``, ``xy_new = xy vz + (v / f) z_new`` with ``f = (K_crop[0,0], K_crop[1,1])``."""
    f = np.stack([K_crop[:, 0, 0], K_crop[:, 1, 1]], axis=-1)
    z_new = vz * t[:, 2:3]
    return np.concatenate([t[:, :2] * vz + vxvy / f * z_new, z_new], axis=-1)


def apply_pose_update(TCO: np.ndarray, K_crop: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``TCO_new [B,4,4]`` float64: the pose ``TCO [B,4,4]`` (m) updated by the network output ``delta [B,9]``.

    ``K_crop [B,3,3]``: intrinsics of the crop the network saw. All inputs are cast to float64.
    """
    TCO, K_crop, delta = (np.asarray(a, dtype=np.float64) for a in (TCO, K_crop, delta))
    B = TCO.shape[0] if TCO.ndim == 3 else -1
    if TCO.shape != (B, 4, 4):
        raise ValueError(f"TCO must be [B,4,4], got {TCO.shape}")
    if K_crop.shape != (B, 3, 3):
        raise ValueError(f"K_crop must be [{B},3,3], got {K_crop.shape}")
    if delta.shape != (B, POSE_DIM):
        raise ValueError(f"delta must be [{B},{POSE_DIM}], got {delta.shape}")
    out = np.zeros_like(TCO)
    out[:, :3, :3] = rotation_update(delta) @ TCO[:, :3, :3]
    out[:, :3, 3] = updated_translation(TCO[:, :3, 3], K_crop, delta[:, 6:8], np.exp(delta[:, 8:9]))
    out[:, 3, 3] = 1.0
    return out
