"""Exact and fast MSSD, MSPD, ADD and ADI of one object: what depends only on the model is prepared once.

The values are those of the definitions in :mod:`cosy_lite.eval.pose_errors` (the toolkit's loops),
obtained with less work:

* **MSSD, MSPD**: ``min_S max_v`` of the distance between the estimated and the symmetric GT
  vertex (projected, for MSPD) in one compiled loop (:mod:`cosy_lite.eval._object_error_kernels`),
  an exact branch and bound: the maxima over a few probe vertices (farthest-point samples) bound
  every symmetry from below, symmetries are taken in increasing order of bound, and a symmetry's
  maximum stops as soon as it reaches the best value found. Poses where a projection could divide
  by zero (a vertex in the camera plane) go to the reference definition, whose NaN rules hold there.
* **ADI**: ``min_u ||T_g v - T_e u|| = min_u ||T_e^-1 T_g v - u||`` (rigid motions keep
  distances), so one k-d tree of the model vertices, built once, answers every pair. Where only
  values under a cap matter, a pair is first bounded from below by the exact distances of a few
  sample points: a vertex ``v`` at ``rho`` from its nearest sample ``s`` is at least ``d(s) - rho``
  from the other pose (the motion keeps ``||v - s||``), and queries far from the surface are the
  slow ones of a k-d tree. These tables (and scipy) are loaded on ADI's first use only.

Everything is float64, metres and pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

PROBES = 16  # vertices bounding each symmetry's MSSD / MSPD from below (objects with symmetries)
ADI_SAMPLES = 128  # vertices bounding ADI from below (the AUC's cap)


def farthest_point_order(pts: np.ndarray, n: int) -> np.ndarray:
    """Indices of ``n`` points of ``pts`` [N,3] by farthest-point sampling, starting from the point
    farthest from the centroid (deterministic)."""
    from cosy_lite.eval._object_error_kernels import farthest_point_order as fps

    pts = np.ascontiguousarray(pts, dtype=np.float64)
    return fps(pts, min(int(n), len(pts)))


@dataclass
class ObjectErrors:
    """Per-object data for MSSD, MSPD, ADD, ADI (see the module docstring).

    Args (of :meth:`from_model`): pts [N,3] ``models_eval`` vertices (m); syms [S,4,4] symmetry set
    (identity first, see :func:`cosy_lite.geometry.symmetries.symmetry_transforms`); diameter (m).
    """

    pts: np.ndarray  # [N,3]
    syms: np.ndarray  # [S,4,4]
    diameter: float
    probes: np.ndarray  # [P] indices into pts: the bounds of the symmetries (empty without symmetries)
    reach: float  # max ||S v|| over vertices and symmetries: GT-posed points lie within it of t_gt (m)
    centre: np.ndarray = field(default_factory=lambda: np.zeros(3))  # [3] bounding-box centre
    radius: float = 0.0  # max distance of a vertex from ``centre``
    # ADI's tables, built on its first use (an evaluation without the AUC never needs them):
    tree: object | None = None  # scipy cKDTree of ``pts``
    _samples: np.ndarray | None = None  # [M,3] farthest-point samples for the ADI bound
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
        probes = farthest_point_order(pts, PROBES) if len(syms) > 1 else np.zeros(0, np.int64)
        norms = np.linalg.norm(pts, axis=1)
        reach = float(norms.max() + np.linalg.norm(syms[:, :3, 3], axis=1).max())
        centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
        radius = float(np.linalg.norm(pts - centre, axis=1).max())
        return ObjectErrors(pts, syms, float(diameter), probes, reach, centre, radius)

    @property
    def samples(self) -> np.ndarray:
        """[M,3] the vertices whose exact distances bound ADI from below (farthest-point samples)."""
        if self._samples is None:
            self._samples = self.pts[farthest_point_order(self.pts, ADI_SAMPLES)]
        return self._samples

    def _adi_tables(self):
        """The k-d tree of the vertices (and ``nearest_sample``, ``sample_dist``), built on first use."""
        if self.tree is None:
            from scipy.spatial import cKDTree

            self.sample_dist, self.nearest_sample = cKDTree(self.samples).query(self.pts, k=1)
            self.tree = cKDTree(self.pts)
        return self.tree

    # ------------------------------------------------------------------ MSSD / MSPD
    def mssd_mspd(self, TCO_est: np.ndarray, TCO_gt: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """MSSD [E] (m) and MSPD [E] (px) of estimates ``TCO_est`` [E,4,4] against ``TCO_gt`` [4,4], ``K`` [3,3].

        Exactly ``pose_errors.mssd_mspd`` (without the toolkit's sphere shortcut: see
        ``image_errors.mssd_mspd_errors``).
        """
        from cosy_lite.eval._object_error_kernels import mssd_mspd_sq

        TCO_est = np.asarray(TCO_est, dtype=np.float64).reshape(-1, 4, 4)
        K = np.ascontiguousarray(K, dtype=np.float64)
        TCO_gt = np.asarray(TCO_gt, dtype=np.float64)
        G = np.ascontiguousarray((TCO_gt @ self.syms)[:, :3, :])  # [S,3,4] GT pose of each symmetric copy
        P = np.ascontiguousarray(K @ G)  # [S,3,4] their projections
        gt_in_front = TCO_gt[2, 3] > self.reach  # every GT-posed vertex has z > 0: finite projections
        mssd, mspd = np.empty(len(TCO_est)), np.empty(len(TCO_est))
        for e, T in enumerate(TCO_est):
            sq3, sq2 = mssd_mspd_sq(self.pts, np.ascontiguousarray(T[:3]), G, P, K, self.probes)
            mssd[e], mspd[e] = np.sqrt(sq3), np.sqrt(sq2) if gt_in_front else np.nan
            if not (np.isfinite(mssd[e]) and np.isfinite(mspd[e])):  # the reference's rules for NaN / inf
                from cosy_lite.eval.pose_errors import mssd_mspd

                with np.errstate(divide="ignore", invalid="ignore"):
                    ref = mssd_mspd(T[None], TCO_gt, K, self.pts, self.syms)
                mssd[e], mspd[e] = ref[0][0], ref[1][0]
        return mssd, mspd

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
