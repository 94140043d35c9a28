"""The pose update of a flow refiner, numpy twin of :mod:`cosy_lite.models.flow_pose_solver` (for the
onnxruntime path, :mod:`cosy_lite.inference.iterate_np`; no torch): robust Gauss-Newton PnP of the
rendering's cells (3D from its depth) to their flow targets, rotation about the object origin. The
algorithm, its fallbacks (too few confident cells, a non-finite solution: the input pose is kept) and
the constants below are the torch solver's; the results are equal (tests/test_flow_refiner.py).
"""

from __future__ import annotations

import numpy as np

FLOW_STRIDE = 8  # px per cell of the flow field (FlowPoseNet.stride; here so that numpy-only code has it)
MIN_CELLS = 6  # correspondences needed for a pose (6 unknowns)
GN_ITERATIONS = 10
HUBER_PX = 2.0  # crop pixels: residuals beyond weigh 1/|r|
DAMPING = 1e-3  # Levenberg-Marquardt on the Gauss-Newton diagonal


def cell_centres(shape: tuple[int, int], stride: int) -> np.ndarray:
    """``[h,w,2]`` crop-pixel coordinates ``(u, v)`` of the centres of an ``h x w`` grid of stride ``stride``
    (crop pixel ``j`` covers ``[j, j+1)``: the centre of cell ``i`` is ``i s + s / 2``)."""
    h, w = shape
    v, u = np.meshgrid(np.arange(h) * stride + stride / 2, np.arange(w) * stride + stride / 2, indexing="ij")
    return np.stack([u, v], axis=-1).astype(np.float64)


