"""The pose update of a flow refiner: from a dense 2D displacement field to a new pose (torch).

The flow network (:class:`~cosy_lite.nets.flow_pose_net.FlowPoseNet`) says, for each stride-``s``
cell of the rendering, where that surface point is in the image crop (``flow [B,2,h,w]``, crop
pixels) and how sure it is (``confidence [B,h,w]``). The rendering's depth at the cell centre gives
the point in 3D at the current pose, so every cell is a 2D-3D correspondence; the new pose is the
weighted least-squares fit of those correspondences (perspective-n-point):

    min over (dR, t)   sum_cells  w * huber(| project(K_crop, dR (X - t_in) + t) - (uv + flow) |)

with ``X`` the cell's 3D point (camera frame, current pose), rotation about the object origin
(``R_new = dR R_in``, as :mod:`cosy_lite.nets.pose_update`), solved by damped Gauss-Newton from
the current pose. Items with fewer than ``MIN_CELLS`` confident rendered cells, or a non-finite or
behind-the-camera solution, keep their input pose.

A flow with a fourth channel (a network with a depth head) also says the log ratio of the object's
new depth to the current one, per cell: the new depth is the current one times the exponential of
their weighted mean, and the fitted translation is scaled to it along its line of sight (the
object's projected origin and the rotation stay the PnP's).

Differentiable in the flow and the confidences (training puts the pose loss behind the solver,
:meth:`cosy_lite.train.pose_task.PoseTask`); computed in float64 with autocast off.
"""

from __future__ import annotations

import torch
from torch import Tensor

from cosy_lite.nets.pose_update import full_precision

FLOW_STRIDE = 8  # px per cell of the flow field, by default (FlowPoseNet.stride; net.flow_stride)
FLOW_STRIDES = (4, 8)  # the strides a FlowPoseNet can have
MIN_CELLS = 6  # correspondences needed for a pose (6 unknowns)
GN_ITERATIONS = 10
HUBER_PX = 2.0  # crop pixels: residuals beyond weigh 1/|r|
DAMPING = 1e-3  # Levenberg-Marquardt on the Gauss-Newton diagonal


def cell_centres(shape: tuple[int, int], stride: int, device: torch.device | str = "cpu") -> Tensor:
    """``[h,w,2]`` float64 crop-pixel ``(u, v)`` of the centres of the stride cells (cell ``i``: ``i s + s / 2``)."""
    h, w = shape
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64, device=device) * stride + stride / 2,
                          torch.arange(w, dtype=torch.float64, device=device) * stride + stride / 2, indexing="ij")
    return torch.stack([u, v], dim=-1)


