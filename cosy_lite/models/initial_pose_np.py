"""The coarse model's starting pose from a 2D box, in numpy: the onnxruntime path's twin of
:func:`cosy_lite.models.initial_pose.initial_pose_from_boxes` (read its module docstring for the
depth rule ``z = min(fx s / w, fy s / h)``, ``s = EXTENT_PER_DIAMETER * d``, and the canonical
rotations). The constants equal the torch module's (``tests/test_numpy_geometry.py`` checks);
this module imports numpy only.
"""

from __future__ import annotations

import numpy as np

EXTENT_PER_DIAMETER = 0.92  # as initial_pose.EXTENT_PER_DIAMETER

# as initial_pose.CANONICAL_ROTATIONS (object-to-camera rotations)
CANONICAL_ROTATIONS: dict[str, np.ndarray] = {
    "identity": np.eye(3),
    "z_up": np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]]),  # z up in the image, x to the camera
}


def initial_pose_from_boxes(boxes: np.ndarray, K: np.ndarray, diameters: np.ndarray, rotation: str = "z_up",
                            extent_per_diameter: float | np.ndarray = EXTENT_PER_DIAMETER) -> np.ndarray:
    """``TCO [B,4,4]`` float64 (m) starting poses of objects seen in ``boxes [B,4]`` (x1, y1, x2, y2 px).

    ``K [B,3,3]``; ``diameters [B]`` (m); ``rotation``: a key of :data:`CANONICAL_ROTATIONS`;
    ``extent_per_diameter``: one number or ``[B]``. A box side below 1 px counts as 1 px.
    """
    boxes, K, diameters = (np.asarray(a, dtype=np.float64) for a in (boxes, K, diameters))
    B = boxes.shape[0] if boxes.ndim == 2 else -1
    if boxes.shape != (B, 4) or K.shape != (B, 3, 3) or diameters.shape != (B,):
        raise ValueError(f"boxes [B,4], K [B,3,3] and diameters [B] expected, got {boxes.shape}, {K.shape}, "
                         f"{diameters.shape}")
    if rotation not in CANONICAL_ROTATIONS:
        raise ValueError(f"rotation must be one of {sorted(CANONICAL_ROTATIONS)}, got {rotation!r}")
    f = np.stack([K[:, 0, 0], K[:, 1, 1]], axis=-1)
    size = np.maximum(boxes[:, 2:] - boxes[:, :2], 1.0)
    extent = np.asarray(extent_per_diameter, dtype=np.float64) * diameters
    z = (f * extent[:, None] / size).min(axis=-1, keepdims=True)  # [B,1]
    xy = ((boxes[:, :2] + boxes[:, 2:]) / 2 - K[:, :2, 2]) / f * z
    TCO = np.zeros((B, 4, 4))
    TCO[:, :3, :3] = CANONICAL_ROTATIONS[rotation]
    TCO[:, :3, 3] = np.concatenate([xy, z], axis=-1)
    TCO[:, 3, 3] = 1.0
    return TCO
