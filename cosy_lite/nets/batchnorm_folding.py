"""BatchNorm folded into the convolution before it, for inference: one convolution instead of two passes.

Measured (bench/RESULTS.md, session 32): the flow refiner's 35 BatchNorms took 16 % of a torch inference;
folded, its forward pass is 1.48x faster at 144x192 with outputs equal to 3e-6 of their magnitude.
"""

from __future__ import annotations

import copy
import warnings

import torch
from torch import nn


def fold_batchnorm(net: nn.Module) -> int:
    """Fold, in place, every eval-mode BatchNorm2d that follows a Conv2d among its parent's children
    (registration order, as in timm's EfficientNet blocks and ``nn.Sequential``) into that convolution;
    the norm is replaced by what it applied after normalising (timm's ``BatchNormAct2d``: its dropout and
    activation; else nothing). Returns how many were folded. Registration order is not data flow:
    :func:`batchnorm_folded` checks the outputs."""
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    folded = 0
    for parent in list(net.modules()):
        names = list(parent._modules)
        for a, b in zip(names, names[1:]):
            conv, norm = parent._modules[a], parent._modules[b]
            if (isinstance(conv, nn.Conv2d) and isinstance(norm, nn.BatchNorm2d) and not norm.training
                    and norm.running_mean is not None and norm.running_var is not None
                    and norm.num_features == conv.out_channels):
                setattr(parent, a, fuse_conv_bn_eval(conv, norm))
                after = [m for m in (getattr(norm, "drop", None), getattr(norm, "act", None)) if isinstance(m, nn.Module)]
                setattr(parent, b, nn.Sequential(*after) if after else nn.Identity())
                folded += 1
    return folded


def batchnorm_folded(net: nn.Module, example_shape: tuple[int, ...] | None = None) -> nn.Module:
    """A copy of the eval-mode ``net`` with its BatchNorms folded (:func:`fold_batchnorm`), or ``net``
    itself when there is nothing to fold or, with ``example_shape``, when the copy's outputs on a random
    input of that shape differ from ``net``'s by more than 1e-3 of their largest magnitude (a warning)."""
    folded = copy.deepcopy(net)
    if not fold_batchnorm(folded):
        return net
    if example_shape is None:
        return folded
    device = next(net.parameters()).device
    x = torch.rand(*example_shape, generator=torch.Generator().manual_seed(0)).to(device)
    with torch.no_grad():
        a, b = net(x), folded(x)
    pairs = list(zip(a, b)) if isinstance(a, (tuple, list)) else [(a, b)]
    if all(torch.allclose(u.float(), v.float(), rtol=0, atol=1e-3 * (float(u.abs().max()) + 1e-6)) for u, v in pairs):
        return folded
    warnings.warn(f"{type(net).__name__} with BatchNorm folded gives other outputs; it runs unfolded",
                  RuntimeWarning, stacklevel=2)
    return net
