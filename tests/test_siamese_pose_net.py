"""SiamesePoseNet: correlation and soft-argmax layers, identity at init, pretrained trunk, ONNX."""

import numpy as np
import pytest
import torch

from cosy_lite.nets.pretrained import timm_state_dict
from cosy_lite.nets.siamese_pose_net import SiamesePoseNet, local_correlation, spatial_soft_argmax
from cosy_lite.weights.pose_nets import PoseNetConfig, build_pose_net


def test_correlation_peaks_at_the_displacement():
    torch.manual_seed(0)
    b = torch.randn(1, 16, 12, 16)
    a = torch.roll(b, shifts=(1, -2), dims=(2, 3))  # a(p) = b(p - (dy, dx)) with dy=1, dx=-2
    corr = local_correlation(a, b, radius=3)
    assert corr.shape == (1, 49, 12, 16)
    peak = corr[0, :, 4:8, 4:12].mean(dim=(1, 2)).argmax().item()  # away from the borders
    dy, dx = divmod(peak, 7)
    assert (dy - 3, dx - 3) == (-1, 2)  # b(p + d) = a(p) for d = (-1, +2)
    assert torch.allclose(corr[0, 24], (a * b).mean(1)[0])  # zero displacement = channel mean of a*b


def test_soft_argmax_finds_a_peak():
    x = torch.full((1, 2, 6, 8), -50.0)
    x[0, 0, 0, 7] = 50.0  # top right
    x[0, 1, 5, 0] = 50.0  # bottom left
    out = spatial_soft_argmax(x)
    assert torch.allclose(out, torch.tensor([[1.0, -1.0, -1.0, 1.0]]), atol=1e-6)  # (x0, x1, y0, y1)


def test_identity_at_init_gradient_and_shape_checks():
    torch.manual_seed(0)
    net = SiamesePoseNet(pretrained=False, crop_resolution=(96, 128), flat_channels=8)
    x = torch.rand(3, 6, 96, 128)
    delta = net(x)
    assert torch.equal(delta, torch.zeros(3, 9))
    delta.sum().backward()
    assert net.head.weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match=r"\[B,6,H,W\]"):
        net(torch.rand(1, 3, 96, 128))


def test_pretrained_trunk_and_checkpoint_rebuild():
    cfg = PoseNetConfig(arch="siamese", backbone="efficientnet_lite0", crop_resolution=[96, 128])
    net = build_pose_net(cfg, "refiner")
    full = timm_state_dict("efficientnet_lite0")
    assert torch.equal(net.trunk.state_dict()["conv_stem.weight"], full["conv_stem.weight"])
    rebuilt = build_pose_net(cfg, "refiner", load_weights=False)  # no file read: weights come next
    assert not torch.equal(rebuilt.trunk.state_dict()["conv_stem.weight"], full["conv_stem.weight"])
    rebuilt.load_state_dict(net.state_dict())
    x = torch.rand(2, 6, 96, 128)
    torch.manual_seed(1)
    torch.nn.init.normal_(net.head.weight, std=0.1)
    rebuilt.load_state_dict(net.state_dict())
    assert torch.allclose(net.eval()(x), rebuilt.eval()(x))


def test_onnx_export_matches_torch(tmp_path):
    pytest.importorskip("onnxruntime")
    import onnxruntime as ort

    torch.manual_seed(0)
    net = SiamesePoseNet(pretrained=False, crop_resolution=(96, 128), flat_channels=8).eval()
    torch.nn.init.normal_(net.head.weight, std=0.1)
    x = torch.rand(2, 6, 96, 128)
    path = tmp_path / "siam.onnx"
    torch.onnx.export(net, (x,), str(path), input_names=["images"], output_names=["delta"], opset_version=17,
                      dynamic_axes={"images": {0: "batch"}, "delta": {0: "batch"}}, dynamo=False)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for n in (1, 3):
        xb = torch.rand(n, 6, 96, 128)
        ref = net(xb).detach().numpy()
        got = sess.run(None, {"images": xb.numpy()})[0]
        np.testing.assert_allclose(got, ref, atol=1e-4, rtol=1e-4)


