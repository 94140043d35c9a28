"""Errors of the evaluated estimates of one test image against its GT instances (BOP19 rules).

Per target (object of the image) the caller gives the top ``inst_count`` estimates; each is
compared with every GT instance of that object, as bop_toolkit ``eval_calc_errors.py``:

* **VSD** only where the projections of the bounding spheres overlap
  (``misc.overlapping_sphere_projections``, radius = diameter / 2 about the model origin);
  elsewhere 1 for every tau. Each estimate and GT pose is rendered once (only if one of its
  pairs needs it), inside its own window; a pair is scored on the union of the two windows,
  which holds every pixel where either model is rendered, so the result equals a full-image VSD.
* **MSSD** is +inf where the bounding spheres do not overlap (``||t_e - t_g|| >= diameter``), as
  the toolkit; **MSPD** is always computed, as the toolkit. **ADD, ADI** only feed the YCB-V AUC
  (PoseCNN's, without the toolkit's shortcut) and are computed only when it is asked for
  (``add_adi``; not part of BOP19, +inf otherwise): ADD always, ADI unless it is provably >= 10 cm
  (then +inf: such errors add nothing to the AUC and are never matched).
"""

from __future__ import annotations

from concurrent.futures import Executor, Future
from dataclasses import dataclass
from typing import Callable

import numpy as np

from cosy_lite.bop.results import PoseEstimate
from cosy_lite.eval import pose_errors
from cosy_lite.eval.depth_renderer import Window, WindowDepthRenderer, object_window
from cosy_lite.eval.object_errors import ObjectErrors
from cosy_lite.eval.scoring import AUC_MAX_M, VSD_TAUS


@dataclass
class PairErrors:
    """Errors of E estimates x G GT instances of one object in one image."""

    vsd: np.ndarray  # [E,G,T] per tau of VSD_TAUS
    mssd: np.ndarray  # [E,G] m
    mspd: np.ndarray  # [E,G] px
    add: np.ndarray  # [E,G] m
    adi: np.ndarray  # [E,G] m

    @staticmethod
    def missing(E: int, G: int) -> PairErrors:
        """Nothing computed: VSD 1, the others +inf."""
        return PairErrors(np.ones((E, G, len(VSD_TAUS))), *(np.full((E, G), np.inf) for _ in range(4)))


