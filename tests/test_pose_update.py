"""The CosyPose image-space update, its inverse, initial poses from boxes and pose noise."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cosy_lite.geometry.rotations import IDENTITY_6D, random_rotations, rotation_angle_deg
from cosy_lite.nets.initial_pose import (
    CANONICAL_ROTATIONS,
    EXTENT_PER_DIAMETER,
    add_pose_noise,
    initial_pose_from_boxes,
)
from cosy_lite.nets.pose_update import apply_pose_update, pose_update_targets

K_CROP = torch.tensor([[[600.0, 0.0, 159.5], [0.0, 620.0, 119.5], [0.0, 0.0, 1.0]]], dtype=torch.float64)


def _poses(n: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    T = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    T[:, :3, :3] = random_rotations(n, g)
    lo, size = torch.tensor([-0.2, -0.15, 0.5]), torch.tensor([0.4, 0.3, 0.7])
    T[:, :3, 3] = lo + torch.rand(n, 3, generator=g, dtype=torch.float64) * size
    return T.to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_zero_update_leaves_pose_unchanged_exactly(dtype):
    TCO = _poses(5, 0, dtype)
    out = apply_pose_update(TCO, K_CROP.to(dtype).expand(5, 3, 3), torch.zeros(5, 9, dtype=dtype))
    assert out.dtype == dtype
    assert torch.equal(out, TCO)


def test_update_by_hand():
    """vx = 60 px at f = 600 and z = 1: x moves 0.1 m; vz = 2 doubles z and keeps x/z; dR 90 deg about z."""
    TCO = torch.eye(4, dtype=torch.float64)[None].clone()
    TCO[0, :3, 3] = torch.tensor([0.1, 0.0, 1.0])
    delta = torch.zeros(1, 9, dtype=torch.float64)
    delta[0, 6] = 60.0
    out = apply_pose_update(TCO, K_CROP, delta)
    torch.testing.assert_close(out[0, :3, 3], torch.tensor([0.2, 0.0, 1.0], dtype=torch.float64))
    delta = torch.zeros(1, 9, dtype=torch.float64)
    delta[0, 8] = math.log(2.0)
    rz90_6d = torch.tensor([0.0, 1.0, 0.0, -1.0, 0.0, 0.0], dtype=torch.float64)  # columns (0,1,0), (-1,0,0)
    delta[0, :6] = rz90_6d - torch.tensor(IDENTITY_6D, dtype=torch.float64)
    out = apply_pose_update(TCO, K_CROP, delta)
    torch.testing.assert_close(out[0, :3, 3], torch.tensor([0.2, 0.0, 2.0], dtype=torch.float64))
    Rz90 = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(out[0, :3, :3], Rz90)
    torch.testing.assert_close(out[0, 3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64))


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_targets_round_trip(dtype, tol):
    TCO_in, TCO_gt = _poses(16, 1, dtype), _poses(16, 2, dtype)
    K = K_CROP.to(dtype).expand(16, 3, 3)
    delta = pose_update_targets(TCO_in, TCO_gt, K)
    out = apply_pose_update(TCO_in, K, delta)
    assert float((out - TCO_gt).abs().max()) < tol
    # And the other way: targets of an updated pose give back the update.
    d = torch.randn(16, 9, generator=torch.Generator().manual_seed(4), dtype=dtype) * 0.1
    back = pose_update_targets(TCO_in, apply_pose_update(TCO_in, K, d), K)
    # The 6D part is only defined up to Gram-Schmidt: compare the rotations and the 3 translation outputs.
    assert float((back[:, 6:] - d[:, 6:]).abs().max()) < tol * 1e3
    R_back = apply_pose_update(TCO_in, K, back)[:, :3, :3]
    R_d = apply_pose_update(TCO_in, K, d)[:, :3, :3]
    assert float((R_back - R_d).abs().max()) < tol * 10


def test_update_is_differentiable():
    TCO = _poses(4, 5)
    delta = (torch.randn(4, 9, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.1).requires_grad_()
    torch.autograd.gradcheck(lambda d: apply_pose_update(TCO, K_CROP.expand(4, 3, 3), d), (delta,))


def test_shapes_are_checked():
    with pytest.raises(ValueError, match="delta"):
        apply_pose_update(_poses(2, 0), K_CROP.expand(2, 3, 3), torch.zeros(2, 7, dtype=torch.float64))
    with pytest.raises(ValueError, match="K_crop"):
        apply_pose_update(_poses(2, 0), K_CROP, torch.zeros(2, 9, dtype=torch.float64))


# ----------------------------------------------------------------------------- initial poses


def _cylinder_points(radius: float, height: float, n: int = 400) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n // 2, endpoint=False)
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], 1)
    return np.concatenate([np.c_[ring, np.full(len(a), -height / 2)], np.c_[ring, np.full(len(a), height / 2)]])


def _box_points(extents) -> np.ndarray:
    e = np.asarray(extents) / 2
    return np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * e


def _rz(a: np.ndarray) -> np.ndarray:
    c, s, o, i = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([c, -s, o, s, c, o, o, o, i], -1).reshape(-1, 3, 3)


def _rx(a: np.ndarray) -> np.ndarray:
    c, s, o, i = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([i, o, o, o, c, -s, o, s, c], -1).reshape(-1, 3, 3)


def test_initial_depth_within_20_percent_of_projected_boxes():
    """Typical views (objects resting on a table seen from 20-80 deg elevation, any azimuth and roll) of
    boxes and cylinders shaped like YCB-V objects: the box of the projected model gives z within 20%."""
    rng = np.random.default_rng(0)
    K = np.array([[1066.778, 0.0, 312.9869], [0.0, 1067.487, 241.3109], [0.0, 0.0, 1.0]])
    shapes = [_box_points((0.16, 0.21, 0.07)), _box_points((0.09, 0.05, 0.18)), _box_points((0.10, 0.07, 0.19)),
              _cylinder_points(0.05, 0.14), _cylinder_points(0.034, 0.10), _cylinder_points(0.043, 0.034)]
    ratios = []
    for pts in shapes:
        diameter = float(np.max(np.linalg.norm(pts[:, None] - pts[None], axis=-1)))
        n = 200
        elev = rng.uniform(np.radians(20), np.radians(80), n)
        azim, roll = rng.uniform(0, 2 * np.pi, n), rng.uniform(-np.pi, np.pi, n)
        # R_CO = roll about the optical axis @ tilt down by the elevation @ z-up side view @ azimuth about z.
        R = _rz(roll) @ _rx(elev) @ CANONICAL_ROTATIONS["z_up"].numpy() @ _rz(azim)
        z = rng.uniform(0.5, 1.2, n)
        t = np.stack([rng.uniform(-0.15, 0.15, n) * z, rng.uniform(-0.1, 0.1, n) * z, z], 1)
        p = np.einsum("bij,nj->bni", R, pts) + t[:, None]
        uv = p[..., :2] / p[..., 2:] * K[[0, 1], [0, 1]] + K[:2, 2]
        boxes = torch.tensor(np.concatenate([uv.min(1), uv.max(1)], 1))
        TCO = initial_pose_from_boxes(boxes, torch.tensor(K).expand(n, 3, 3), torch.full((n,), diameter, dtype=torch.float64))
        ratios.append(TCO[:, 2, 3].numpy() / z)
        # x, y back-projected from the box centre at the estimated depth.
        c = (boxes[:, :2] + boxes[:, 2:]) / 2
        uv_est = TCO[:, :2, 3] / TCO[:, 2:3, 3] * torch.tensor(K[[0, 1], [0, 1]]) + torch.tensor(K[:2, 2])
        torch.testing.assert_close(uv_est, c)
    r = np.concatenate(ratios)
    assert np.mean(np.abs(r - 1) < 0.2) > 0.85, np.percentile(r, [5, 50, 95])  # 0.887 here
    assert np.percentile(r, 2) > 0.85  # the box side is at most f d / z: depth is rarely underestimated
    assert abs(np.median(r) - 1) < 0.1


def test_initial_pose_by_hand():
    """A 100 x 50 px box with f = 500 and an object of extent 0.92 * 0.2 m: z = 500 * 0.184 / 100."""
    K = torch.tensor([[[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]])
    boxes = torch.tensor([[370.0, 240.0, 470.0, 290.0]])  # centre (420, 265)
    TCO = initial_pose_from_boxes(boxes, K, torch.tensor([0.2]), rotation="identity")
    z = 500 * EXTENT_PER_DIAMETER * 0.2 / 100
    torch.testing.assert_close(TCO[0, :3, 3], torch.tensor([100 * z / 500, 25 * z / 500, z]))
    torch.testing.assert_close(TCO[0, :3, :3], torch.eye(3))
    TCO = initial_pose_from_boxes(boxes, K, torch.tensor([0.2]))  # default: CosyPose's z-up
    torch.testing.assert_close(TCO[0, :3, :3], CANONICAL_ROTATIONS["z_up"].float())
    # z-up: the object's z axis points up in the image (-y camera), its x axis towards the camera.
    torch.testing.assert_close(TCO[0, :3, 2], torch.tensor([0.0, -1.0, 0.0]))
    torch.testing.assert_close(TCO[0, :3, 0], torch.tensor([0.0, 0.0, -1.0]))


def test_pose_noise_statistics_and_determinism():
    n = 4000
    TCO = _poses(1, 0).expand(n, 4, 4).float()
    g = torch.Generator().manual_seed(0)
    noisy = add_pose_noise(TCO, rot_std_deg=15.0, trans_std=(0.01, 0.01, 0.05), generator=g)
    dt = noisy[:, :3, 3] - TCO[:, :3, 3]
    torch.testing.assert_close(dt.std(0), torch.tensor([0.01, 0.01, 0.05]), rtol=0.05, atol=0)
    # Camera frame: dR = R_noisy R^T is the Euler noise; its angles have std 15 deg per axis.
    dR = noisy[:, :3, :3] @ TCO[:, :3, :3].transpose(1, 2)
    ax = torch.rad2deg(torch.atan2(dR[:, 2, 1], dR[:, 2, 2]))  # x angle of Rz Ry Rx
    assert abs(float(ax.std()) - 15.0) < 0.75
    ang = rotation_angle_deg(noisy[:, :3, :3], TCO[:, :3, :3])
    assert 20 < float(ang.median()) < 30  # ~ 15 deg * median of a chi(3) = 23 deg
    again = add_pose_noise(TCO, generator=torch.Generator().manual_seed(0))
    assert torch.equal(again, noisy)
    # Object frame (CosyPose's add_noise): R_noisy = R @ noise.
    obj = add_pose_noise(TCO, generator=torch.Generator().manual_seed(0), frame="object")
    torch.testing.assert_close(TCO[:, :3, :3] @ (noisy[:, :3, :3] @ TCO[:, :3, :3].transpose(1, 2)), obj[:, :3, :3])
    # Zero noise is the identity.
    assert torch.equal(add_pose_noise(TCO, 0.0, (0.0, 0.0, 0.0), g), TCO)
