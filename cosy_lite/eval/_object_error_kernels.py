"""The compiled loops of :mod:`cosy_lite.eval.object_errors` (numba, ``cache=True``: compiled once
per install, then loaded): MSSD / MSPD as one branch-and-bound loop over the symmetries, and the
farthest-point order of its probe points. Where numpy computed every symmetry's maximum over
every vertex (or bounds of them, in chunks of temporaries), the loop stops a symmetry's maximum
as soon as it reaches the best value found, which never changes the minimum.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _sq_dist(est, pts, M, k, i, project):
    """||est[i] - f_k(pts[i])||^2 with f_k(v) = M[k] [v; 1] ([3,4]), divided by its third
    coordinate first when ``project`` (pixels: M = K [R | t], est [N,2])."""
    vx, vy, vz = pts[i, 0], pts[i, 1], pts[i, 2]
    x = M[k, 0, 0] * vx + M[k, 0, 1] * vy + M[k, 0, 2] * vz + M[k, 0, 3]
    y = M[k, 1, 0] * vx + M[k, 1, 1] * vy + M[k, 1, 2] * vz + M[k, 1, 3]
    z = M[k, 2, 0] * vx + M[k, 2, 1] * vy + M[k, 2, 2] * vz + M[k, 2, 3]
    if project:
        dx, dy = est[i, 0] - x / z, est[i, 1] - y / z
        return dx * dx + dy * dy
    dx, dy, dz = est[i, 0] - x, est[i, 1] - y, est[i, 2] - z
    return dx * dx + dy * dy + dz * dz


@njit(cache=True, nogil=True, error_model="numpy")  # x / 0: inf or NaN, no exception
def min_max_sq_dist(est, pts, M, probes, project):
    """``min_k max_i ||est[i] - f_k(pts[i])||^2`` (see :func:`_sq_dist`) over the S maps ``M``
    [S,3,4], the points ``pts`` [N,3] and their images ``est`` [N,3] (or [N,2] pixels, ``project``).

    Exact branch and bound: the maximum over the ``probes`` (indices into ``pts``) is a lower
    bound of each map's maximum; maps are taken in increasing order of bound, each map's maximum
    stops once it reaches the best value so far (it can no longer be the minimum), and the loop
    ends at the first bound not below it. NaN if a NaN distance is met (the caller then uses the
    reference definition, whose NaN rules this loop does not follow)."""
    S, N = M.shape[0], pts.shape[0]
    lb = np.zeros(S)
    if S > 1:
        for k in range(S):
            m = 0.0
            for j in range(probes.shape[0]):
                d = _sq_dist(est, pts, M, k, probes[j], project)
                if d > m:
                    m = d
                elif d != d:
                    return np.nan
            lb[k] = m
    order = np.argsort(lb, kind="mergesort")
    best = np.inf
    for j in range(S):
        k = order[j]
        if lb[k] >= best:
            break
        m = 0.0
        for i in range(N):
            d = _sq_dist(est, pts, M, k, i, project)
            if d > m:
                m = d
                if m >= best:
                    break
            elif d != d:
                return np.nan
        if m < best:
            best = m
    return best


@njit(cache=True, nogil=True, error_model="numpy")
def mssd_mspd_sq(pts, T, G, P, K, probes):
    """(MSSD^2, MSPD^2) of the estimate ``T`` [3,4] (R | t) against the symmetric GT poses ``G``
    [S,3,4] and their projections ``P`` = K G [S,3,4], over the model points ``pts`` [N,3] (m);
    ``K`` [3,3]. MSPD^2 is NaN where an estimated point is not in front of the camera (z <= 0),
    MSSD^2 or MSPD^2 where a NaN distance is met (see :func:`min_max_sq_dist`)."""
    N = pts.shape[0]
    cam = np.empty((N, 3))
    uv = np.empty((N, 2))
    front = True
    for i in range(N):
        vx, vy, vz = pts[i, 0], pts[i, 1], pts[i, 2]
        x = T[0, 0] * vx + T[0, 1] * vy + T[0, 2] * vz + T[0, 3]
        y = T[1, 0] * vx + T[1, 1] * vy + T[1, 2] * vz + T[1, 3]
        z = T[2, 0] * vx + T[2, 1] * vy + T[2, 2] * vz + T[2, 3]
        cam[i, 0], cam[i, 1], cam[i, 2] = x, y, z
        if not z > 0.0:
            front = False
        w = K[2, 0] * x + K[2, 1] * y + K[2, 2] * z
        uv[i, 0] = (K[0, 0] * x + K[0, 1] * y + K[0, 2] * z) / w
        uv[i, 1] = (K[1, 0] * x + K[1, 1] * y + K[1, 2] * z) / w
    mssd = min_max_sq_dist(cam, pts, G, probes, False)
    mspd = min_max_sq_dist(uv, pts, P, probes, True) if front else np.nan
    return mssd, mspd


@njit(cache=True, nogil=True)
def farthest_point_order(pts, n):
    """Indices of ``n`` (<= N) points of ``pts`` [N,3] by farthest-point sampling, starting from the
    point farthest from the centroid; ties go to the lowest index."""
    N = pts.shape[0]
    idx = np.empty(n, np.int64)
    c = np.zeros(3)
    for i in range(N):
        for a in range(3):
            c[a] += pts[i, a]
    c /= N
    d = np.empty(N)
    for i in range(N):
        d[i] = (pts[i, 0] - c[0]) ** 2 + (pts[i, 1] - c[1]) ** 2 + (pts[i, 2] - c[2]) ** 2
    idx[0] = np.argmax(d)
    for i in range(N):
        s = pts[idx[0]]
        d[i] = (pts[i, 0] - s[0]) ** 2 + (pts[i, 1] - s[1]) ** 2 + (pts[i, 2] - s[2]) ** 2
    for k in range(1, n):
        idx[k] = np.argmax(d)
        s = pts[idx[k]]
        for i in range(N):
            e = (pts[i, 0] - s[0]) ** 2 + (pts[i, 1] - s[1]) ** 2 + (pts[i, 2] - s[2]) ** 2
            if e < d[i]:
                d[i] = e
    return idx