def mssd_mspd_errors(obj: ObjectErrors, T_est: np.ndarray, T_gt: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MSSD [E] (m) and MSPD [E] (px) of estimates ``T_est`` [E,4,4] against one GT pose, as the toolkit's
    ``eval_calc_errors.py``: MSSD is +inf where the bounding spheres do not overlap (``||t_e - t_g|| >= diameter``)."""
    near = np.linalg.norm(T_est[:, :3, 3] - T_gt[:3, 3], axis=1) < obj.diameter
    mssd, mspd = obj.mssd_mspd(T_est, T_gt, K)
    mssd = np.where(near, mssd, np.inf)
    return mssd, mspd


def _model_errors(obj: ObjectErrors, T_est: np.ndarray, gt_TCO: list[np.ndarray], K: np.ndarray,
                  out: PairErrors, add_adi: bool = True) -> None:
    """Fill ``out.mssd``, ``mspd`` and, with ``add_adi``, ``add``, ``adi`` (in place) of estimates
    ``T_est`` [E,4,4] x ``gt_TCO`` (G)."""
    for g, T_gt in enumerate(gt_TCO):
        out.mssd[:, g], out.mspd[:, g] = mssd_mspd_errors(obj, T_est, T_gt, K)
        if add_adi:
            out.add[:, g] = obj.add(T_est, T_gt)
            out.adi[:, g] = obj.adi(T_est, T_gt, cap=AUC_MAX_M)


def _vsd_pairs(obj_id: int, obj: ObjectErrors, T_est: list[np.ndarray], gt_TCO: list[np.ndarray],
               gt_keys: list[int]) -> list[tuple[int, int, tuple, tuple]]:
    """(e, g, render key of estimate e, of GT g) of the pairs whose VSD is computed: those whose
    bounding spheres' projections overlap (the toolkit's shortcut; VSD is 1 elsewhere), GT-major."""
    radius = 0.5 * obj.diameter
    return [(e, g, ("est", obj_id, e), ("gt", gkey)) for g, (T_gt, gkey) in enumerate(zip(gt_TCO, gt_keys))
            for e, T_e in enumerate(T_est) if pose_errors.sphere_projections_overlap(radius, T_e[:3, 3], T_gt[:3, 3])]


class ImageErrors:
    """Computes :class:`PairErrors` for the targets of one image; renders lazily, each pose once.

    Args:
        renderer: depth renderer of the image size.
        load_depth: ``() -> [H,W]`` test depth (m, 0 = no measurement); called when VSD first needs it.
        K: [3,3] intrinsics; delta: VSD visibility tolerance (m).
        executor: where the errors that need no rendering run (e.g. a one-thread pool), or None.
        add_adi: also compute ADD and ADI (for the YCB-V AUC); else they stay +inf.
    """

    def __init__(self, renderer: WindowDepthRenderer, load_depth: Callable[[], np.ndarray], K: np.ndarray,
                 delta: float, executor: Executor | None = None, add_adi: bool = True):
        self.renderer = renderer
        self.executor = executor
        self.add_adi = add_adi
        self._load_depth = load_depth
        self._depth: np.ndarray | None = None
        self.K = np.asarray(K, dtype=np.float64)
        self.delta = float(delta)
        self._rendered: dict[tuple, tuple[Window, np.ndarray]] = {}

    def _test_depth(self) -> np.ndarray:
        if self._depth is None:
            self._depth = self._load_depth()
        return self._depth

    def _render(self, key: tuple, obj_id: int, obj: ObjectErrors, TCO: np.ndarray) -> tuple[Window, np.ndarray]:
        """Window and float32 depth map (m) of one pose (cached under ``key``)."""
        if key not in self._rendered:
            self._render_batch([(key, obj_id, obj, TCO)])
        return self._rendered[key]

    def _render_batch(self, poses: list[tuple[tuple, int, ObjectErrors, np.ndarray]]) -> None:
        """Render ``(key, obj_id, obj, TCO)`` poses not yet cached, as one batch of the renderer."""
        r = self.renderer
        todo = [(key, obj_id, object_window(obj.pts, TCO, self.K, r.width, r.height), TCO)
                for key, obj_id, obj, TCO in dict((p[0], p) for p in poses).values() if key not in self._rendered]
        depths = r.render_many([(obj_id, TCO, win) for _, obj_id, win, TCO in todo], self.K)
        for (key, _, win, _), depth in zip(todo, depths):
            self._rendered[key] = (win, depth)

    def prefetch(self, targets: list[tuple[int, ObjectErrors, list[PoseEstimate], list[np.ndarray], list[int]]]) -> None:
        """Render, as one batch, every pose that :meth:`target` of these ``(obj_id, obj, ests,
        gt_TCO, gt_keys)`` will need for VSD (those of the pairs whose bounding spheres overlap)."""
        poses = []
        for obj_id, obj, ests, gt_TCO, gt_keys in targets:
            T_est = [e.TCO for e in ests]
            for e, g, key_e, key_g in _vsd_pairs(obj_id, obj, T_est, gt_TCO, gt_keys):
                poses += [(key_e, obj_id, obj, T_est[e]), (key_g, obj_id, obj, gt_TCO[g])]
        self._render_batch(poses)

    def target(self, obj_id: int, obj: ObjectErrors, ests: list[PoseEstimate], gt_TCO: list[np.ndarray],
               gt_keys: list[int], pending: list[Future] | None = None) -> PairErrors:
        """Errors of ``ests`` (E, evaluated order) against GT poses ``gt_TCO`` (G; ``gt_keys``: their GT indices).

        MSSD, MSPD, ADD and ADI run on ``executor`` (if given) while VSD renders here: the k-d tree
        and large numpy products release the GIL, so the two overlap on a second core. With
        ``pending``, their job is appended to it instead of awaited: the returned ``mssd``, ``mspd``,
        ``add``, ``adi`` are complete only once the caller has waited for it (``Future.result``),
        so that one target's slow model errors overlap the next targets' rendering.
        """
        E, G = len(ests), len(gt_TCO)
        out = PairErrors.missing(E, G)
        if E == 0 or G == 0:
            return out
        T_est = np.stack([e.TCO for e in ests])
        job = (self.executor.submit(_model_errors, obj, T_est, gt_TCO, self.K, out, self.add_adi)
               if self.executor else None)
        if job is None:
            _model_errors(obj, T_est, gt_TCO, self.K, out, self.add_adi)
        for e, g, key_e, key_g in _vsd_pairs(obj_id, obj, list(T_est), gt_TCO, gt_keys):
            out.vsd[e, g] = self._vsd(obj_id, obj, key_e, T_est[e], key_g, gt_TCO[g])
        if job is not None:
            if pending is None:
                job.result()
            else:
                pending.append(job)
        return out

    def _vsd(self, obj_id: int, obj: ObjectErrors, key_e, T_e, key_g, T_g) -> np.ndarray:
        win_e, depth_e = self._render(key_e, obj_id, obj, T_e)
        win_g, depth_g = self._render(key_g, obj_id, obj, T_g)
        if win_e.union(win_g).empty:  # neither pose is rendered in the image: empty union
            return np.ones(len(VSD_TAUS))
        return pose_errors.vsd_of_depth_windows(depth_e, (win_e.x0, win_e.y0), depth_g, (win_g.x0, win_g.y0),
                                                self._test_depth(), self.K, self.delta, VSD_TAUS, diameter=obj.diameter)