def sample_cells(depth: np.ndarray, stride: int, shape: tuple[int, int]) -> np.ndarray:
    """Depth ``[B,H,W]`` (m, 0 = no object) at the centre pixel of each stride cell: ``[B,h,w]``."""
    h, w = shape
    d = np.asarray(depth, dtype=np.float64)[:, stride // 2::stride, stride // 2::stride][:, :h, :w]
    if d.shape[1:] != (h, w):
        raise ValueError(f"depth {tuple(depth.shape)} has no {h}x{w} cells of stride {stride}")
    return d


def backproject(uv: np.ndarray, depth: np.ndarray, K_crop: np.ndarray) -> np.ndarray:
    """Camera-frame points ``[B,h,w,3]`` of the pixels ``uv [h,w,2]`` at depths ``[B,h,w]`` (m)."""
    uv1 = np.concatenate([uv, np.ones_like(uv[..., :1])], axis=-1)
    rays = np.einsum("bij,hwj->bhwi", np.linalg.inv(K_crop), uv1)
    return rays * depth[..., None]


def _skew(w: np.ndarray) -> np.ndarray:
    z = np.zeros_like(w[..., 0])
    return np.stack([np.stack([z, -w[..., 2], w[..., 1]], -1), np.stack([w[..., 2], z, -w[..., 0]], -1),
                     np.stack([-w[..., 1], w[..., 0], z], -1)], axis=-2)


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[B,3,3]`` of axis-angle vectors ``w [B,3]`` (Rodrigues)."""
    theta = np.linalg.norm(w, axis=-1)[:, None, None]
    k = _skew(w / np.maximum(theta[:, :, 0], 1e-12))
    return np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * (k @ k)


def solve_pose(TCO: np.ndarray, K_crop: np.ndarray, points: np.ndarray, targets: np.ndarray, weights: np.ndarray,
               iterations: int = GN_ITERATIONS, huber_px: float = HUBER_PX) -> np.ndarray:
    """Weighted robust PnP from the current pose.

    ``TCO [B,4,4]`` (m) the current pose; ``points [B,N,3]`` camera-frame 3D points at that pose;
    ``targets [B,N,2]`` their image positions (crop px, ``K_crop [B,3,3]``); ``weights [B,N] >= 0``.
    Returns ``TCO_new [B,4,4]``: ``R_new = dR R``, ``t_new`` (the object origin moves with the points).
    """
    TCO = np.asarray(TCO, dtype=np.float64)
    B = len(TCO)
    centred = points - TCO[:, None, :3, 3]
    dR = np.repeat(np.eye(3)[None], B, axis=0)
    t = TCO[:, :3, 3].copy()
    fx, fy = K_crop[:, 0, 0, None], K_crop[:, 1, 1, None]
    cx, cy = K_crop[:, 0, 2, None], K_crop[:, 1, 2, None]
    for _ in range(iterations):
        P = np.einsum("bij,bnj->bni", dR, centred)
        Y = P + t[:, None]
        z = np.maximum(Y[..., 2], 1e-3)
        residual = np.stack([fx * Y[..., 0] / z + cx, fy * Y[..., 1] / z + cy], axis=-1) - targets
        zero = np.zeros_like(z)
        J_y = np.stack([np.stack([fx / z, zero, -fx * Y[..., 0] / z ** 2], -1),
                        np.stack([zero, fy / z, -fy * Y[..., 1] / z ** 2], -1)], axis=-2)  # [B,N,2,3]
        J = np.concatenate([-J_y @ _skew(P), J_y], axis=-1)  # d/d(rotation about the origin, translation)
        e = np.linalg.norm(residual, axis=-1)
        w = weights * np.where(e < huber_px, 1.0, huber_px / np.maximum(e, 1e-12))
        H = np.einsum("bnki,bn,bnkj->bij", J, w, J)
        g = np.einsum("bnki,bn,bnk->bi", J, w, residual)
        H = H + DAMPING * np.einsum("bii->bi", H)[:, :, None] * np.eye(6) + 1e-12 * np.eye(6)
        step = -np.linalg.solve(H, g[..., None])[..., 0]
        dR = so3_exp(step[:, :3]) @ dR
        t = t + step[:, 3:]
    out = TCO.copy()
    out[:, :3, :3] = dR @ TCO[:, :3, :3]
    out[:, :3, 3] = t
    return out


def pose_from_flow(TCO: np.ndarray, K_crop: np.ndarray, depth: np.ndarray, flow: np.ndarray, stride: int) -> np.ndarray:
    """``TCO_new [B,4,4]`` from the flow network's output ``flow [B,3,h,w]`` (displacement x, y in crop
    px of each rendered cell, confidence in [0, 1]) and the rendering's ``depth [B,H,W]`` or
    ``[B,1,H,W]`` (m) at the current poses ``TCO [B,4,4]`` with intrinsics ``K_crop [B,3,3]``."""
    TCO = np.asarray(TCO, dtype=np.float64)
    K_crop = np.asarray(K_crop, dtype=np.float64)
    flow = np.asarray(flow, dtype=np.float64)
    depth = np.asarray(depth)
    if depth.ndim == 4:
        depth = depth[:, 0]
    B, _, h, w = flow.shape
    uv = cell_centres((h, w), stride)
    d = sample_cells(depth, stride, (h, w))
    X = backproject(uv, d, K_crop).reshape(B, -1, 3)
    targets = (uv[None] + flow[:, :2].transpose(0, 2, 3, 1)).reshape(B, -1, 2)
    finite = np.isfinite(flow).all(axis=1).reshape(B, -1)  # a cell with a NaN output is no correspondence
    weights = np.where(d > 0, np.clip(np.nan_to_num(flow[:, 2], nan=0.0), 0.0, 1.0), 0.0).reshape(B, -1)
    weights = np.where(finite, weights, 0.0)
    targets = np.where(finite[..., None], targets, 0.0)
    enough = (weights > 0).sum(axis=1) >= MIN_CELLS
    new = TCO.copy()
    if enough.any():
        new[enough] = solve_pose(TCO[enough], K_crop[enough], X[enough], targets[enough], weights[enough])
    bad = ~np.isfinite(new).all(axis=(1, 2)) | (new[:, 2, 3] <= 0)
    new[bad] = TCO[bad]
    return new


def flow_confidence(depth: np.ndarray, flow: np.ndarray, stride: int) -> np.ndarray:
    """``[B]`` float64: mean confidence over each item's rendered cells (0 with none). As
    :func:`cosy_lite.models.flow_pose_solver.flow_confidence`."""
    depth = np.asarray(depth)
    if depth.ndim == 4:
        depth = depth[:, 0]
    B, _, h, w = flow.shape
    on = sample_cells(depth, stride, (h, w)) > 0
    conf = np.clip(np.nan_to_num(np.asarray(flow, dtype=np.float64)[:, 2], nan=0.0), 0.0, 1.0)
    return (conf * on).sum(axis=(1, 2)) / np.maximum(on.sum(axis=(1, 2)), 1)
