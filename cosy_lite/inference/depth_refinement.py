"""Depth ICP as a predictor stage: the poses of one image refined against its measured depth.

:class:`DepthRefinement` runs :func:`~cosy_lite.inference.icp.refine_poses_icp` on the valid poses
(inside each detection's mask, or its box when there is no mask) and, with several hypotheses per
detection, keeps the one whose depth agrees best with the measurement.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from cosy_lite.bop.detections import Detections
from cosy_lite.geometry.pose_checks import orthonormalise, valid_poses
from cosy_lite.inference.icp import IcpConfig, IcpResult, refine_poses_icp

if TYPE_CHECKING:
    from cosy_lite.render.renderer import MeshRenderer


def box_masks(boxes: Tensor, size: tuple[int, int]) -> np.ndarray:
    """``[N,H,W]`` bool masks filling ``boxes [N,4]`` (x1, y1, x2, y2 px)."""
    H, W = size
    masks = np.zeros((len(boxes), H, W), dtype=bool)
    for k, (x1, y1, x2, y2) in enumerate(boxes.double().tolist()):
        r0, r1 = max(0, int(np.floor(y1))), max(0, int(np.ceil(y2)))
        c0, c1 = max(0, int(np.floor(x1))), max(0, int(np.ceil(x2)))
        masks[k, r0:r1, c0:c1] = True
    return masks


class DepthRefinement:
    """ICP of a predictor's poses: ``renderer`` of the objects, ``config``, ``symmetries`` obj_id ->
    ``[S,4,4]`` symmetry set (m; None: no symmetry handling)."""

    def __init__(self, renderer: MeshRenderer, config: IcpConfig, symmetries: dict[int, np.ndarray] | None = None):
        self.renderer, self.config, self.symmetries = renderer, config, symmetries
        self._warned = False

    def refine(self, TCO: Tensor, K: Tensor, depth: np.ndarray, det: Detections,
               size: tuple[int, int]) -> tuple[Tensor, list[IcpResult]]:
        """ICP of the poses ``TCO [N,4,4]`` (m) of the detections ``det`` in an image of ``size``
        (H, W) with ``depth [H,W]`` (m): (poses [N,4,4] float64, one result each; an invalid pose
        is kept, its result says so)."""
        depth, masks = self._inputs(depth, det, size)
        ok = valid_poses(TCO)
        results: list[IcpResult | None] = [None] * len(TCO)
        idx = ok.nonzero().flatten().tolist()
        if idx:
            ids = det.obj_ids.tolist()
            syms = None if self.symmetries is None else [self.symmetries.get(ids[i]) for i in idx]
            out = refine_poses_icp(TCO[idx].numpy(), K.numpy(), depth, masks[idx], self.renderer,
                                   [ids[i] for i in idx], self.config, syms)
            for i, r in zip(idx, out):
                results[i] = r
        done = [r if r is not None else IcpResult(TCO[i].numpy().copy(), False, "invalid pose before ICP")
                for i, r in enumerate(results)]
        TCO_new = torch.from_numpy(np.stack([r.TCO for r in done])).double()
        return orthonormalise(TCO_new), done

    def _inputs(self, depth: np.ndarray, det: Detections, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """(depth [H,W] float32 m, masks [N,H,W] bool: the detections' masks, or their boxes)."""
        depth = np.asarray(depth, dtype=np.float32)
        if depth.shape != size:
            raise ValueError(f"depth must be [H,W] = {size} (as rgb), in metres; got {depth.shape}")
        if det.masks is not None:
            return depth, det.masks.cpu().numpy().astype(bool)
        if not self._warned:
            warnings.warn("Predictor: detections without masks; ICP uses the detection boxes as masks",
                          RuntimeWarning, stacklevel=4)
            self._warned = True
        return depth, box_masks(det.boxes, size)

    def refine_hypotheses(self, hypotheses: Tensor, K: Tensor, depth: np.ndarray, det: Detections,
                          size: tuple[int, int]) -> tuple[Tensor, list[IcpResult]]:
        """ICP of every hypothesis ``[N,k,4,4]``; per detection the result whose depth agrees best
        with the measured depth (:attr:`IcpResult.agreement`, :func:`~cosy_lite.inference.icp.depth_agreement`)."""
        N, k = hypotheses.shape[:2]
        flat_det = det.select(torch.arange(N).repeat_interleave(k))
        refined, results = self.refine(hypotheses.reshape(N * k, 4, 4).double(), K, depth, flat_det, size)
        agreement = np.array([r.agreement for r in results]).reshape(N, k)
        best = torch.from_numpy(agreement.argmax(axis=1) + np.arange(N) * k)
        return refined[best], [results[i] for i in best.tolist()]
