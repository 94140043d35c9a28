"""What the predictor returns for one image: :class:`PoseEstimates` (poses, scores, validity, timings)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from cosy_lite.geometry.pose_checks import valid_poses
from cosy_lite.inference.icp import IcpResult

# seconds per stage of an image; "total" is the image's (detection to the last pose) and does not
# hold "templates": the one-time rendering of an object's templates, on its first image
TIMING_KEYS = ("detection", "crops", "render", "networks", "icp", "total", "templates")


@dataclass
class PoseEstimates:
    """Pose estimates of the objects of one image, by decreasing score.

    obj_ids [N] int64; TCO [N,4,4] float64 object-to-camera (m); scores [N] float32 (the detection
    scores); boxes [N,4] float32 detection boxes x1, y1, x2, y2 (px); valid [N] bool: finite pose,
    rotation matrix, in front of the camera (>= :data:`~cosy_lite.geometry.pose_checks.MIN_DEPTH`) — invalid poses must not be
    written; TCO_coarse [N,4,4] where the refiner started (after the coarse model, or the chosen
    template); icp: one
    :class:`~cosy_lite.inference.icp.IcpResult` per object, or None when ICP did not run;
    TCO_before_icp [N,4,4]: the refiner's poses when ICP ran (None otherwise); masks [N,H,W] bool:
    the detections' masks (None for detections given as boxes only);
    timings: seconds per stage (:data:`TIMING_KEYS`; "crops" is the rest of the pose iterations:
    crop boxes, roi_align, K_crop, pose updates).
    """

    obj_ids: Tensor
    TCO: Tensor
    scores: Tensor
    boxes: Tensor
    valid: Tensor
    TCO_coarse: Tensor
    timings: dict[str, float] = field(default_factory=dict)
    icp: list[IcpResult] | None = None
    TCO_before_icp: Tensor | None = None
    masks: Tensor | None = None

    def __len__(self) -> int:
        return len(self.obj_ids)

    @classmethod
    def empty(cls, timings: dict[str, float] | None = None) -> "PoseEstimates":
        z4 = torch.zeros((0, 4, 4), dtype=torch.float64)
        return cls(torch.zeros(0, dtype=torch.int64), z4, torch.zeros(0), torch.zeros((0, 4)),
                   torch.zeros(0, dtype=torch.bool), z4.clone(), dict(timings or {}))

    def only_valid(self) -> "PoseEstimates":
        """The estimates with a valid pose (same order)."""
        keep = self.valid.nonzero().flatten().tolist()
        icp = None if self.icp is None else [self.icp[i] for i in keep]
        before = None if self.TCO_before_icp is None else self.TCO_before_icp[keep]
        masks = None if self.masks is None else self.masks[keep]
        return replace(self, obj_ids=self.obj_ids[keep], TCO=self.TCO[keep], scores=self.scores[keep],
                       boxes=self.boxes[keep], valid=self.valid[keep], TCO_coarse=self.TCO_coarse[keep], icp=icp,
                       TCO_before_icp=before, masks=masks)

    def before_icp(self) -> "PoseEstimates":
        """The estimates as they were before ICP (the refiner's poses; validity and timings without
        ICP); these estimates themselves when ICP did not run."""
        if self.TCO_before_icp is None:
            return self
        timings = dict(self.timings, total=self.timings.get("total", 0.0) - self.timings.get("icp", 0.0), icp=0.0)
        return replace(self, TCO=self.TCO_before_icp, valid=valid_poses(self.TCO_before_icp), icp=None,
                       TCO_before_icp=None, timings=timings)
