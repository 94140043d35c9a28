"""Camera poses and intrinsics for synthetic scenes, sampled as BlenderProc4BOP does.

Each view looks at one of the objects nearest the centre of the pile from a point on a spherical
shell around it (uniform over the shell's area within the elevation band, radius uniform), then
rolls the camera by a random angle about its optical axis. World frame: z up, floor at z = 0,
metres; poses are ``T_CW`` (world-to-camera, OpenCV camera: x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cosy_lite.geometry.transforms import look_at, make_T, rotation_about_axis

# YCB-V test camera ("uw"): fx, fy, cx, cy in pixels, image width and height.
YCBV_CAMERA = {"fx": 1066.778, "fy": 1067.487, "cx": 312.9869, "cy": 241.3109, "width": 640, "height": 480}


@dataclass
class CameraConfig:
    """Ranges sampled uniformly per view (metres, radians)."""

    distance: tuple[float, float] = (0.5, 1.2)  # camera to look-at point, as in YCB-V
    elevation: tuple[float, float] = (0.35, 1.4)  # above the floor plane, about 20..80 degrees
    azimuth: tuple[float, float] = (0.0, 2 * np.pi)
    inplane: tuple[float, float] = (-np.pi, np.pi)  # roll about the optical axis
    lookat_jitter: float = 0.02  # the look-at point moves up to this far per axis from the object
    n_central: int = 3  # look at one of the objects nearest (in xy) the pile centroid


def ycbv_intrinsics() -> tuple[np.ndarray, tuple[int, int]]:
    """YCB-V "uw" camera: ``K`` [3,3] (pixels) and ``(width, height)``."""
    c = YCBV_CAMERA
    K = np.array([[c["fx"], 0.0, c["cx"]], [0.0, c["fy"], c["cy"]], [0.0, 0.0, 1.0]])
    return K, (int(c["width"]), int(c["height"]))


def central_objects(object_positions_W: np.ndarray, n: int) -> np.ndarray:
    """Indices of the ``n`` positions [N,3] nearest (in xy) their centroid, nearest first."""
    p = np.asarray(object_positions_W, dtype=np.float64)
    d = np.linalg.norm(p[:, :2] - p[:, :2].mean(axis=0), axis=1)
    return np.argsort(d, kind="stable")[: max(1, min(n, len(p)))]


def sample_camera_poses(
    object_positions_W: np.ndarray, n_views: int, rng: np.random.Generator, cfg: CameraConfig
) -> list[np.ndarray]:
    """``n_views`` world-to-camera poses T_CW [4,4], each looking at one of the central objects.

    ``object_positions_W`` [N,3] (metres, N >= 1). Deterministic for a given rng state.
    """
    p = np.asarray(object_positions_W, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"object_positions_W must be [N>=1,3], got {p.shape}")
    if n_views < 0:
        raise ValueError(f"n_views must be >= 0, got {n_views}")
    lo, hi = np.sin(cfg.elevation[0]), np.sin(cfg.elevation[1])
    if not (0.0 < lo <= hi):
        raise ValueError(f"elevation range {cfg.elevation} must lie in (0, pi/2]: the camera stays above the floor")
    candidates = central_objects(p, cfg.n_central)
    poses = []
    for _ in range(n_views):
        target = p[rng.choice(candidates)] + rng.uniform(-cfg.lookat_jitter, cfg.lookat_jitter, size=3)
        elevation = np.arcsin(rng.uniform(lo, hi))  # uniform over the shell's area
        azimuth = rng.uniform(*cfg.azimuth)
        distance = rng.uniform(*cfg.distance)
        direction = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
        T_CW = look_at(target + distance * direction, target)
        roll = make_T(rotation_about_axis(np.array([0.0, 0.0, 1.0]), rng.uniform(*cfg.inplane)), np.zeros(3))
        poses.append(roll @ T_CW)
    return poses
