"""A coarse scorer checkpoint written for tests: the ImageNet Lite0 (its first convolution scaled
by ``scale``, so 1.0 describes as the frozen templates do), ``iou_weight`` 0.25."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import torch


def scorer_file(path: Path, obj_ids: Sequence[int] = (1, 2, 5, 8), shading: str = "headlight",
                scale: float = 1.0) -> Path:
    from cosy_lite.nets.appearance_scorer import AppearanceScorer
    from cosy_lite.weights.checkpoint import Checkpoint, save_checkpoint

    net = AppearanceScorer(load_pretrained=True)
    with torch.no_grad():
        net.iou_weight.fill_(0.25)
        net.query.trunk.conv_stem.weight.mul_(scale)
    meta = {"obj_ids": list(obj_ids), "trunk": "efficientnet_lite0", "templates": {"shading": shading}}
    save_checkpoint(path, Checkpoint("scorer", net.state_dict(), {}, 1, meta=meta))
    return path
