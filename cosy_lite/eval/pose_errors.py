"""Pose errors of the BOP Challenge (VSD, MSSD, MSPD) and the classic ADD / ADI, in metres: the definitions.

Semantics follow bop_toolkit ``pose_error.py`` and ``eval_calc_errors.py`` (BOP 2019-2020 paper,
Sec. 2): poses are object-to-camera ``TCO`` [4,4] (t in m), model points are ``models_eval``
vertices [N,3] in m, a symmetry ``S`` [4,4] maps model coordinates to model coordinates.
These functions are written as the toolkit's loops and serve as the reference;
:mod:`cosy_lite.eval.object_errors` computes the same values much faster for the evaluator.
"""

from __future__ import annotations

import numpy as np

SYM_CHUNK_POINTS = 2_000_000  # symmetries x points evaluated at once (memory bound)


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply rigid transforms [...,4,4] to points [N,3] -> [...,N,3]."""
    T = np.asarray(T, dtype=np.float64)
    return pts @ np.swapaxes(T[..., :3, :3], -1, -2) + T[..., None, :3, 3]


def project_points(pts_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection of camera-frame points [...,N,3] with ``K`` [3,3] -> pixels [...,N,2]."""
    K = np.asarray(K, dtype=np.float64)
    uvw = pts_cam @ K.T
    return uvw[..., :2] / uvw[..., 2:3]


def _check_pose(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"{name} must be [4,4], got {T.shape}")
    return T


def _check_points(pts: np.ndarray) -> np.ndarray:
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"pts must be [N,3] with N > 0, got {pts.shape}")
    return pts


def _check_syms(syms: np.ndarray) -> np.ndarray:
    syms = np.asarray(syms, dtype=np.float64)
    if syms.ndim != 3 or syms.shape[1:] != (4, 4) or len(syms) == 0:
        raise ValueError(f"syms must be [S,4,4] with S > 0 (identity included), got {syms.shape}")
    return syms


def _max_sq_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """max over the point axis of squared distances: a [...,N,D], b [...,N,D] -> [...]."""
    d = a - b
    return np.einsum("...nd,...nd->...n", d, d).max(axis=-1)


