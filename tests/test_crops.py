"""Pose-aware crops: box geometry, the K rewrite against roi_align's sampling, nearest crops."""

from __future__ import annotations

import math

import pytest
import torch

from cosy_lite.geometry.crops import crop_boxes, crop_images, crop_intrinsics, project_points

K_YCBV = torch.tensor([[1066.778, 0.0, 312.9869], [0.0, 1067.487, 241.3109], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _pose(rx: float, ry: float, rz: float, t: tuple[float, float, float]) -> torch.Tensor:
    from cosy_lite.geometry.rotations import euler_xyz_to_matrix

    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = euler_xyz_to_matrix(torch.tensor([[rx, ry, rz]], dtype=torch.float64))[0]
    T[:3, 3] = torch.tensor(t, dtype=torch.float64)
    return T


def _box_points(extents=(0.10, 0.06, 0.04)) -> torch.Tensor:
    """[8,3] corners of a box centred at the origin (m)."""
    e = torch.tensor(extents, dtype=torch.float64) / 2
    s = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=torch.float64)
    return s * e


def test_box_centred_on_projected_origin_with_crop_aspect_and_margin():
    TCO = torch.stack([_pose(0.3, -0.2, 0.1, (-0.09, 0.01, 0.7)), _pose(1.2, 0.0, -0.4, (0.06, -0.05, 0.68))])
    K = K_YCBV.expand(2, 3, 3)
    pts = _box_points().expand(2, 8, 3)
    boxes = crop_boxes(TCO, K, pts, crop_resolution=(240, 320), margin=1.4)
    w, h = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    torch.testing.assert_close(w / h, torch.full((2,), 4 / 3, dtype=torch.float64))
    # Centre = projected origin.
    origin = project_points(TCO, K, torch.zeros(2, 1, 3, dtype=torch.float64))[:, 0]
    torch.testing.assert_close((boxes[:, :2] + boxes[:, 2:]) / 2, origin)
    # The binding extent, divided by the margin, touches the farthest projected corner exactly.
    uv = project_points(TCO, K, pts)
    dx = (uv[..., 0] - origin[:, None, 0]).abs().amax(1)
    dy = (uv[..., 1] - origin[:, None, 1]).abs().amax(1)
    torch.testing.assert_close(w / 2 / 1.4, torch.maximum(dx, dy * 4 / 3))
    assert bool(((w / 2 / 1.4 >= dx - 1e-9) & (h / 2 / 1.4 >= dy - 1e-9)).all())


def test_box_by_hand():
    """One point at (0.1, 0.05, 1) with f = 100, c = (50, 40): origin -> (50, 40), point 10 px right, 5 down."""
    K = torch.tensor([[[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]]])
    TCO = torch.eye(4)[None].clone()
    TCO[0, 2, 3] = 1.0
    box = crop_boxes(TCO, K, torch.tensor([[[0.1, 0.05, 0.0]]]), crop_resolution=(30, 40), margin=2.0)
    # dx = 10, dy = 5, r = 4/3: half_w = max(10, 6.667) * 2 = 20, half_h = 15.
    torch.testing.assert_close(box, torch.tensor([[30.0, 25.0, 70.0, 55.0]]))
    # An extra box reaching 30 px above the centre widens it: dy = 30 -> half_w = 40 * 2 = 80.
    extra = torch.tensor([[45.0, 10.0, 55.0, 45.0]])
    box = crop_boxes(TCO, K, torch.tensor([[[0.1, 0.05, 0.0]]]), crop_resolution=(30, 40), margin=2.0, extra_boxes=extra)
    torch.testing.assert_close(box, torch.tensor([[-30.0, -20.0, 130.0, 100.0]]))


def test_crop_intrinsics_formula():
    """K_crop = A K, A: u' = (u - x1) / s with s = box width / crop width."""
    K = torch.tensor([[[500.0, 2.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    boxes = torch.tensor([[100.0, 60.0, 260.0, 180.0]], dtype=torch.float64)  # 160 x 120 -> 320 x 240: s = 0.5
    Kc = crop_intrinsics(K, boxes, (240, 320))[0]
    expected = torch.tensor(
        [[1000.0, 4.0, (320.0 - 100.0) / 0.5], [0.0, 1200.0, (240.0 - 60.0) / 0.5], [0.0, 0.0, 1.0]], dtype=torch.float64
    )
    torch.testing.assert_close(Kc, expected)
    # The box corners map to the crop corners (0, 0) and (w, h).
    X = torch.tensor(
        [[(100.0 - 320.0) / 500.0, (60.0 - 240.0) / 600.0, 1.0], [(260.0 - 320.0) / 500.0, (180.0 - 240.0) / 600.0, 1.0]],
        dtype=torch.float64,
    )
    K0 = K[0].clone()
    K0[0, 1] = 0.0
    Kc0 = crop_intrinsics(K0[None], boxes, (240, 320))[0]
    uv = (X @ Kc0.T)[:, :2] / (X @ Kc0.T)[:, 2:]
    torch.testing.assert_close(uv, torch.tensor([[0.0, 0.0], [320.0, 240.0]], dtype=torch.float64))


def _blob_image(centres_uv: torch.Tensor, H: int, W: int, sigma: float) -> torch.Tensor:
    """[B,1,H,W] Gaussian blobs centred at image coordinates ``centres_uv`` [B,2] (pixel i at i + 0.5)."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5, indexing="ij")
    d2 = (u[None] - centres_uv[:, 0, None, None]) ** 2 + (v[None] - centres_uv[:, 1, None, None]) ** 2
    return torch.exp(-d2 / (2 * sigma**2))[:, None]


def _centroid(img: torch.Tensor) -> torch.Tensor:
    """Intensity-weighted centroid [B,2] (image coordinates) of [B,1,h,w] images."""
    B, _, h, w = img.shape
    v, u = torch.meshgrid(torch.arange(h, dtype=img.dtype) + 0.5, torch.arange(w, dtype=img.dtype) + 0.5, indexing="ij")
    m = img[:, 0]
    s = m.sum((1, 2))
    return torch.stack([(m * u).sum((1, 2)) / s, (m * v).sum((1, 2)) / s], dim=-1)


@pytest.mark.parametrize("scale", [0.5, 1.7])  # crop enlarges (box smaller than the crop) / shrinks
def test_k_crop_reprojects_points_onto_the_sampled_pixels(scale):
    """A 3D point projected with K_crop lands (sub-pixel) where roi_align put its image location."""
    gen = torch.Generator().manual_seed(3)
    H, W, B = 240, 320, 3
    K = torch.tensor([[300.0, 0.0, 161.3], [0.0, 310.0, 118.7], [0.0, 0.0, 1.0]], dtype=torch.float64).expand(B, 3, 3)
    X = torch.ones(B, 3, dtype=torch.float64)  # points at z = 1 m
    X[:, :2] = torch.rand(B, 2, generator=gen, dtype=torch.float64) * 0.2 - 0.1
    uv = (X @ K[0].T)[:, :2] / X[:, 2:]  # image coordinates of the points
    sigma = 4.0 * scale
    images = _blob_image(uv, H, W, sigma)
    # Boxes around each point, off-centre by a non-integer amount, 4:3.
    off = torch.rand(B, 2, generator=gen, dtype=torch.float64) * 20 - 10
    half = torch.tensor([40.0, 30.0], dtype=torch.float64) * scale
    centre = uv + off
    boxes = torch.cat([centre - half, centre + half], 1)
    res = (48, 64)
    crops = crop_images(images, boxes, res, sampling_ratio=2)
    K_crop = crop_intrinsics(K, boxes, res)
    uv_crop = (X[:, None] @ K_crop.transpose(1, 2))[:, 0]
    uv_crop = uv_crop[:, :2] / uv_crop[:, 2:]
    err = (_centroid(crops) - uv_crop).norm(dim=-1)
    assert float(err.max()) < 0.05, err  # well below the 0.5 px requirement


def test_origin_lands_at_crop_centre():
    TCO = _pose(0.1, 0.2, 0.3, (0.05, -0.03, 0.8))[None]
    pts = _box_points()[None]
    boxes = crop_boxes(TCO, K_YCBV[None], pts, crop_resolution=(240, 320))
    Kc = crop_intrinsics(K_YCBV[None], boxes, (240, 320))
    o = (Kc[0] @ TCO[0, :3, 3])
    torch.testing.assert_close(o[:2] / o[2], torch.tensor([160.0, 120.0], dtype=torch.float64))  # w/2, h/2


def test_nearest_crop_of_a_mask_and_outside_is_zero():
    mask = torch.zeros(1, 1, 10, 12, dtype=torch.bool)
    mask[0, 0, 2:5, 3:9] = True  # rows 2..4, cols 3..8
    # Box = exactly the pixels rows 2..4, cols 3..8 at 1:1 -> the crop is all True.
    box = torch.tensor([[3.0, 2.0, 9.0, 5.0]])
    crop = crop_images(mask, box, (3, 6), mode="nearest")
    assert crop.dtype == torch.bool and bool(crop.all())
    # A box twice the size, half outside the image on the left: 2x2 blocks, zeros outside.
    box = torch.tensor([[-4.2, -0.3, 7.8, 9.7]])
    crop = crop_images(mask.to(torch.uint8) * 7, box, (5, 6), mode="nearest")[0, 0]
    # Samples: u = -3.2 + 2j -> pixels -4, -2, 0, 2, 4, 6; v = 0.7 + 2i -> 0, 2, 4, 6, 8.
    expected = torch.zeros(5, 6, dtype=torch.uint8)
    expected[1:3, 4:6] = 7  # v in {2, 4} (rows 2..4) and u in {4, 6} (cols 3..8)
    assert torch.equal(crop, expected), crop


def test_bilinear_needs_float_and_modes_are_checked():
    with pytest.raises(ValueError, match="floating"):
        crop_images(torch.zeros(1, 1, 4, 4, dtype=torch.uint8), torch.tensor([[0.0, 0.0, 4.0, 4.0]]), (2, 2))
    with pytest.raises(ValueError, match="mode"):
        crop_images(torch.zeros(1, 1, 4, 4), torch.tensor([[0.0, 0.0, 4.0, 4.0]]), (2, 2), mode="cubic")
    with pytest.raises(ValueError, match="boxes"):
        crop_images(torch.zeros(2, 1, 4, 4), torch.tensor([[0.0, 0.0, 4.0, 4.0]]), (2, 2))


def test_points_behind_camera_give_finite_boxes():
    TCO = torch.eye(4)[None].clone()
    TCO[0, 2, 3] = -0.5
    box = crop_boxes(TCO, K_YCBV.float()[None], _box_points().float()[None])
    assert bool(torch.isfinite(box).all())
    assert math.isclose(float((box[0, 2] - box[0, 0]) / (box[0, 3] - box[0, 1])), 4 / 3, rel_tol=1e-5)


@pytest.mark.parametrize("n_boxes", [1, 2, 5])
def test_crops_split_over_threads_equal_one_thread(n_boxes, monkeypatch):
    """Outside autograd (inference mode, no_grad) the bilinear crops of 2 boxes or more are split over
    torch's threads, with the same numbers as on one thread; with autograd on they are one roi_align
    call on the calling thread, whose gradient reaches the image."""
    from cosy_lite.geometry import crops

    pools: list[int] = []  # the thread count of each split
    real = crops._crop_threads
    monkeypatch.setattr(crops, "_crop_threads", lambda n: pools.append(n) or real(n))
    g = torch.Generator().manual_seed(n_boxes)
    images = torch.rand(n_boxes, 3, 60, 80, generator=g)
    boxes = torch.rand(n_boxes, 2, generator=g) * 30
    boxes = torch.cat([boxes, boxes + torch.tensor([40.0, 30.0])], dim=1)
    one = crop_images(images, boxes, (24, 32))  # (the tests run on one thread)
    assert pools == []
    torch.set_num_threads(2)  # (restored by conftest)
    with torch.inference_mode():
        split = crop_images(images.clone(), boxes, (24, 32))
    assert split.shape == (n_boxes, 3, 24, 32) and torch.equal(split, one)
    with torch.no_grad():
        assert torch.equal(crop_images(images, boxes, (24, 32)), one)
    assert pools == ([] if n_boxes == 1 else [2, 2])
    x = images.clone().requires_grad_(True)
    crop_images(x, boxes, (24, 32)).sum().backward()
    assert x.grad is not None and float(x.grad.abs().sum()) > 0
    assert len(pools) == (0 if n_boxes == 1 else 2)  # not split with autograd on
