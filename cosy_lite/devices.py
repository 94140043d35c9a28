"""The one device rule of training and inference: a name as given, or the GPU when there is one."""

from __future__ import annotations

import torch


def resolve_device(name: str | None, local_rank: int = 0) -> torch.device:
    """``None`` or ``"auto"``: the local GPU (``cuda:local_rank``) if there is one, else the CPU;
    otherwise ``torch.device(name)``."""
    if name is None or name == "auto":
        return torch.device(f"cuda:{local_rank}") if torch.cuda.is_available() else torch.device("cpu")
    return torch.device(name)
