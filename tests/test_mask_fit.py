"""Depth from an exact mask (cosy_lite.inference.mask_fit, ``depth_from_mask``): real renders of YCB-V
meshes; the fitted depth, the occlusion rule, the poses it leaves alone, and the pipeline setting."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from cosy_lite.inference.mask_fit import MIN_VISIBLE, SCALES, depth_scale, fit_depth_to_masks, guarded_iterations, silhouette_ious
from cosy_lite.render.renderer import GlRenderer

MUSTARD, DRILL = 5, 15
K = np.array([[1066.778, 0.0, 312.9869], [0.0, 1067.487, 241.3109], [0.0, 0.0, 1.0]])  # YCB-V camera
SIZE = (480, 640)


def _T(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(np.asarray(rotvec, dtype=np.float64))[0], t
    return T


GT = {MUSTARD: _T([0.6, -0.9, 0.4], [0.06, -0.03, 0.80]), DRILL: _T([-1.2, 0.3, 0.5], [-0.12, 0.05, 0.90])}


@pytest.fixture(scope="module")
def renderer():
    from cosy_lite.synth.objects import load_ycb_mesh

    with GlRenderer(meshes={MUSTARD: load_ycb_mesh(MUSTARD), DRILL: load_ycb_mesh(DRILL)}) as r:
        yield r


def _masks(renderer, ids) -> torch.Tensor:
    return torch.from_numpy(renderer.render(ids, np.stack([GT[i] for i in ids]), K, SIZE, depth_only=True).mask)


@pytest.mark.parametrize("factor", [0.92, 0.97, 1.06, 1.15])
def test_the_depth_is_fitted_to_an_exact_mask(renderer, factor):
    """A pose at the right rotation and pixel but ``factor`` x the distance comes back to within 1 %
    of the GT depth (the grid's step is 0.5 %, the silhouette's scaling weak perspective); rotation and
    line of sight unchanged."""
    ids = [MUSTARD, DRILL]
    start = np.stack([GT[i] for i in ids])
    start[:, :3, 3] *= factor
    out = fit_depth_to_masks(torch.from_numpy(start), torch.from_numpy(K), _masks(renderer, ids), ids, renderer).numpy()
    for j, i in enumerate(ids):
        assert abs(out[j, 2, 3] / GT[i][2, 3] - 1) < 0.01, (factor, out[j, 2, 3], GT[i][2, 3])
        np.testing.assert_allclose(out[j, :3, :3], start[j, :3, :3])
        np.testing.assert_allclose(np.cross(out[j, :3, 3], start[j, :3, 3]), 0.0, atol=1e-12)  # same line of sight


def test_a_partly_hidden_object_keeps_its_depth(renderer):
    """A mask covering less than MIN_VISIBLE of the silhouette (the lower half hidden) does not tell the
    object's size: the depth is kept, exactly. Just above the limit it is fitted."""
    ids = [MUSTARD]
    full = _masks(renderer, ids)
    rows = full[0].any(dim=1).nonzero().flatten()
    cut = int(rows.min() + 0.5 * (rows.max() - rows.min()))
    hidden = full.clone()
    hidden[0, cut:] = False
    assert hidden.sum() < MIN_VISIBLE * full.sum()
    start = GT[MUSTARD][None].copy()
    start[0, :3, 3] *= 1.06
    out = fit_depth_to_masks(torch.from_numpy(start), torch.from_numpy(K), hidden, ids, renderer).numpy()
    np.testing.assert_array_equal(out, start)
    fitted = fit_depth_to_masks(torch.from_numpy(start), torch.from_numpy(K), full, ids, renderer).numpy()
    assert abs(fitted[0, 2, 3] / GT[MUSTARD][2, 3] - 1) < 0.01


def test_poses_it_cannot_fit_are_returned_as_they_are(renderer):
    """An empty mask, a pose behind the camera and a NaN pose stay as given; no detection: no render."""
    ids = [MUSTARD, DRILL, MUSTARD]
    poses = np.stack([GT[MUSTARD], GT[DRILL], GT[MUSTARD]])
    poses[1, 2, 3] = -0.5
    poses[2, 0, 3] = np.nan
    masks = torch.zeros((3, *SIZE), dtype=torch.bool)
    masks[1:] = _masks(renderer, [DRILL])
    out = fit_depth_to_masks(torch.from_numpy(poses), torch.from_numpy(K), masks, ids, renderer).numpy()
    np.testing.assert_array_equal(out, poses)
    empty = fit_depth_to_masks(torch.zeros((0, 4, 4)), torch.from_numpy(K), torch.zeros((0, *SIZE), dtype=torch.bool),
                               [], renderer)
    assert empty.shape == (0, 4, 4)


def test_depth_scale_searches_the_grid_around_one():
    """1.0 is on the grid (an exact fit keeps the depth); a disc of radius 40 px against a mask of
    radius 50 px about the same centre asks for 0.8 x the distance, the grid's nearest end."""
    assert 1.0 in SCALES and SCALES.min() == 0.8 and SCALES.max() == 1.25
    yy, xx = np.mgrid[:200, :200]
    disc = lambda r: (xx - 100.0) ** 2 + (yy - 100.0) ** 2 <= r * r  # noqa: E731
    assert depth_scale(disc(40), disc(40), (100.0, 100.0)) == 1.0
    assert depth_scale(disc(40), disc(50), (100.0, 100.0)) == 0.8
    assert abs(depth_scale(disc(40), disc(44), (100.0, 100.0)) - 40 / 44) < 0.006
    assert depth_scale(disc(40), np.zeros((200, 200), bool), (100.0, 100.0)) == 1.0


def _turned(T: np.ndarray, deg: float) -> np.ndarray:
    out = T.copy()
    out[:3, :3] = cv2.Rodrigues(np.radians([0.0, deg, 0.0]))[0] @ T[:3, :3]
    return out


def test_the_guard_keeps_an_earlier_iteration_only_when_the_last_fits_the_mask_clearly_worse(renderer):
    """Iterations [GT, 40 deg off] of the mustard bottle and [40 deg off, GT] of the drill against their exact
    masks: the bottle goes back to its first iteration, the drill keeps its last; a margin above the IoU gap
    keeps the last for both; a NaN last iteration gives way to the earlier one."""
    ids = [MUSTARD, DRILL]
    masks, K_t = _masks(renderer, ids), torch.from_numpy(K)
    gt = np.stack([GT[i] for i in ids])
    off = np.stack([_turned(GT[i], 40.0) for i in ids])
    first, last = torch.from_numpy(np.stack([gt[0], off[1]])), torch.from_numpy(np.stack([off[0], gt[1]]))
    ious = [silhouette_ious(T, K_t, masks, ids, renderer) for T in (first, last)]
    np.testing.assert_allclose([ious[0][0], ious[1][1]], 1.0, atol=1e-6)  # the exact pose: the mask itself
    gap = ious[0][0] - ious[1][0]
    assert 0.1 < gap < 0.9 and ious[1][1] > ious[0][1] + 0.1
    assert guarded_iterations([first, last], K_t, masks, ids, renderer, 0.05).tolist() == [0, 1]
    assert guarded_iterations([first, last], K_t, masks, ids, renderer, gap + 0.01).tolist() == [1, 1]
    assert guarded_iterations([last], K_t, masks, ids, renderer, 0.05).tolist() == [0, 0]  # one iteration: no choice
    broken = last.clone()
    broken[1, 0, 3] = float("nan")
    assert guarded_iterations([first, broken], K_t, masks, ids, renderer, 0.05).tolist() == [0, 0]
