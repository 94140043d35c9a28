"""Depth ICP as a predictor stage: the poses of one image refined against its measured depth.

:class:`DepthRefinement` runs :func:`~cosy_lite.inference.icp.refine_poses_icp` on the valid poses
(inside each detection's mask, or its box when there is no mask) and, with several hypotheses per
detection, keeps the one whose depth agrees best with the measurement (trying the others only
where the pipeline's choice does not already agree).
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
        """ICP of the hypotheses ``[N,k,4,4]`` of each detection, the pipeline's choice first: per
        detection the result whose depth agrees best with the measured depth (:attr:`IcpResult.agreement`,
        :func:`~cosy_lite.inference.icp.depth_agreement`; ties keep the first). The others are tried only
        where the first one's agreement after ICP is below ``config.accept_agreement``."""
        N, k = hypotheses.shape[:2]
        TCO, results = self.refine(hypotheses[:, 0].double(), K, depth, det, size)
        first = np.array([r.agreement for r in results])
        pending = np.flatnonzero(first < self.config.accept_agreement) if k > 1 else np.zeros(0, dtype=np.int64)
        if not len(pending):
            return TCO, results
        owners = torch.from_numpy(pending).repeat_interleave(k - 1)
        others, other_results = self.refine(hypotheses[torch.from_numpy(pending), 1:].reshape(-1, 4, 4).double(), K, depth,
                                            det.select(owners), size)
        agreement = np.array([r.agreement for r in other_results]).reshape(len(pending), k - 1)
        TCO = TCO.clone()
        for j, i in enumerate(pending.tolist()):
            best = int(agreement[j].argmax())
            if agreement[j, best] > first[i]:
                TCO[i], results[i] = others[j * (k - 1) + best], other_results[j * (k - 1) + best]
        return TCO, results
