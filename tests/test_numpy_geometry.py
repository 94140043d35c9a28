"""The numpy twins of the torch geometry used by the onnxruntime path: crop boxes, K_crop and
roi_align crops (``geometry/crops_np.py``), the pose update (``models/pose_update_np.py``), the box
initial pose (``models/initial_pose_np.py``), pose checks (``inference/iterate_np.py``): equal to
the torch functions (float64: 1e-9; crops: far below 1/255), same constants, importable without torch."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from cosy_lite.geometry import crops, crops_np
from cosy_lite.geometry.rotations import IDENTITY_6D, random_rotations
from cosy_lite.inference import iterate_np, predictor
from cosy_lite.models import initial_pose, initial_pose_np, pose_update, pose_update_np

ROOT = Path(__file__).resolve().parents[1]
K_YCBV = np.array([[1066.778, 0.0, 312.9869], [0.0, 1067.487, 241.3109], [0.0, 0.0, 1.0]])


def _poses(n: int, seed: int) -> np.ndarray:
    """[n,4,4] float64: random rotations, objects 0.4-1.2 m in front of the camera, some off-centre."""
    g = torch.Generator().manual_seed(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = random_rotations(n, g).numpy()
    rng = np.random.default_rng(seed)
    T[:, :3, 3] = rng.uniform([-0.3, -0.2, 0.4], [0.3, 0.2, 1.2], size=(n, 3))
    return T


def _image(H: int = 480, W: int = 640, seed: int = 0) -> np.ndarray:
    """[H,W,3] float32 in [0, 1] of uint8 values: smooth shading, noise and sharp-edged rectangles."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W]
    im = np.stack([u / W, v / H, 0.5 + 0.5 * np.sin(u / 17.0 + v / 23.0)], axis=-1) * 180
    im = im + rng.normal(0, 12, size=im.shape)
    for _ in range(12):
        x, y = rng.integers(0, W - 40), rng.integers(0, H - 40)
        im[y: y + rng.integers(5, 120), x: x + rng.integers(5, 160)] = rng.integers(0, 256, size=3)
    return (np.clip(np.round(im), 0, 255).astype(np.uint8)).astype(np.float32) / np.float32(255.0)


def test_constants_equal_the_torch_modules():
    assert crops_np.CROP_RESOLUTION == crops.CROP_RESOLUTION and crops_np.MARGIN == crops.MARGIN
    assert crops_np.Z_MIN == crops.Z_MIN and crops_np.SAMPLING_RATIO == crops.SAMPLING_RATIO
    assert pose_update_np.IDENTITY_6D == IDENTITY_6D and pose_update_np.POSE_DIM == pose_update.POSE_DIM
    assert initial_pose_np.EXTENT_PER_DIAMETER == initial_pose.EXTENT_PER_DIAMETER
    assert set(initial_pose_np.CANONICAL_ROTATIONS) == set(initial_pose.CANONICAL_ROTATIONS)
    for name, R in initial_pose.CANONICAL_ROTATIONS.items():
        np.testing.assert_array_equal(initial_pose_np.CANONICAL_ROTATIONS[name], R.numpy())
    assert predictor.MIN_DEPTH == iterate_np.MIN_DEPTH == 0.02


