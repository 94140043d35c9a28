"""Training targets and loss of the flow refiner (:class:`~cosy_lite.nets.flow_pose_net.FlowPoseNet`).

The GT pose gives, for free, where each rendered surface point really is: a rendering cell with
depth ``d`` at crop pixel ``uv`` is the 3D point ``X = d K_crop^-1 (uv, 1)`` at the input pose; at the
(symmetry-closest) GT pose it is ``T_gt T_in^-1 X``, projected at ``uv*``. The target displacement
is ``uv* - uv`` (crop pixels). A cell supervises only where its point is visible in the image: ``uv*``
inside the crop and on the instance's visible mask (``mask_visib``, cropped like the image).

Loss: cross-entropy of the cost volume's softmax against the target displacement spread
bilinearly over its 4 neighbouring cells (a sub-cell target), averaged over supervised cells; cells
whose target lies outside the ``+-radius`` window are not supervised.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from cosy_lite.nets.flow_pose_solver import backproject, cell_centres, sample_cells


@dataclass
class FlowTargets:
    """flow [B,h,w,2] crop px (target displacement of each rendering cell); valid [B,h,w] bool."""

    flow: Tensor
    valid: Tensor


def flow_targets(depth: Tensor, K_crop: Tensor, TCO_in: Tensor, TCO_gt: Tensor, visible: Tensor, stride: int) -> FlowTargets:
    """Targets for renderings ``depth [B,1,H,W]`` (m) made at ``TCO_in [B,4,4]`` with ``K_crop [B,3,3]``;
    ``TCO_gt [B,4,4]`` the GT (already the symmetric pose closest to ``TCO_in``); ``visible [B,H,W]``
    bool the instance's visible pixels in the image crop."""
    B, _, H, W = depth.shape
    h, w = H // stride, W // stride
    d = sample_cells(depth, stride, (h, w))
    uv = cell_centres((h, w), stride, depth.device)
    X = backproject(uv, d, K_crop)
    T = TCO_gt.double() @ torch.linalg.inv(TCO_in.double())
    Y = torch.einsum("bij,bhwj->bhwi", T[:, :3, :3], X) + T[:, None, None, :3, 3]
    p = torch.einsum("bij,bhwj->bhwi", K_crop.double(), Y)
    target = p[..., :2] / p[..., 2:3].clamp(min=1e-6)
    inside = (target[..., 0] >= 0) & (target[..., 0] < W) & (target[..., 1] >= 0) & (target[..., 1] < H) & (Y[..., 2] > 0)
    ui = target[..., 0].clamp(0, W - 1).long()
    vi = target[..., 1].clamp(0, H - 1).long()
    on_mask = torch.gather(visible.reshape(B, -1), 1, (vi * W + ui).reshape(B, -1)).view(B, h, w)
    return FlowTargets((target - uv).float(), (d > 0) & inside & on_mask)


def flow_loss(logits: Tensor, targets: FlowTargets, radius: int, stride: int) -> Tensor:
    """Mean cross-entropy of ``logits [B,(2r+1)^2,h,w]`` at the bilinear target cells (0 if no cell is supervised)."""
    n = 2 * radius + 1
    c = targets.flow.to(logits.dtype) / stride + radius  # window coordinates of the target
    in_window = (c >= 0).all(-1) & (c <= 2 * radius).all(-1)
    mask = (targets.valid & in_window).to(logits.dtype)
    x0 = c[..., 0].floor().clamp(0, 2 * radius - 1)
    y0 = c[..., 1].floor().clamp(0, 2 * radius - 1)
    fx, fy = (c[..., 0] - x0).clamp(0, 1), (c[..., 1] - y0).clamp(0, 1)
    log_p = logits.log_softmax(dim=1)

    def at(yy: Tensor, xx: Tensor) -> Tensor:
        return torch.gather(log_p, 1, (yy * n + xx).long()[:, None]).squeeze(1)

    ce = -((1 - fx) * (1 - fy) * at(y0, x0) + fx * (1 - fy) * at(y0, x0 + 1)
           + (1 - fx) * fy * at(y0 + 1, x0) + fx * fy * at(y0 + 1, x0 + 1))
    return (ce * mask).sum() / mask.sum().clamp(min=1.0)


def end_point_error(flow: Tensor, targets: FlowTargets) -> Tensor:
    """Mean |predicted - target| (px) over the supervised cells; ``flow [B,>=2,h,w]``."""
    e = (flow[:, :2].permute(0, 2, 3, 1).to(targets.flow) - targets.flow).norm(dim=-1)
    m = targets.valid.to(e.dtype)
    return (e * m).sum() / m.sum().clamp(min=1.0)
