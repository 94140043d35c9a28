"""The symmetry-aware disentangled point-matching loss of CosyPose (torch, metres).

The network output ``delta [B,9]`` (see :mod:`cosy_lite.nets.pose_update`) is scored by three
partial poses, each taking one part from the prediction and the others from the ground truth:

* rotation: ``(R_pred, t_gt)``, ``R_pred = dR R_in``;
* xy: ``(R_gt, [xy from the predicted pixel shift at depth z_gt, z_gt])``;
* depth: ``(R_gt, [xy_gt, vz z_in])``.

A partial pose is scored by the L1 distance per coordinate, averaged over the model points and
their 3 coordinates (CosyPose: ``loss_CO_symmetric`` with ``l1``), between the points moved by it
and by a symmetric GT pose ``GT @ S`` of the object's (discretised) symmetry set.

Choice of the symmetry. CosyPose (``lib3d/cosypose_ops.py: loss_refiner_CO_disentangled``, also
MegaPose) takes the minimum over ``S`` for each term separately, and builds the partial poses from
the unsymmetrised GT. It does not pick one symmetric GT pose once. Here every candidate ``G_S = GT @ S``
supplies both the GT parts of the partial poses and the points they are compared with; the three
terms are summed for each candidate, and the candidate with the smallest sum is scored. Then:

* the loss depends only on the set ``{GT @ S}``: it does not change when GT is replaced by ``GT @ S'``
  for a symmetry ``S'`` of the set (CosyPose's changes slightly, through the GT parts);
* it is zero exactly at the symmetric GT poses. With per-term minima, symmetries that move the
  origin (a nonzero translation, which CosyPose cannot load: it asserts zero offsets) give zeros
  at poses made of the rotation of one candidate and the translation of another;
* for symmetries that fix the origin (all of YCB-V), every candidate has the same translation, so
  the xy and depth terms do not depend on ``S`` and the joint minimum is the minimum of the
  rotation term, as in CosyPose. The values then equal CosyPose's whenever the point sample's
  centroid is fixed by the symmetries (tested).

With the candidate's rotation in the xy and depth partial poses, their point distances reduce to
translation differences: ``(|dx| + |dy|) / 3`` and ``|dz| / 3`` (the mean over 3 coordinates); only
the rotation term needs the points, ``mean |(R_pred - R_S) x|``, computed for the real entries of
the padded sets only (a batch pays for the sum of its set sizes, not B times the largest).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from cosy_lite.nets.pose_update import POSE_DIM, apply_pose_update, full_precision, rotation_update


@dataclass
class LossTerms:
    """Batch means of the loss and its terms (scalars), plus per-item values."""

    total: Tensor  # rotation + xy + depth, mean over the batch [m]
    rotation: Tensor
    xy: Tensor
    depth: Tensor
    per_item: Tensor  # [B] total of each item
    TCO_pred: Tensor  # [B,4,4] the full update applied to TCO_in (differentiable in delta)
    sym_index: Tensor  # [B] int64: index of the symmetry S whose GT @ S was scored


def _check_loss_inputs(
    TCO_in: Tensor, K_crop: Tensor, delta: Tensor, TCO_gt: Tensor, points: Tensor, symmetries: Tensor, sym_mask: Tensor
) -> None:
    B = TCO_in.shape[0]
    S = symmetries.shape[1] if symmetries.dim() == 4 else -1
    expected = {
        "TCO_in": (TCO_in, (B, 4, 4)),
        "K_crop": (K_crop, (B, 3, 3)),
        "delta": (delta, (B, POSE_DIM)),
        "TCO_gt": (TCO_gt, (B, 4, 4)),
        "symmetries": (symmetries, (B, S, 4, 4)),
        "sym_mask": (sym_mask, (B, S)),
    }
    for name, (x, shape) in expected.items():
        if tuple(x.shape) != shape:
            raise ValueError(f"{name} must be {list(shape)}, got {list(x.shape)}")
    if points.dim() != 3 or points.shape[0] != B or points.shape[2] != 3:
        raise ValueError(f"points must be [{B},N,3], got {list(points.shape)}")
    if sym_mask.dtype != torch.bool or not bool(sym_mask.any(dim=1).all()):
        raise ValueError("sym_mask must be bool with at least one True per item (the identity)")


@full_precision
def disentangled_loss(
    TCO_in: Tensor,
    K_crop: Tensor,
    delta: Tensor,
    TCO_gt: Tensor,
    points: Tensor,
    symmetries: Tensor,
    sym_mask: Tensor,
) -> LossTerms:
    """Disentangled symmetric L1 loss of the pose update ``delta [B,9]`` (see the module docstring).

    Args:
        TCO_in: [B,4,4] pose the network saw (m). K_crop: [B,3,3] intrinsics of its crop.
        delta: [B,9] network output. TCO_gt: [B,4,4] ground truth (m).
        points: [B,N,3] model points (m), e.g. :func:`cosy_lite.geometry.points.sample_model_points`.
        symmetries: [B,S,4,4] symmetry sets padded; sym_mask: [B,S] True for real entries
            (:func:`cosy_lite.geometry.points.symmetry_tensor`).
    Returns:
        :class:`LossTerms` (metres: mean absolute coordinate differences), in TCO_in's dtype
        (``delta`` is cast to it; autocast is off inside).
    """
    _check_loss_inputs(TCO_in, K_crop, delta, TCO_gt, points, symmetries, sym_mask)
    dtype = TCO_in.dtype
    delta, K_crop, TCO_gt = delta.to(dtype), K_crop.to(dtype), TCO_gt.to(dtype)
    cand = TCO_gt[:, None] @ symmetries.to(TCO_gt)  # [B,S,4,4] the symmetric GT poses
    R_c, t_c = cand[..., :3, :3], cand[..., :3, 3]

    # Rotation term: (R_pred, t_c) against (R_c, t_c), for the real (unpadded) candidates only.
    R_pred = rotation_update(delta) @ TCO_in[:, :3, :3]
    bi, si = sym_mask.nonzero(as_tuple=True)
    diff = torch.einsum("vij,vnj->vni", R_pred[bi] - R_c[bi, si], points.to(R_c)[bi])
    rot = torch.full_like(t_c[..., 0], float("inf")).index_put((bi, si), diff.abs().mean(dim=(-1, -2)))  # [B,S]

    # xy term: (R_c, [(v / f + xy_in / z_in) z_c, z_c]) against (R_c, t_c).
    f = torch.stack([K_crop[:, 0, 0], K_crop[:, 1, 1]], dim=-1)
    t_in = TCO_in[:, :3, 3]
    uv_pred = delta[:, 6:8] / f + t_in[:, :2] / t_in[:, 2:3]  # [B,2] normalised image coordinates
    xy = (uv_pred[:, None] * t_c[..., 2:3] - t_c[..., :2]).abs().sum(-1) / 3.0  # [B,S]

    # Depth term: (R_c, [xy_c, vz z_in]) against (R_c, t_c).
    z_pred = torch.exp(delta[:, 8:9]) * t_in[:, 2:3]  # [B,1]
    depth = (z_pred - t_c[..., 2]).abs() / 3.0  # [B,S]

    total = rot + xy + depth  # inf where padded
    k = total.argmin(dim=1)  # [B]
    pick = lambda x: x.gather(1, k[:, None])[:, 0]  # noqa: E731
    rot_k, xy_k, depth_k = pick(rot), pick(xy), pick(depth)
    per_item = rot_k + xy_k + depth_k
    return LossTerms(
        total=per_item.mean(),
        rotation=rot_k.mean(),
        xy=xy_k.mean(),
        depth=depth_k.mean(),
        per_item=per_item,
        TCO_pred=apply_pose_update(TCO_in, K_crop, delta),
        sym_index=k,
    )


def closest_symmetric_pose(TCO: Tensor, TCO_gt: Tensor, points: Tensor, symmetries: Tensor, sym_mask: Tensor) -> Tensor:
    """``GT @ S [B,4,4]`` nearest ``TCO [B,4,4]``: smallest mean L1 point distance over the
    masked set (for errors of symmetric objects, e.g. a rotation error in validation). No gradient."""
    with torch.no_grad():
        cand = TCO_gt[:, None] @ symmetries.to(TCO_gt)
        p = points.to(TCO_gt)
        moved_gt = torch.einsum("bsij,bnj->bsni", cand[..., :3, :3], p) + cand[..., None, :3, 3]
        moved = torch.einsum("bij,bnj->bni", TCO[:, :3, :3].to(p), p) + TCO[:, None, :3, 3].to(p)
        dist = (moved_gt - moved[:, None]).abs().mean(dim=(-1, -2)).masked_fill(~sym_mask, float("inf"))
        return cand[torch.arange(len(TCO)), dist.argmin(dim=1)]