def test_crop_boxes_and_k_crop_equal_torch():
    B = 64
    TCO = _poses(B, 0)
    TCO[0, 2, 3] = 0.05  # nearer than Z_MIN: clamped depths
    K = np.tile(K_YCBV, (B, 1, 1))
    K[1, 0, 1] = 3.0  # skew
    points = np.random.default_rng(1).uniform(-0.1, 0.1, size=(B, 300, 3))
    t = [torch.from_numpy(a) for a in (TCO, K, points)]
    for res, margin in (((240, 320), 1.4), ((96, 128), 1.0), ((50, 50), 2.0)):
        boxes = crops_np.crop_boxes(TCO, K, points, crop_resolution=res, margin=margin)
        ref = crops.crop_boxes(*t, crop_resolution=res, margin=margin).numpy()
        assert boxes.shape == (B, 4) and boxes.dtype == np.float64
        np.testing.assert_allclose(boxes, ref, rtol=0, atol=1e-9)
        K_crop = crops_np.crop_intrinsics(K, boxes, res)
        np.testing.assert_allclose(K_crop, crops.crop_intrinsics(t[1], torch.from_numpy(boxes), res).numpy(),
                                   rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(crops_np.project_points(TCO, K, points), crops.project_points(*t).numpy(),
                               rtol=0, atol=1e-9)


def test_crop_boxes_by_hand_and_shapes_checked():
    """One point at (0.1, 0.05, 1) with f = 100, c = (50, 40): 10 px right, 5 down; r = 4/3, margin 2."""
    K = np.array([[[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]]])
    TCO = np.eye(4)[None].copy()
    TCO[0, 2, 3] = 1.0
    box = crops_np.crop_boxes(TCO, K, np.array([[[0.1, 0.05, 0.0]]]), crop_resolution=(30, 40), margin=2.0)
    np.testing.assert_allclose(box, [[30.0, 25.0, 70.0, 55.0]])
    with pytest.raises(ValueError, match=r"points must be a numpy array of shape \[1,\*,3\], got \(1, 2\)"):
        crops_np.crop_boxes(TCO, K, np.zeros((1, 2)))
    with pytest.raises(ValueError, match="image must be floating"):
        crops_np.crop_image(np.zeros((4, 4, 3), np.uint8), box)


def test_crops_equal_roi_align():
    """Boxes inside, across the border, far beyond the image, below one pixel, enlarging and
    shrinking: max |numpy - torch| ~ 4e-5 (float32 rounding), the bound 1e-4 is 1/40 of 1/255."""
    image = _image()
    boxes = np.array([[100.3, 50.7, 420.1, 290.8],  # shrinks: 320 px -> 320 (x), 240 -> 240
                      [-50.0, -30.0, 110.0, 90.0],  # top-left corner outside
                      [500.0, 400.0, 800.0, 625.0],  # bottom-right outside
                      [600.2, 10.1, 650.7, 48.0],  # across the right edge, enlarged
                      [-5000.0, -3000.0, 5000.0, 4500.0],  # the image is a small patch of the crop
                      [200.0, 200.0, 200.5, 200.375],  # below one pixel
                      [-0.7, -0.4, 639.6, 479.9],  # about the whole image
                      [700.0, 10.0, 900.0, 160.0]])  # entirely outside: zeros
    for res, ratio in (((240, 320), 2), ((48, 64), 2), ((30, 40), 3)):
        t_image = torch.from_numpy(image).permute(2, 0, 1)[None].expand(len(boxes), -1, -1, -1).contiguous()
        ref = crops.crop_images(t_image, torch.from_numpy(boxes).float(), res, sampling_ratio=ratio).numpy()
        out = crops_np.crop_image(image, boxes.astype(np.float32), res, sampling_ratio=ratio)
        assert out.shape == ref.shape == (len(boxes), 3, *res) and out.dtype == np.float32
        assert np.abs(out - ref).max() <= 1e-4
        assert out[:4].std() > 0.1 and np.all(out[-1] == 0)  # real content compared; outside is 0
    # out=: written in place, e.g. into the first 3 of 6 channels.
    buffer = np.full((len(boxes), 6, 48, 64), -1.0, dtype=np.float32)
    crops_np.crop_image(image, boxes, (48, 64), out=buffer[:, :3])
    np.testing.assert_array_equal(buffer[:, :3], crops_np.crop_image(image, boxes, (48, 64)))
    assert np.all(buffer[:, 3:] == -1.0)


def test_crop_weights_by_hand():
    """A 2-sample bin at [0, 2) px of a 4-pixel line: samples at pixel-centre units 0 and 1 (box
    start 0 -> -0.5 + 0.5 and + 1.5); both land on pixels, each weighs 1/2."""
    idx, w = crops_np.axis_weights(0.0, 2.0, 1, 4, 2)
    line = np.array([10.0, 20.0, 40.0, 80.0])
    assert float((w * line[idx]).sum()) == pytest.approx(15.0)
    # Half a pixel beyond the image: clamped to the border pixel; beyond one pixel: zero.
    idx, w = crops_np.axis_weights(-1.0, 1.0, 2, 4, 1)  # samples at -1.0 (kept, clamped) and 0.0
    np.testing.assert_allclose((w * line[idx]).sum(axis=1), [10.0, 10.0])
    idx, w = crops_np.axis_weights(-3.0, -1.0, 1, 4, 1)  # sample at -2.5: outside
    assert float((w * line[idx]).sum()) == 0.0


def test_pose_update_equals_torch():
    B = 50
    TCO = _poses(B, 2)
    rng = np.random.default_rng(3)
    K_crop = np.tile([[600.0, 0.0, 159.5], [0.0, 620.0, 119.5], [0.0, 0.0, 1.0]], (B, 1, 1)) * rng.uniform(
        0.5, 2.0, size=(B, 1, 1))
    K_crop[:, 2, 2] = 1.0
    delta = rng.normal(0, 0.3, size=(B, 9))
    delta[0] = 0.0
    delta[1, :3] = 0.0  # a degenerate 6D first column: normalised with torch's eps
    out = pose_update_np.apply_pose_update(TCO, K_crop, delta)
    ref = pose_update.apply_pose_update(*(torch.from_numpy(a) for a in (TCO, K_crop, delta))).numpy()
    assert out.dtype == np.float64 and np.abs(out[2:, :3, 3] - TCO[2:, :3, 3]).max() > 0.01  # moved
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(out[0], TCO[0])  # zero update: unchanged bit for bit
    # float32 network outputs are cast up, as torch casts them to the poses' dtype.
    d32 = delta.astype(np.float32)
    np.testing.assert_array_equal(pose_update_np.apply_pose_update(TCO, K_crop, d32),
                                  pose_update_np.apply_pose_update(TCO, K_crop, d32.astype(np.float64)))
    np.testing.assert_allclose(pose_update_np.rot6d_to_matrix(delta[:, :6]),
                               pose_update.rot6d_to_matrix(torch.from_numpy(delta[:, :6])).numpy(), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match=r"delta must be \[50,9\], got \(50, 6\)"):
        pose_update_np.apply_pose_update(TCO, K_crop, delta[:, :6])


def test_initial_pose_equals_torch():
    rng = np.random.default_rng(4)
    B = 40
    xy = rng.uniform(-50, 600, size=(B, 2))
    boxes = np.concatenate([xy, xy + rng.uniform(0.2, 300, size=(B, 2))], axis=1)
    boxes[0, 2:] = boxes[0, :2]  # a degenerate box counts as 1 px
    K = np.tile(K_YCBV, (B, 1, 1))
    diameters = rng.uniform(0.05, 0.4, size=B)
    ratios = rng.uniform(0.7, 1.0, size=B)
    for rotation in ("z_up", "identity"):
        for ratio in (initial_pose_np.EXTENT_PER_DIAMETER, ratios):
            out = initial_pose_np.initial_pose_from_boxes(boxes, K, diameters, rotation, ratio)
            ref = initial_pose.initial_pose_from_boxes(
                *(torch.from_numpy(a) for a in (boxes, K, diameters)), rotation,
                torch.from_numpy(np.asarray(ratio)) if isinstance(ratio, np.ndarray) else ratio).numpy()
            np.testing.assert_allclose(out, ref, rtol=0, atol=1e-9)
    # By hand: f = 500, box 100 px wide and 50 high at the principal point, d = 0.2 m: z = 500 * 0.92 * 0.2 / 100.
    K1 = np.array([[[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]])
    T = initial_pose_np.initial_pose_from_boxes(np.array([[270.0, 215.0, 370.0, 265.0]]), K1, np.array([0.2]))
    np.testing.assert_allclose(T[0, :3, 3], [0.0, 0.0, 500 * 0.92 * 0.2 / 100], atol=1e-15)
    with pytest.raises(ValueError, match="rotation must be one of"):
        initial_pose_np.initial_pose_from_boxes(boxes, K, diameters, "upside_down")


def test_valid_poses_and_orthonormalise_equal_torch():
    TCO = _poses(8, 5)
    TCO[1, 0, 3] = np.nan
    TCO[2, 2, 3] = 0.01  # too near
    TCO[3, :3, :3] *= 1.01  # not a rotation
    TCO[4, :3, 0] *= -1  # det -1
    TCO[5, :3, :3] += 1e-4  # nearly a rotation: valid, snapped back by orthonormalise
    valid = iterate_np.valid_poses(TCO)
    assert valid.tolist() == [True, False, False, False, False, True, True, True]
    np.testing.assert_array_equal(valid, predictor.valid_poses(torch.from_numpy(TCO)).numpy())
    out = iterate_np.orthonormalise(TCO)
    np.testing.assert_allclose(out, predictor.orthonormalise(torch.from_numpy(TCO)).numpy(), rtol=0, atol=1e-12,
                               equal_nan=True)
    R = out[[0, 5], :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.tile(np.eye(3), (2, 1, 1)), atol=1e-12)
    assert iterate_np.valid_poses(np.zeros((0, 4, 4))).shape == (0,)


def test_numpy_modules_import_without_torch():
    """The onnxruntime loop's modules run where torch is not installed (``import torch`` fails)."""
    code = ("import sys; sys.modules['torch'] = None\n"
            "import numpy as np\n"
            "from cosy_lite.geometry import crops_np\n"
            "from cosy_lite.inference import iterate_np\n"
            "from cosy_lite.models import initial_pose_np, pose_update_np\n"
            "from cosy_lite.export import onnx_models\n"
            "box = np.array([[0.0, 0.0, 4.0, 4.0]])\n"
            "print(crops_np.crop_image(np.ones((4, 4, 3), np.float32), box, (2, 2)).sum())\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "12.0"