def test_flattened_map_needs_a_crop_divisible_by_16():
    with pytest.raises(ValueError, match="divisible by 16"):
        SiamesePoseNet(pretrained=False, crop_resolution=(90, 120), flat_channels=8)
    net = SiamesePoseNet(pretrained=False, crop_resolution=(96, 128), flat_channels=8)
    assert net.head.in_features == 3 * 256 + 8 * 6 * 8


def test_scale_mix_noise_is_smaller_in_training_only():
    from cosy_lite.geometry.rotations import rotation_angle_deg
    from cosy_lite.train.pose_task import PoseNoiseConfig, initial_poses

    T = torch.eye(4, dtype=torch.float64).repeat(400, 1, 1)
    T[:, 2, 3] = 0.8
    cfg = PoseNoiseConfig(scale_mix=True)
    g = torch.Generator().manual_seed(0)
    full = initial_poses("refiner", T, None, None, None, cfg, generator=g)
    mixed = initial_poses("refiner", T, None, None, None, cfg, generator=g, training=True)
    a_full = rotation_angle_deg(full[:, :3, :3], T[:, :3, :3]).median()
    a_mix = rotation_angle_deg(mixed[:, :3, :3], T[:, :3, :3]).median()
    assert 18 < a_full < 30 and a_mix < 0.7 * a_full  # E[u] = 1/2 of the stds


def test_backbone_of_the_other_arch_is_a_config_error():
    from cosy_lite.errors import ConfigError

    with pytest.raises(ConfigError, match=r"\[net.backbone\].*pretrained trunk"):
        build_pose_net(PoseNetConfig(arch="siamese", backbone="resnet18"))
    with pytest.raises(ConfigError, match=r"\[net.backbone\].*net.arch=early needs"):
        build_pose_net(PoseNetConfig(arch="early", backbone="efficientnet_lite0"))
    with pytest.raises(ConfigError, match=r"\[net.arch\]"):
        build_pose_net(PoseNetConfig(arch="late"))


@pytest.mark.parametrize("stored, expected", [(None, "flat"), ("headlight", "headlight")])
def test_inference_renders_as_the_checkpoint_was_trained(tmp_path, stored, expected):
    """Checkpoints from before ``net.render_shading`` existed were trained on flat renderings."""
    from dataclasses import asdict

    from cosy_lite.weights.checkpoint import Checkpoint, save_checkpoint
    from cosy_lite.weights.loaders import load_pose_model

    cfg = PoseNetConfig(arch="early", backbone="resnet18", crop_resolution=[48, 64])
    net_meta = asdict(cfg)
    if stored is None:
        del net_meta["render_shading"]
    else:
        net_meta["render_shading"] = stored
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, Checkpoint(kind="refiner", model=build_pose_net(cfg).state_dict(), config={}, step=1,
                                     meta={"net": net_meta, "obj_ids": [1, 2]}))
    assert load_pose_model(path, "refiner").render_shading == expected


def test_every_parameter_gets_a_gradient_and_older_checkpoints_still_load():
    # DDP stops at an unused parameter: the trunk's blocks after its last feature level are gone
    import timm

    net = SiamesePoseNet(pretrained=False, corr_radius=2, width=16, crop_resolution=(96, 128), flat_channels=8)
    net(torch.rand(2, 6, 96, 128)).sum().backward()
    assert [n for n, p in net.named_parameters() if p.grad is None] == []
    assert len(net.trunk.blocks) == 5  # stride 16 is block 4 of EfficientNet-Lite0
    full = timm.create_model("efficientnet_lite0", features_only=True, out_indices=(2, 3)).state_dict()
    removed = {f"trunk.{k}": v for k, v in full.items() if k.startswith(("blocks.5.", "blocks.6."))}
    assert removed  # a checkpoint written before carries them
    state = {k: v.clone() for k, v in net.state_dict().items()}
    fresh = SiamesePoseNet(pretrained=False, corr_radius=2, width=16, crop_resolution=(96, 128), flat_channels=8)
    fresh.load_state_dict({**state, **removed})
    assert all(torch.equal(fresh.state_dict()[k], v) for k, v in state.items())
