"""Exact and fast MSSD, MSPD, ADD and ADI of one object: what depends only on the model is prepared once.

The values are those of the definitions in :mod:`cosy_lite.eval.pose_errors` (the toolkit's loops),
obtained with less work:

* **MSSD** ``min_S max_v ||R_e v + t_e - (R_g (R_S v + t_S) + t_g)||``: for one symmetry the error
  is ``||A v + b||``, a convex function of ``v``, so its maximum over the vertices is attained at a
  vertex of their convex hull: only hull vertices are evaluated.
* **MSPD** (not convex) and the minimum over symmetries of both: exact branch and bound. The
  maximum over a subset of the vertices is a lower bound of the maximum over all of them; bounds
  from small vertex subsets (farthest-point samples of the hull, coarse to fine) are computed for
  every symmetry at once, and the full maximum is computed only for symmetries whose bound is
  below the best full value found so far, in increasing order of bound.
* **ADI**: ``min_u ||T_g v - T_e u|| = min_u ||T_e^-1 T_g v - u||`` (rigid motions keep
  distances), so one k-d tree of the model vertices, built once, answers every pair. Where only
  values under a cap matter, a pair is first bounded from below by the exact distances of a few
  sample points (the finest MSSD probes): a vertex ``v`` at ``rho`` from its nearest sample ``s``
  is at least ``d(s) - rho`` from the other pose (the motion keeps ``||v - s||``), and queries
  far from the surface are the slow ones of a k-d tree.

Everything is float64, metres and pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

PROBE_SIZES = (16, 128)  # vertices per bound level (farthest-point samples of the hull vertices)


def farthest_point_order(pts: np.ndarray, n: int) -> np.ndarray:
    """Indices of ``n`` points of ``pts`` [N,3] by farthest-point sampling, starting from the point
    farthest from the centroid (deterministic)."""
    n = min(n, len(pts))
    idx = np.empty(n, dtype=np.int64)
    idx[0] = int(np.argmax(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))
    d = np.linalg.norm(pts - pts[idx[0]], axis=1)
    for i in range(1, n):
        idx[i] = int(np.argmax(d))
        d = np.minimum(d, np.linalg.norm(pts - pts[idx[i]], axis=1))
    return idx


def hull_vertex_indices(pts: np.ndarray) -> np.ndarray:
    """Sorted indices of the vertices of the convex hull of ``pts`` [N,3]; all points if the hull is
    degenerate (flat models). Points qhull merges as coplanar lie within round-off of the hull, so
    a maximum of a convex function over the vertices changes by round-off at most."""
    try:
        hull = ConvexHull(pts)
    except Exception:  # qhull raises QhullError on flat / degenerate point sets
        return np.arange(len(pts))
    return np.sort(hull.vertices.astype(np.int64))


def _project(p: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points [...,3] -> pixels [...,2] (toolkit ``project_pts``: K p, then divide by z)."""
    uvw = p @ K.T
    return uvw[..., :2] / uvw[..., 2:3]


def _max_norm(d: np.ndarray) -> np.ndarray:
    """max over the point axis of ||d||: [...,P,D] -> [...] (NaN if any distance is NaN)."""
    return np.sqrt(np.einsum("...pd,...pd->...p", d, d).max(axis=-1))


def min_of_max(n_syms: int, bound, full) -> float:
    """``min_k full(k)`` over ``k < n_syms`` by branch and bound.

    Args:
        bound: ``bound(level, ks) -> [len(ks)]`` lower bounds of ``full`` for symmetries ``ks``;
            ``level`` = 0, 1, ... coarse to fine (``len(PROBE_SIZES)`` levels).
        full: ``full(ks) -> [len(ks)]`` the exact values.
    Returns:
        The exact minimum (NaN bounds count as +inf; a NaN full value is kept as the toolkit would).
    """
    if n_syms == 1:
        return float(full(np.array([0]))[0])
    ks = np.arange(n_syms)
    lb = np.nan_to_num(bound(0, ks), nan=np.inf)
    done: dict[int, float] = {}

    def evaluate(sel: np.ndarray) -> float:
        new = [int(k) for k in sel if int(k) not in done]
        if new:
            for k, v in zip(new, full(np.array(new))):
                done[k] = float(v)
        return min(done[int(k)] for k in sel)

    best = evaluate(ks[[int(np.argmin(lb))]])
    for level in range(1, len(PROBE_SIZES)):
        keep = lb < best
        ks, lb = ks[keep], lb[keep]
        if len(ks) <= 4:
            break
        lb = np.maximum(lb, np.nan_to_num(bound(level, ks), nan=np.inf))
        best = min(best, evaluate(ks[[int(np.argmin(lb))]]))
    order = np.argsort(lb, kind="stable")
    ks, lb = ks[order], lb[order]
    i = 0
    while i < len(ks) and lb[i] < best:
        j = i + 1
        while j < len(ks) and j - i < 8 and lb[j] < best:  # a few at a time: one vectorised call
            j += 1
        best = min(best, evaluate(ks[i:j]))
        i = j
    return best


