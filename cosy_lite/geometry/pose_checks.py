"""Which estimated poses are poses at all, and the nearest rotation of a drifting one.

One policy for every render-and-compare loop (:func:`cosy_lite.nets.render_and_compare.iterate_poses`)
and for the results the predictor writes: a pose is valid when it is finite, its rotation part is
a rotation (orthonormal, det +1, within a tolerance) and the object is in front of the camera, at
least :data:`MIN_DEPTH` away. An invalid pose is neither rendered again nor written.
"""

from __future__ import annotations

import torch
from torch import Tensor

MIN_DEPTH = 0.02  # m: an estimate nearer than this (or behind the camera) is invalid (BOP: t >= 20 mm)


def valid_poses(TCO: Tensor, rotation_tol: float = 1e-3, min_depth: float = MIN_DEPTH) -> Tensor:
    """``[N]`` bool: ``TCO [N,4,4]`` finite, ``R`` orthonormal with det +1 (within ``rotation_tol``),
    z >= ``min_depth`` (m)."""
    TCO = TCO.double()
    finite = torch.isfinite(TCO).all(dim=(1, 2))
    eye = torch.eye(3, dtype=TCO.dtype, device=TCO.device)
    R = torch.where(finite[:, None, None], TCO[:, :3, :3], eye)
    ortho = (R @ R.transpose(1, 2) - eye).abs().amax(dim=(1, 2)) <= rotation_tol
    det = (torch.linalg.det(R) - 1.0).abs() <= rotation_tol
    return finite & ortho & det & (TCO[:, 2, 3].nan_to_num(nan=-1.0) >= min_depth)


def orthonormalise(TCO: Tensor) -> Tensor:
    """``TCO [N,4,4]`` float64 with each finite rotation replaced by the nearest rotation matrix (SVD)."""
    TCO = TCO.double().clone()
    ok = torch.isfinite(TCO).all(dim=(1, 2))
    if ok.any():
        U, _, Vh = torch.linalg.svd(TCO[ok, :3, :3])
        D = torch.ones(int(ok.sum()), 3, dtype=TCO.dtype, device=TCO.device)
        D[:, 2] = torch.sign(torch.linalg.det(U @ Vh))
        TCO[ok, :3, :3] = U @ torch.diag_embed(D) @ Vh
    return TCO
