"""The coarse network that scores hypotheses: a trained view of the detection against fixed templates.

:mod:`cosy_lite.nets.appearance_templates` ranks an object's 2,048 template rotations by the
cosine similarity of frozen ImageNet features (textured template rendering against the image inside
the detection mask) + silhouette IoU. Frozen features see a rendering and a photograph of the same
view as different things (light, noise, blur, occlusion): the best-scored template is within 30 deg
for only half of the test instances, although one of the 2,048 always is.

:class:`AppearanceScorer` learns the detection side only: an ImageNet EfficientNet-Lite0 (the same
trunk as the templates', up to stride 16) trained so that the image crop lands next to the frozen
descriptors of the templates close to its pose. The templates keep their frozen descriptors (cached
once per mesh, as before), so scoring a detection costs one small forward pass and one
``[2048, D] @ [D]`` product, and the cached templates of an untrained set stay valid. Its
``iou_weight`` (the silhouette's share of the score) is learned with it.

Loss (:func:`listwise_loss`): softmax over all templates of the object, ``logit_scale x score``,
against the uniform distribution over the templates within ``positive_deg`` of the GT rotation
(symmetry-aware; the closest one always counts): a ranking loss over the whole hypothesis set,
not a regression, which learns from few samples (bench/RESULTS.md, "Coarse scorer").
"""

from __future__ import annotations

import math
from typing import Mapping

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from cosy_lite.nets.appearance_templates import AppearanceDescriptor


class AppearanceScorer(nn.Module):
    """``[B,3,S,S]`` crops in [0, 1] (as :func:`~cosy_lite.nets.appearance_templates.square_crops`
    cuts them) -> ``[B,D]`` descriptors comparable with the frozen template descriptors.

    Its BatchNorm layers keep the ImageNet statistics in training too (their affine weights train):
    the templates are described with those statistics, and batches of 32 crops of one scene would
    be poor estimates of them."""

    def __init__(self, trunk: str = "efficientnet_lite0", load_pretrained: bool = True, iou_weight: float = 0.5,
                 logit_scale: float = 20.0):
        super().__init__()
        self.trunk_name = trunk
        self.query = AppearanceDescriptor(trunk, load_weights=load_pretrained)
        self.iou_weight = nn.Parameter(torch.tensor(float(iou_weight)))
        self.log_logit_scale = nn.Parameter(torch.tensor(math.log(logit_scale)))

    def train(self, mode: bool = True) -> "AppearanceScorer":
        super().train(mode)
        for m in self.modules():
            if isinstance(m, nn.modules.batchnorm._BatchNorm):
                m.eval()
        return self

    def forward(self, crops: Tensor) -> Tensor:
        return self.query(crops)

    def scores(self, descriptors: Tensor, obj_ids: Tensor, template_descriptors: Mapping[int, Tensor],
               iou: Tensor) -> Tensor:
        """``[B,N]``: each detection's ``descriptors [B,D]`` against the ``[N,D]`` template descriptors
        of its object (``template_descriptors[obj_ids[b]]``), + ``iou_weight`` x its silhouette IoU
        ``iou [B,N]`` (one product per object in the batch, no ``[B,N,D]`` copy)."""
        similarity = torch.empty_like(iou, dtype=descriptors.dtype)
        for o in torch.unique(obj_ids).tolist():
            rows = obj_ids == o
            similarity[rows] = descriptors[rows] @ template_descriptors[int(o)].to(descriptors.device).T
        return similarity + self.iou_weight * iou


def listwise_loss(scores: Tensor, errors_deg: Tensor, logit_scale: Tensor, positive_deg: float = 15.0) -> Tensor:
    """Cross-entropy of ``softmax(logit_scale x scores [B,N])`` against the uniform distribution over
    the hypotheses whose rotation error ``errors_deg [B,N]`` is under ``positive_deg`` (the closest
    one always included)."""
    target = (errors_deg < positive_deg).float()
    target[torch.arange(len(target)), errors_deg.argmin(dim=1)] = 1.0
    target = target / target.sum(dim=1, keepdim=True)
    return -(target * F.log_softmax(logit_scale * scores, dim=1)).sum(dim=1).mean()


def flip_loss(scores: Tensor, errors_deg: Tensor, logit_scale: Tensor, flipped_deg: float) -> Tensor:
    """The hard negative the listwise loss does not single out: ``softplus(logit_scale x (best
    score of a hypothesis more than flipped_deg off - score of the closest hypothesis))`` [B,N] ->
    scalar, averaged over the instances that have such a hypothesis (0 when none has)."""
    flipped = errors_deg > flipped_deg
    has = flipped.any(dim=1)
    if not bool(has.any()):
        return scores.sum() * 0.0
    closest = scores.gather(1, errors_deg.argmin(dim=1, keepdim=True))[:, 0]
    worst = scores.masked_fill(~flipped, float("-inf")).max(dim=1).values
    return F.softplus(logit_scale * (worst[has] - closest[has])).mean()
