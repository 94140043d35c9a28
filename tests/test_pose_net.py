"""Backbone table and PoseNet: shapes, identity update at init, ONNX export (legacy + dynamo)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from cosy_lite.nets.backbones import BACKBONES, Backbone
from cosy_lite.nets.pose_net import PoseNet

H, W = 120, 160
FEATURES = {"resnet18": 512, "resnet34": 512, "resnet50": 2048, "efficientnet_b0": 1280,
            "efficientnet_b3": 1536, "mobilenet_v3_small": 576, "mobilenet_v3_large": 960}


@pytest.mark.parametrize("norm", ["batch", "group"])
def test_backbones_take_six_channels_and_pool(norm):
    assert set(BACKBONES) == set(FEATURES)
    x = torch.rand(2, 6, 64, 64)
    for name, n in FEATURES.items():
        b = Backbone(name, in_channels=6, norm=norm).eval()
        assert b.out_features == n
        assert b(x).shape == (2, n), name
        norms = [m for m in b.modules() if isinstance(m, (torch.nn.BatchNorm2d, torch.nn.GroupNorm))]
        assert norms and all(isinstance(m, torch.nn.GroupNorm if norm == "group" else torch.nn.BatchNorm2d) for m in norms)
        assert all(p.requires_grad for p in b.parameters())


def test_unknown_backbone_lists_the_names():
    with pytest.raises(ValueError, match="efficientnet_b0.*resnet18"):
        Backbone("vgg16")
    with pytest.raises(ValueError, match="norm"):
        Backbone("resnet18", norm="layer")


def test_untrained_net_outputs_identity_update_and_learns():
    torch.manual_seed(0)
    net = PoseNet("resnet18")
    x = torch.rand(4, 6, H, W)
    delta = net(x)
    assert delta.shape == (4, 9)
    assert torch.equal(delta, torch.zeros(4, 9))  # 6D residual 0, shift 0, log vz 0
    delta.sum().backward()
    assert net.head.weight.grad.abs().sum() > 0  # the zero head still gets a gradient
    with pytest.raises(ValueError, match=r"\[B,6,H,W\]"):
        net(torch.rand(1, 3, H, W))


def test_normalisation_is_inside_the_module():
    net = PoseNet("resnet18").eval()
    assert torch.allclose(net.mean.flatten(), torch.tensor([0.485, 0.456, 0.406] * 2))
    assert torch.allclose(net.std.flatten(), torch.tensor([0.229, 0.224, 0.225] * 2))
    assert "mean" not in net.state_dict()  # not a weight: checkpoints stay backbone + head


def _random_head(net: PoseNet) -> PoseNet:
    torch.manual_seed(1)
    torch.nn.init.normal_(net.head.weight, std=0.02)
    torch.nn.init.normal_(net.head.bias, std=0.02)
    return net.eval()


def _check_onnx(path, net: PoseNet) -> None:
    ort = pytest.importorskip("onnxruntime")
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for batch in (1, 8):
        x = torch.rand(batch, 6, H, W, generator=torch.Generator().manual_seed(batch))
        with torch.no_grad():
            ref = net(x).numpy()
        (out,) = session.run(None, {"images": x.numpy()})
        assert out.shape == (batch, 9)
        assert np.abs(ref).max() > 0.01  # a non-trivial output is compared
        np.testing.assert_allclose(out, ref, atol=1e-4, rtol=0)


def test_onnx_legacy_export_dynamic_batch(tmp_path):
    net = _random_head(PoseNet("resnet18"))
    path = tmp_path / "pose_legacy.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(net, (torch.rand(1, 6, H, W),), path, dynamo=False, opset_version=17,
                          input_names=["images"], output_names=["delta"],
                          dynamic_axes={"images": {0: "batch"}, "delta": {0: "batch"}})
    _check_onnx(path, net)


def test_onnx_dynamo_export_dynamic_batch(tmp_path):
    pytest.importorskip("onnxscript")  # the dynamo exporter needs it; not a project dependency
    net = _random_head(PoseNet("resnet18"))
    path = tmp_path / "pose_dynamo.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(net, (torch.rand(2, 6, H, W),), path, dynamo=True, input_names=["images"],
                          output_names=["delta"], dynamic_shapes=({0: torch.export.Dim("batch")},), verbose=False)
    _check_onnx(path, net)