@dataclass
class ObjectErrors:
    """Per-object data for MSSD, MSPD, ADD, ADI (see the module docstring).

    Args (of :meth:`from_model`): pts [N,3] ``models_eval`` vertices (m); syms [S,4,4] symmetry set
    (identity first, see :func:`cosy_lite.geometry.symmetries.symmetry_transforms`); diameter (m).
    """

    pts: np.ndarray  # [N,3]
    syms: np.ndarray  # [S,4,4]
    diameter: float
    hull: np.ndarray  # [H,3] convex hull vertices
    probes: list[np.ndarray] = field(default_factory=list)  # per level [P,3], subsets of hull
    centre: np.ndarray = field(default_factory=lambda: np.zeros(3))  # [3] bounding-box centre
    radius: float = 0.0  # max distance of a vertex from ``centre``
    samples: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # [M,3] for the ADI bound: probes[-1]
    # ADI's tables, built on its first use (an evaluation without the AUC never needs them):
    tree: cKDTree | None = None  # k-d tree of ``pts``
    nearest_sample: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [N] index into samples
    sample_dist: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [N] ||v - its nearest sample||

    @staticmethod
    def from_model(pts: np.ndarray, syms: np.ndarray, diameter: float) -> ObjectErrors:
        pts = np.ascontiguousarray(pts, dtype=np.float64)
        syms = np.asarray(syms, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
            raise ValueError(f"pts must be [N,3] with N > 0, got {pts.shape}")
        if syms.ndim != 3 or syms.shape[1:] != (4, 4) or len(syms) == 0:
            raise ValueError(f"syms must be [S,4,4] with S > 0 (identity included), got {syms.shape}")
        hull = pts[hull_vertex_indices(pts)]
        order = farthest_point_order(hull, max(PROBE_SIZES))
        probes = [hull[order[:n]] for n in PROBE_SIZES]
        centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
        radius = float(np.linalg.norm(pts - centre, axis=1).max())
        return ObjectErrors(pts, syms, float(diameter), hull, probes, centre, radius, probes[-1])

    def _adi_tables(self) -> cKDTree:
        """The k-d tree of the vertices (and ``nearest_sample``, ``sample_dist``), built on first use."""
        if self.tree is None:
            self.sample_dist, self.nearest_sample = cKDTree(self.samples).query(self.pts, k=1)
            self.tree = cKDTree(self.pts)
        return self.tree

    # ------------------------------------------------------------------ MSSD / MSPD
    def mssd_mspd(self, TCO_est: np.ndarray, TCO_gt: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """MSSD [E] (m) and MSPD [E] (px) of estimates ``TCO_est`` [E,4,4] against ``TCO_gt`` [4,4], ``K`` [3,3].

        Exactly ``pose_errors.mssd_mspd`` (no shortcut: see :meth:`errors` for the toolkit's).
        """
        TCO_est = np.asarray(TCO_est, dtype=np.float64).reshape(-1, 4, 4)
        K = np.asarray(K, dtype=np.float64)
        G = np.asarray(TCO_gt, dtype=np.float64) @ self.syms  # [S,4,4] GT pose of each symmetric copy
        mssd = np.array([self._mssd_one(T, G) for T in TCO_est])
        with np.errstate(divide="ignore", invalid="ignore"):
            mspd = np.array([self._mspd_one(T, G, K) for T in TCO_est])
        return mssd, mspd

    def _mssd_one(self, T: np.ndarray, G: np.ndarray) -> float:
        A = T[None, :3, :3] - G[:, :3, :3]  # [S,3,3]: T v - G_k v = A_k v + b_k
        b = T[None, :3, 3] - G[:, :3, 3]  # [S,3]

        def err(pts: np.ndarray, ks: np.ndarray) -> np.ndarray:
            return _max_norm(pts[None] @ np.swapaxes(A[ks], 1, 2) + b[ks, None])

        return min_of_max(len(G), lambda level, ks: err(self.probes[level], ks), lambda ks: err(self.hull, ks))

    def _mspd_one(self, T: np.ndarray, G: np.ndarray, K: np.ndarray) -> float:
        def err(pts: np.ndarray, uv_est: np.ndarray, ks: np.ndarray) -> np.ndarray:
            uv_gt = _project(pts[None] @ np.swapaxes(G[ks, :3, :3], 1, 2) + G[ks, None, :3, 3], K)  # [k,P,2]
            return _max_norm(uv_est[None] - uv_gt)

        uv_probes = [_project(p @ T[:3, :3].T + T[:3, 3], K) for p in self.probes]
        uv_all = _project(self.pts @ T[:3, :3].T + T[:3, 3], K)
        return min_of_max(len(G), lambda level, ks: err(self.probes[level], uv_probes[level], ks),
                          lambda ks: err(self.pts, uv_all, ks))

    # ------------------------------------------------------------------ ADD / ADI
    def add(self, TCO_est: np.ndarray, TCO_gt: np.ndarray) -> np.ndarray:
        """ADD [E] (m): ``mean_v ||T_e v - T_g v||`` for ``TCO_est`` [E,4,4]."""
        TCO_est = np.asarray(TCO_est, dtype=np.float64).reshape(-1, 4, 4)
        TCO_gt = np.asarray(TCO_gt, dtype=np.float64)
        A = TCO_est[:, :3, :3] - TCO_gt[None, :3, :3]
        b = TCO_est[:, :3, 3] - TCO_gt[None, :3, 3]
        d = self.pts[None] @ np.swapaxes(A, 1, 2) + b[:, None]
        return np.sqrt(np.einsum("epd,epd->ep", d, d)).mean(axis=1)

    def adi(self, TCO_est: np.ndarray, TCO_gt: np.ndarray, cap: float | None = None) -> np.ndarray:
        """ADI / ADD-S [E] (m): mean over GT-posed vertices of the distance to the nearest estimated-posed vertex.

        With ``cap`` (m), a pair whose ADI is provably >= ``cap`` gets +inf without the nearest-neighbour
        search of every vertex (slow for far-apart poses), by two lower bounds: every estimated-posed
        vertex lies within ``radius`` of the posed ``centre``, so ``ADI >= mean_v max(0, |T_g v - T_e
        centre| - radius)``; then the exact distances ``d`` of the posed ``samples`` give ``ADI >= mean_v
        max(0, d(s_v) - rho_v)`` (``s_v`` the sample nearest to ``v``, ``rho_v`` their distance, kept
        by the motion), less a 1e-12 m margin for round-off. Values below the cap are unchanged.
        """
        TCO_est = np.asarray(TCO_est, dtype=np.float64).reshape(-1, 4, 4)
        out = np.empty(len(TCO_est))
        for i, T in enumerate(TCO_est):
            M = np.linalg.solve(T, np.asarray(TCO_gt, dtype=np.float64))  # T_e^-1 T_g
            q = self.pts @ M[:3, :3].T + M[:3, 3]  # GT-posed vertices in the estimate's model frame
            if cap is not None and self._adi_beyond(q, self.samples @ M[:3, :3].T + M[:3, 3], cap):
                out[i] = np.inf
                continue
            dist, _ = self._adi_tables().query(q, k=1)
            out[i] = dist.mean()
        return out

    def _adi_beyond(self, q: np.ndarray, q_samples: np.ndarray, cap: float) -> bool:
        """Whether ``mean_v min_u ||q_v - u||`` over the vertices ``u`` is provably >= ``cap`` (see :meth:`adi`);
        ``q`` [N,3], ``q_samples`` [M,3]: vertices and ``samples`` under the same motion."""
        if np.maximum(np.linalg.norm(q - self.centre, axis=1) - self.radius, 0.0).mean() >= cap:
            return True
        if len(self.samples) == 0:
            return False
        d, _ = self._adi_tables().query(q_samples, k=1)
        lower = d[self.nearest_sample] - self.sample_dist * (1.0 + 1e-9) - 1e-12
        return bool(np.maximum(lower, 0.0).mean() >= cap)