def sample_cells(depth: Tensor, stride: int, shape: tuple[int, int]) -> Tensor:
    """Depth ``[B,1,H,W]`` or ``[B,H,W]`` (m, 0 = no object) at the centre pixel of each cell: ``[B,h,w]`` float64."""
    if depth.dim() == 4:
        depth = depth[:, 0]
    h, w = shape
    d = depth[:, stride // 2::stride, stride // 2::stride][:, :h, :w].double()
    if d.shape[1:] != (h, w):
        raise ValueError(f"depth {tuple(depth.shape)} has no {h}x{w} cells of stride {stride}")
    return d


def flow_stride(depth: Tensor, flow: Tensor) -> int:
    """The stride (crop px per cell) of ``flow [B,C,h,w]`` answered for renderings ``depth [B,1,H,W]``:
    ``H / h``, which must equal ``W / w`` and be one of :data:`FLOW_STRIDES`."""
    (H, W), (h, w) = depth.shape[-2:], flow.shape[-2:]
    stride = H // h if h else 0
    if stride not in FLOW_STRIDES or (h * stride, w * stride) != (H, W):
        raise ValueError(f"flow {tuple(flow.shape)} is not a stride-{'/'.join(map(str, FLOW_STRIDES))} field "
                         f"of renderings {tuple(depth.shape)}")
    return stride


def backproject(uv: Tensor, depth: Tensor, K_crop: Tensor) -> Tensor:
    """Camera-frame points ``[B,h,w,3]`` of the pixels ``uv [h,w,2]`` at depths ``[B,h,w]`` (m)."""
    uv1 = torch.cat([uv, torch.ones_like(uv[..., :1])], dim=-1)
    return torch.einsum("bij,hwj->bhwi", torch.linalg.inv(K_crop.double()), uv1) * depth[..., None]


def _skew(w: Tensor) -> Tensor:
    z = torch.zeros_like(w[..., 0])
    return torch.stack([torch.stack([z, -w[..., 2], w[..., 1]], -1), torch.stack([w[..., 2], z, -w[..., 0]], -1),
                        torch.stack([-w[..., 1], w[..., 0], z], -1)], dim=-2)


def so3_exp(w: Tensor) -> Tensor:
    """Rotation matrices ``[B,3,3]`` of axis-angle vectors ``w [B,3]`` (Rodrigues)."""
    theta = w.norm(dim=-1)[:, None, None]
    k = _skew(w / theta[:, :, 0].clamp(min=1e-12))
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + theta.sin() * k + (1 - theta.cos()) * (k @ k)


def weighted_cells(points: Tensor, targets: Tensor, weights: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``points [B,N,3]``, ``targets [B,N,2]``, ``weights [B,N]`` cut to the cells with weight, each
    item's first (the others padded with weight 0): ``N`` becomes the most weighted cells of an item.
    Cells without weight add exactly nothing to the fit; the rendering covers a fraction of its crop."""
    if weights.shape[1] == 0:
        return points, targets, weights
    n = int((weights > 0).sum(dim=1).max())
    if n == weights.shape[1]:
        return points, targets, weights
    order = torch.argsort((weights > 0).to(torch.int8), dim=1, descending=True, stable=True)[:, :n]
    return (torch.gather(points, 1, order[..., None].expand(-1, -1, 3)),
            torch.gather(targets, 1, order[..., None].expand(-1, -1, 2)), torch.gather(weights, 1, order))


def solve_pose(TCO: Tensor, K_crop: Tensor, points: Tensor, targets: Tensor, weights: Tensor,
               iterations: int = GN_ITERATIONS, huber_px: float = HUBER_PX) -> Tensor:
    """Weighted robust PnP from the current pose (float64).

    ``TCO [B,4,4]`` (m) the current pose; ``points [B,N,3]`` camera-frame 3D points at that pose;
    ``targets [B,N,2]`` their image positions (crop px, ``K_crop [B,3,3]``); ``weights [B,N] >= 0``.
    Returns ``TCO_new [B,4,4]``: ``R_new = dR R``, ``t_new`` (the object origin moves with the points).
    """
    TCO, K_crop = TCO.double(), K_crop.double()
    points, targets, weights = weighted_cells(points, targets, weights)
    B, N = weights.shape
    centred = points - TCO[:, None, :3, 3]
    eye6 = torch.eye(6, dtype=torch.float64, device=TCO.device)
    dR = torch.eye(3, dtype=torch.float64, device=TCO.device).expand(B, 3, 3)
    t = TCO[:, :3, 3]
    f = torch.stack([K_crop[:, 0, 0], K_crop[:, 1, 1]], dim=-1)[:, None]  # [B,1,2]
    c = torch.stack([K_crop[:, 0, 2], K_crop[:, 1, 2]], dim=-1)[:, None]
    for _ in range(iterations):
        P = centred @ dR.transpose(1, 2)
        Y = P + t[:, None]
        z = Y[..., 2:].clamp(min=1e-3)
        residual = f * Y[..., :2] / z + c - targets  # [B,N,2]
        # d(projection)/dY, row k: f_k / z on axis k, -f_k Y_k / z^2 on z; d/d(rotation) of row a is P x a
        J_y = torch.zeros(B, N, 2, 3, dtype=torch.float64, device=TCO.device)
        J_y[..., 0, 0] = f[..., 0] / z[..., 0]
        J_y[..., 1, 1] = f[..., 1] / z[..., 0]
        J_y[..., :, 2] = -f * Y[..., :2] / z ** 2
        J = torch.cat([torch.linalg.cross(P[:, :, None].expand(-1, -1, 2, -1), J_y, dim=-1), J_y], dim=-1)
        e = residual.norm(dim=-1)
        w = weights * torch.where(e < huber_px, torch.ones_like(e), huber_px / e.clamp(min=1e-12))
        Jw = (J * w[..., None, None]).reshape(B, 2 * N, 6)
        J2 = J.reshape(B, 2 * N, 6)
        H = Jw.transpose(1, 2) @ J2
        g = (Jw.transpose(1, 2) @ residual.reshape(B, 2 * N, 1))[..., 0]
        H = H + DAMPING * torch.diag_embed(torch.diagonal(H, dim1=1, dim2=2)) + 1e-12 * eye6
        step = -torch.linalg.solve(H, g[..., None])[..., 0]
        dR = so3_exp(step[:, :3]) @ dR
        t = t + step[:, 3:]
    top = torch.cat([dR @ TCO[:, :3, :3], t[:, :, None]], dim=2)
    return torch.cat([top, TCO[:, 3:]], dim=1)


@full_precision
def pose_from_flow(TCO: Tensor, K_crop: Tensor, depth: Tensor, flow: Tensor, stride: int,
                   iterations: int = GN_ITERATIONS) -> Tensor:
    """``TCO_new [B,4,4]`` (float64) from the flow network's output ``flow [B,3,h,w]`` (displacement
    x, y in crop px of each rendered cell, confidence in [0, 1]) and the rendering's ``depth
    [B,1,H,W]`` (m) at the current poses ``TCO [B,4,4]`` with intrinsics ``K_crop [B,3,3]``."""
    TCO, flow = TCO.double(), flow.double()
    B, channels, h, w = flow.shape
    uv = cell_centres((h, w), stride, flow.device)
    d = sample_cells(depth, stride, (h, w))
    X = backproject(uv, d, K_crop).reshape(B, -1, 3)
    finite = torch.isfinite(flow).all(dim=1).reshape(B, -1)  # a cell with a NaN output is no correspondence
    safe = torch.where(torch.isfinite(flow), flow, torch.zeros_like(flow))
    targets = (uv[None] + safe[:, :2].permute(0, 2, 3, 1)).reshape(B, -1, 2)
    weights = torch.where((d > 0).reshape(B, -1) & finite, safe[:, 2].clamp(0.0, 1.0).reshape(B, -1),
                          torch.zeros_like(finite, dtype=torch.float64))
    enough = (weights > 0).sum(dim=1) >= MIN_CELLS
    out = TCO.clone()
    if bool(enough.any()):
        out[enough] = solve_pose(TCO[enough], K_crop[enough], X[enough], targets[enough], weights[enough], iterations)
    if channels > 3 and bool(enough.any()):
        out[enough] = with_depth_ratio(out[enough], TCO[enough, 2, 3], safe[enough, 3].reshape(-1, h * w),
                                       weights[enough])
    ok = torch.isfinite(out).all(dim=2).all(dim=1) & (out[:, 2, 3] > 0)
    return torch.where(ok[:, None, None], out, TCO)


def mean_depth_ratio(log_ratios: Tensor, weights: Tensor) -> Tensor:
    """``[B]``: the ``weights``-weighted mean of per-cell log depth ratios ``[B, N]`` (0 without weight)."""
    return (log_ratios * weights).sum(dim=1) / weights.sum(dim=1).clamp(min=1e-12)


def with_depth_ratio(TCO: Tensor, depth_in: Tensor, log_ratios: Tensor, weights: Tensor) -> Tensor:
    """``TCO [B,4,4]`` with its translation scaled along its line of sight to the depth
    ``depth_in [B] * exp(mean log ratio)`` (:func:`mean_depth_ratio`); a translation behind the
    camera is left as it is (the caller rejects it)."""
    depth = depth_in * mean_depth_ratio(log_ratios, weights).exp()
    z = TCO[:, 2, 3]
    scale = torch.where(z > 0, depth / torch.where(z > 0, z, torch.ones_like(z)), torch.ones_like(z))
    out = TCO.clone()
    out[:, :3, 3] = TCO[:, :3, 3] * scale[:, None]
    return out


def flow_confidence(depth: Tensor, flow: Tensor, stride: int) -> Tensor:
    """``[B]`` float64: the flow network's mean confidence over the rendered cells (those the solver
    uses) of each item, 0 for an item with no rendered cell; how well the rendering was recognised
    in the crop, used to choose among candidate poses."""
    B, _, h, w = flow.shape
    on = sample_cells(depth, stride, (h, w)) > 0
    conf = torch.nan_to_num(flow[:, 2].double(), nan=0.0).clamp(0.0, 1.0)
    return (conf * on).sum(dim=(1, 2)) / on.sum(dim=(1, 2)).clamp(min=1)
