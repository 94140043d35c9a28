"""pyrender plumbing shared by every renderer: EGL set-up, OpenCV <-> OpenGL camera frames.

Pixel convention: pyrender's ``IntrinsicsCamera`` (like the BOP toolkit's renderer) maps a point
with OpenCV projection ``u = fx x/z + cx`` to window coordinate ``u``; pixel ``i`` covers
``[i, i+1)``. Masks and depth maps are therefore comparable with those of the BOP toolkit.
"""

from __future__ import annotations

import os

import numpy as np

# OpenCV camera (x right, y down, z forward) -> OpenGL camera (x right, y up, z backward).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def use_egl() -> None:
    """Select headless EGL for PyOpenGL unless the user chose a platform. Call before importing pyrender."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def pyrender_module():
    """Import pyrender with EGL selected (lazy: nothing happens at import of cosy_lite)."""
    use_egl()
    import pyrender

    return pyrender


def camera_node_pose(T_CW: np.ndarray) -> np.ndarray:
    """pyrender camera node pose (camera-to-world, OpenGL axes) from an OpenCV world-to-camera transform."""
    return np.linalg.inv(T_CW) @ CV_TO_GL


def intrinsics_camera(K: np.ndarray, znear: float = 0.01, zfar: float = 20.0):
    pyrender = pyrender_module()
    return pyrender.IntrinsicsCamera(
        fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]), znear=znear, zfar=zfar
    )
