"""Per-object tensors the pose networks need, indexed by obj_id: model points (for crops and the
loss), padded symmetry sets (for the loss and symmetric errors) and diameters (for initial poses)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.geometry.points import N_CONTINUOUS, N_POINTS, object_symmetries, sample_model_points, symmetry_tensor


@dataclass
class ObjectTable:
    """obj_ids [O]; points [O,N,3] (m); symmetries [O,S,4,4] (m) + sym_mask [O,S]; diameters [O] (m)."""

    obj_ids: list[int]
    points: Tensor
    symmetries: Tensor
    sym_mask: Tensor
    diameters: Tensor

    @classmethod
    def from_dataset(cls, dataset: BopDataset, obj_ids: Sequence[int] | None = None, n_points: int = N_POINTS,
                     n_continuous: int = N_CONTINUOUS) -> "ObjectTable":
        """Points sampled on each model's surface (seeded by obj_id), symmetries from models_info."""
        infos = dataset.models_info
        ids = sorted(infos) if not obj_ids else [int(i) for i in obj_ids]
        for i in ids:
            if i not in infos:
                raise KeyError(f"{dataset.models_dir / 'models_info.json'}: no obj_id {i}; known: {sorted(infos)}")
        points, syms = [], []
        for i in ids:
            mesh = dataset.load_model(i)
            points.append(sample_model_points(np.asarray(mesh.vertices), n_points, seed=i, faces=np.asarray(mesh.faces)))
            syms.append(object_symmetries(infos[i], n_continuous))
        padded, mask = symmetry_tensor(syms)
        diameters = torch.tensor([infos[i].diameter for i in ids], dtype=torch.float32)
        return cls(ids, torch.stack(points), padded, mask, diameters)

    def index(self, obj_ids: Tensor | Sequence[int]) -> Tensor:
        """Rows of ``obj_ids`` [B] in this table (KeyError naming an unknown id)."""
        lookup = {o: k for k, o in enumerate(self.obj_ids)}
        ids = obj_ids.tolist() if isinstance(obj_ids, Tensor) else list(obj_ids)
        missing = [i for i in ids if i not in lookup]
        if missing:
            raise KeyError(f"obj_id(s) {sorted(set(missing))} not in this model's objects {self.obj_ids}")
        return torch.tensor([lookup[i] for i in ids], dtype=torch.long)

    def to(self, device: torch.device | str) -> "ObjectTable":
        return ObjectTable(self.obj_ids, self.points.to(device), self.symmetries.to(device),
                           self.sym_mask.to(device), self.diameters.to(device))