def mssd_mspd(
    TCO_est: np.ndarray, TCO_gt: np.ndarray, K: np.ndarray, pts: np.ndarray, syms: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """MSSD [m] and MSPD [px] of E estimates against one GT pose, sharing the symmetric GT points.

    Args:
        TCO_est: [E,4,4]; TCO_gt: [4,4]; K: [3,3]; pts: [N,3] model points (m); syms: [S,4,4].
    Returns:
        mssd [E] = min_S max_v ||TCO_est v - TCO_gt S v||, mspd [E] the same on projections (px).
    """
    TCO_est = np.asarray(TCO_est, dtype=np.float64).reshape(-1, 4, 4)
    TCO_gt = _check_pose(TCO_gt, "TCO_gt")
    pts, syms = _check_points(pts), _check_syms(syms)
    pts_est = transform_points(TCO_est, pts)[:, None]  # [E,1,N,3]
    uv_est = project_points(pts_est, K)  # [E,1,N,2]
    chunk = max(1, SYM_CHUNK_POINTS // (len(pts) * max(1, len(TCO_est))))
    best_3d = np.full(len(TCO_est), np.inf)
    best_2d = np.full(len(TCO_est), np.inf)
    for i in range(0, len(syms), chunk):
        pts_gt = transform_points(TCO_gt @ syms[i:i + chunk], pts)  # [s,N,3]
        best_3d = np.minimum(best_3d, _max_sq_dist(pts_est, pts_gt[None]).min(axis=1))
        best_2d = np.minimum(best_2d, _max_sq_dist(uv_est, project_points(pts_gt, K)[None]).min(axis=1))
    return np.sqrt(best_3d), np.sqrt(best_2d)


def mssd(TCO_est: np.ndarray, TCO_gt: np.ndarray, pts: np.ndarray, syms: np.ndarray) -> float:
    """Maximum Symmetry-aware Surface Distance [m].

    ``min_S max_v ||TCO_est v - TCO_gt S v||`` over symmetries ``syms`` [S,4,4] and points ``pts`` [N,3].
    """
    TCO_est = _check_pose(TCO_est, "TCO_est")
    with np.errstate(divide="ignore", invalid="ignore"):  # the unused projection may divide by z = 0
        return float(mssd_mspd(TCO_est, TCO_gt, np.eye(3), pts, syms)[0][0])


def mspd(TCO_est: np.ndarray, TCO_gt: np.ndarray, K: np.ndarray, pts: np.ndarray, syms: np.ndarray) -> float:
    """Maximum Symmetry-aware Projection Distance [px].

    ``min_S max_v ||proj(TCO_est v) - proj(TCO_gt S v)||`` with intrinsics ``K`` [3,3].
    """
    TCO_est = _check_pose(TCO_est, "TCO_est")
    return float(mssd_mspd(TCO_est, TCO_gt, K, pts, syms)[1][0])


def add(TCO_est: np.ndarray, TCO_gt: np.ndarray, pts: np.ndarray) -> float:
    """Average Distance of model points (ADD) [m]: ``mean_v ||TCO_est v - TCO_gt v||``."""
    pts = _check_points(pts)
    d = transform_points(_check_pose(TCO_est, "TCO_est"), pts) - transform_points(_check_pose(TCO_gt, "TCO_gt"), pts)
    return float(np.linalg.norm(d, axis=1).mean())


def adi(TCO_est: np.ndarray, TCO_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADD-S / ADI [m]: mean over GT-posed points of the distance to the nearest estimated-posed point (cKDTree)."""
    from scipy.spatial import cKDTree

    pts = _check_points(pts)
    pts_est = transform_points(_check_pose(TCO_est, "TCO_est"), pts)
    pts_gt = transform_points(_check_pose(TCO_gt, "TCO_gt"), pts)
    dist, _ = cKDTree(pts_est).query(pts_gt, k=1)
    return float(dist.mean())


def sphere_projections_overlap(radius: float, t_est: np.ndarray, t_gt: np.ndarray) -> bool:
    """Whether the image projections of spheres of ``radius`` at centres ``t_est``, ``t_gt`` [3] (m) may overlap.

    The toolkit's approximate test (``misc.overlapping_sphere_projections``): False if a centre
    has z = 0, else ``|p_e - p_g| < radius (1/z_e + 1/z_g)`` with ``p = (x/z, y/z)``. Where it is
    False the toolkit sets VSD to 1 for every tau without rendering.
    """
    t_est, t_gt = np.asarray(t_est, dtype=np.float64), np.asarray(t_gt, dtype=np.float64)
    if t_est[2] == 0 or t_gt[2] == 0:
        return False
    dist = np.linalg.norm(t_est[:2] / t_est[2] - t_gt[:2] / t_gt[2])
    return bool(dist < radius * (1.0 / t_est[2] + 1.0 / t_gt[2]))


def vsd(
    dist_est: np.ndarray, dist_gt: np.ndarray, dist_test: np.ndarray, delta: float, taus: np.ndarray,
    diameter: float | None = None,
) -> np.ndarray:
    """Visible Surface Discrepancy (BOP19: 'step' cost, ``visib_mode='bop19'``) for each tolerance tau.

    As bop_toolkit ``pose_error.vsd``: visibility of the GT model ``V_g`` = rendered and
    ``dist_gt - dist_test <= delta`` (float32 difference) or no test measurement (0);
    visibility of the estimate ``V_e`` = the same test on ``dist_est``, united with
    ``V_g & (dist_est > 0)``. Over the union ``U = V_g | V_e`` (1 for every tau if empty),
    ``e = (#{p in V_g & V_e: cost(p) >= tau} + #(U minus V_g & V_e)) / #U`` with
    ``cost = |dist_gt - dist_est|`` (float64), divided by ``diameter`` when given (the toolkit's
    ``vsd_normalized_by_diameter``; then ``taus`` are fractions of the diameter).

    Args:
        dist_est, dist_gt: [H,W] distance maps (m, 0 = not rendered) of the model at the estimated
            and the GT pose (distance from the camera centre, not depth).
        dist_test: [H,W] distance map of the test depth image (m, 0 = no measurement).
        delta: tolerance of the visibility test (m), e.g. 0.015.
        taus: [T] misalignment tolerances (m, or x diameter when ``diameter`` is given).
        diameter: object diameter (m) to normalise the costs by, or None.
    Returns:
        [T] errors in [0, 1].
    """
    if not (dist_est.shape == dist_gt.shape == dist_test.shape) or dist_test.ndim != 2:
        raise ValueError(f"distance maps must be [H,W] of one shape, got {dist_est.shape}, {dist_gt.shape}, "
                         f"{dist_test.shape}")
    return _vsd(dist_est, (0, 0), dist_gt, (0, 0), dist_test, None, delta, taus, diameter)


def vsd_of_depth_windows(
    depth_est: np.ndarray, origin_est: tuple[int, int], depth_gt: np.ndarray, origin_gt: tuple[int, int],
    depth_test: np.ndarray, K: np.ndarray, delta: float, taus: np.ndarray, diameter: float | None = None,
) -> np.ndarray:
    """:func:`vsd` from depth maps (m) that cover only image windows (0 outside them), over the
    union of the two windows, their distances (and the test image's) computed pixel by pixel as the
    toolkit's ``depth_im_to_dist_im_fast`` (float64 of the depth; ``K`` [3,3], pixel indices).

    Args:
        depth_est, depth_gt: [h,w] depth maps of the windows whose top-left pixels (x0, y0) are
            ``origin_est``, ``origin_gt``.
        depth_test: [H,W] the whole test image's depth (0 = no measurement).
    """
    return _vsd(depth_est, origin_est, depth_gt, origin_gt, depth_test, K, delta, taus, diameter)


def _vsd(map_est: np.ndarray, origin_est: tuple[int, int], map_gt: np.ndarray, origin_gt: tuple[int, int],
         map_test: np.ndarray, K: np.ndarray | None, delta: float, taus: np.ndarray,
         diameter: float | None) -> np.ndarray:
    """VSD over the union of two windows: distance maps (``K`` None) or depth maps (compiled loop:
    :func:`cosy_lite.eval._vsd_kernel.vsd_counts`)."""
    from cosy_lite.eval._vsd_kernel import vsd_counts

    taus = np.ascontiguousarray(taus, dtype=np.float64).reshape(-1)
    (ex0, ey0), (gx0, gy0) = (int(v) for v in origin_est), (int(v) for v in origin_gt)
    boxes = [(x, y, x + m.shape[1], y + m.shape[0]) for (x, y), m in (((ex0, ey0), map_est), ((gx0, gy0), map_gt))
             if m.size]
    if not boxes:
        return np.ones(len(taus))
    x0, y0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
    x1, y1 = max(b[2] for b in boxes), max(b[3] for b in boxes)
    if x0 < 0 or y0 < 0 or x1 > map_test.shape[1] or y1 > map_test.shape[0]:
        raise ValueError(f"windows {boxes} (x0, y0, x1, y1) are not inside the {map_test.shape[1]}x"
                         f"{map_test.shape[0]} test image")
    fx, fy, cx, cy = (1.0, 1.0, 0.0, 0.0) if K is None else (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    matches = np.zeros(len(taus), np.int64)
    union = vsd_counts(map_est, ex0, ey0, map_gt, gx0, gy0, map_test, K is not None, float(fx), float(fy),
                       float(cx), float(cy), x0, y0, x1, y1, float(delta), taus,
                       float(diameter) if diameter is not None else 0.0, matches)
    if union == 0:
        return np.ones(len(taus))
    return (union - matches) / float(union)
