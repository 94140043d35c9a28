"""Model points and symmetry sets as batched tensors, for the pose loss (metres).

Typical use: once per dataset, ``points = torch.stack([sample_model_points(...) for each object])``
``[O,N,3]`` and ``symmetries, mask = symmetry_tensor([object_symmetries(info) for each object])``
``[O,S,4,4]``, ``[O,S]``; per batch, index them with the batch's object indices.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from cosy_lite.geometry.symmetries import SymmetryInfo, symmetry_transforms

N_POINTS = 2000  # CosyPose: 2000 points for the crop boxes, 2600 for the loss (n_points_loss)
N_CONTINUOUS = 64  # steps of a continuous symmetry for training, as CosyPose (the BOP evaluation uses 315)


def sample_model_points(
    vertices: np.ndarray | Tensor,
    n: int = N_POINTS,
    seed: int = 0,
    faces: np.ndarray | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """``[n,3]`` points of a model (``vertices [V,3]``, metres), deterministic for a given ``seed``.

    With ``faces [F,3]``: uniform over the surface area (trimesh). Without: a random subset of the
    vertices (all of them, then repeats, when ``V < n``).
    """
    v = np.asarray(vertices.detach().cpu() if isinstance(vertices, Tensor) else vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"vertices must be [V,3] with V >= 1, got {v.shape}")
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if faces is not None:
        import trimesh

        mesh = trimesh.Trimesh(vertices=v, faces=np.asarray(faces), process=False)
        pts, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
        return torch.as_tensor(np.asarray(pts), dtype=dtype)
    rng = np.random.default_rng(seed)
    if len(v) >= n:
        idx = rng.choice(len(v), n, replace=False)
    else:
        idx = np.concatenate([np.arange(len(v)), rng.choice(len(v), n - len(v), replace=True)])
    return torch.as_tensor(v[idx], dtype=dtype)


def object_symmetries(info: SymmetryInfo, n_continuous: int = N_CONTINUOUS) -> np.ndarray:
    """The symmetry set ``[S,4,4]`` (m) of an object, identity first, each continuous symmetry
    discretised into ``n_continuous`` rotations (``k 2 pi / n_continuous``, k = 0..n-1), composed
    with the discrete ones as :func:`~cosy_lite.geometry.symmetries.symmetry_transforms` does."""
    if n_continuous < 1:
        raise ValueError(f"n_continuous must be >= 1, got {n_continuous}")
    # symmetry_transforms uses n = ceil(pi / step) steps; a step a hair above pi / n gives exactly n.
    S = symmetry_transforms(info, max_sym_disc_step=math.pi / n_continuous * (1 + 1e-9), include_zero_angle=True)
    if not np.allclose(S[0], np.eye(4)):
        raise AssertionError("symmetry_transforms must list the identity first")
    return S


def symmetry_tensor(sets: Sequence[np.ndarray | Tensor], dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
    """Stack symmetry sets ``[S_i,4,4]`` into ``padded [B,S,4,4]`` (padding: identity) and
    ``mask [B,S]`` (True for real entries), ``S = max S_i``."""
    mats = [torch.as_tensor(np.asarray(s) if not isinstance(s, Tensor) else s, dtype=dtype) for s in sets]
    for i, m in enumerate(mats):
        if m.dim() != 3 or m.shape[1:] != (4, 4) or m.shape[0] < 1:
            raise ValueError(f"symmetry set {i} must be [S>=1,4,4], got {tuple(m.shape)}")
    S = max((m.shape[0] for m in mats), default=1)
    padded = torch.eye(4, dtype=dtype).repeat(len(mats), S, 1, 1)
    mask = torch.zeros(len(mats), S, dtype=torch.bool)
    for i, m in enumerate(mats):
        padded[i, : len(m)] = m
        mask[i, : len(m)] = True
    return padded, mask
