"""Depth ICP on synthetic depth images made with the real renderer: recovery of known offsets
(1 cm / 5 deg, a 3 cm depth error, occlusion, two objects in one call) and every rejection rule."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh

from cosy_lite.inference.icp import IcpConfig, IcpResult, depth_agreement, refine_pose_icp, refine_poses_icp, rotation_angle_deg
from cosy_lite.render.renderer import GlRenderer

MUSTARD, DRILL, PLANE, OCCLUDER, CAN = 5, 15, 90, 91, 92  # YCB-V mustard bottle and power drill: no symmetry
K = np.array([[1066.778, 0.0, 312.9869], [0.0, 1067.487, 241.3109], [0.0, 0.0, 1.0]])  # YCB-V camera
SIZE = (480, 640)
NOISE = 0.001  # m, Gaussian depth noise


def _T(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _rodrigues(v) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(v, dtype=np.float64))[0]


GT = {
    MUSTARD: _T(_rodrigues([0.6, -0.9, 0.4]), [0.06, -0.03, 0.80]),
    DRILL: _T(_rodrigues([-1.2, 0.3, 0.5]), [-0.12, 0.05, 0.90]),
    CAN: _T(_rodrigues([1.1, 0.2, 0.3]), [0.02, 0.04, 0.85]),  # a closed cylinder, axis z
}
CAN_SYMMETRIES = np.stack([_T(_rodrigues([0.0, 0.0, a]), [0.0, 0.0, 0.0]) for a in np.radians(np.arange(0, 360, 0.5))])
T_PLANE = _T(np.eye(3), [0.0, 0.0, 1.00])  # a wall behind both objects: the mask decides what is the object
T_OCCLUDER = _T(np.eye(3), [0.06, 0.03, 0.65])  # a box in front of the lower part of the mustard bottle


@pytest.fixture(scope="module")
def renderer():
    from cosy_lite.synth.objects import load_ycb_mesh

    meshes = {
        MUSTARD: load_ycb_mesh(MUSTARD), DRILL: load_ycb_mesh(DRILL),
        PLANE: trimesh.creation.box(extents=(3.0, 3.0, 0.01)), OCCLUDER: trimesh.creation.box(extents=(0.2, 0.05, 0.05)),
        CAN: trimesh.creation.cylinder(radius=0.04, height=0.12, sections=64),
    }
    with GlRenderer(meshes=meshes) as r:
        yield r


def _scene(renderer, obj_ids, occluder: bool = False, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Measured depth [H,W] (m, + noise) of the objects at GT in front of the wall, and their visible masks [N,H,W]."""
    ids = [*obj_ids, PLANE] + ([OCCLUDER] if occluder else [])
    poses = [GT[i] for i in obj_ids] + [T_PLANE] + ([T_OCCLUDER] if occluder else [])
    d = renderer.render(ids, np.stack(poses), K, SIZE, depth_only=True).depth
    d = np.where(d > 0, d, np.inf)
    nearest = d.argmin(axis=0)
    depth = d.min(axis=0)
    depth[~np.isfinite(depth)] = 0.0
    depth += np.random.default_rng(seed).normal(0.0, NOISE, depth.shape) * (depth > 0)
    masks = np.stack([(nearest == k) & np.isfinite(d[k]) for k in range(len(obj_ids))])
    return depth.astype(np.float32), masks


def _perturbed(TCO: np.ndarray, deg: float, metres: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    axis, direction = (v / np.linalg.norm(v) for v in rng.normal(size=(2, 3)))
    out = TCO.copy()
    out[:3, :3] = _rodrigues(np.radians(deg) * axis) @ TCO[:3, :3]
    out[:3, 3] += metres * direction
    return out


def _errors(TCO: np.ndarray, TCO_gt: np.ndarray) -> tuple[float, float]:
    """(translation error mm, rotation error deg)."""
    return float(np.linalg.norm(TCO[:3, 3] - TCO_gt[:3, 3]) * 1000), rotation_angle_deg(TCO[:3, :3] @ TCO_gt[:3, :3].T)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_recovers_1cm_5deg(renderer, seed):
    depth, masks = _scene(renderer, [MUSTARD])
    start = _perturbed(GT[MUSTARD], 5.0, 0.01, seed)
    assert _errors(start, GT[MUSTARD]) == pytest.approx((10.0, 5.0), abs=1e-6)
    res = refine_pose_icp(start, K, depth, masks[0], renderer, MUSTARD)
    e_t, e_r = _errors(res.TCO, GT[MUSTARD])
    print(f"seed {seed}: {e_t:.3f} mm, {e_r:.3f} deg, fitness {res.fitness:.3f}, rmse {res.inlier_rmse * 1000:.2f} mm, "
          f"{res.n_points}/{res.n_model_points} points, {res.seconds * 1000:.1f} ms {res.timings}")
    assert res.accepted and res.reason == ""
    assert e_t < 2.0 and e_r < 1.0  # measured: ~0.05 mm, ~0.1 deg
    assert res.fitness > 0.95 and res.inlier_rmse < 2 * NOISE
    assert res.delta_translation == pytest.approx(0.01, abs=0.002) and res.delta_rotation_deg == pytest.approx(5.0, abs=1.0)
    assert res.n_points >= 500 and res.n_model_points >= 500
    assert set(res.timings) == {"render", "clouds", "normals", "icp", "agreement"}
    assert res.seconds == pytest.approx(sum(res.timings.values()))


def test_recovers_3cm_depth_error_and_occlusion(renderer):
    """An RGB estimate typically errs in depth: 3 cm along the viewing ray + 3 deg, lower part occluded."""
    depth, masks = _scene(renderer, [MUSTARD], occluder=True)
    full = renderer.render([MUSTARD], GT[MUSTARD][None], K, SIZE, depth_only=True).mask[0]
    assert 0.5 < masks[0].sum() / full.sum() < 0.9  # the occluder hides part of the bottle
    start = _perturbed(GT[MUSTARD], 3.0, 0.0, seed=4)
    start[:3, 3] *= 1.0 + 0.03 / start[2, 3]
    res = refine_pose_icp(start, K, depth, masks[0], renderer, MUSTARD)
    e_t, e_r = _errors(res.TCO, GT[MUSTARD])
    print(f"3 cm depth + occlusion: {e_t:.3f} mm, {e_r:.3f} deg, fitness {res.fitness:.3f}")
    assert res.accepted and e_t < 2.0 and e_r < 1.0
    # pre-alignment matters where the depth error exceeds the first stage's 4 cm correspondences (at
    # 3 cm both end within 0.002 mm of each other): from 8 cm, 0.05 mm with it, 176 mm without it
    far = start.copy()
    far[:3, 3] *= 1.0 + 0.05 / start[2, 3]
    assert _errors(refine_pose_icp(far, K, depth, masks[0], renderer, MUSTARD).TCO, GT[MUSTARD])[0] < 2.0
    no_prealign = refine_pose_icp(far, K, depth, masks[0], renderer, MUSTARD, IcpConfig(depth_prealign=False))
    assert not no_prealign.accepted or _errors(no_prealign.TCO, GT[MUSTARD])[0] > 20.0


def test_two_objects_one_render_call(renderer):
    depth, masks = _scene(renderer, [MUSTARD, DRILL])
    calls = []

    class Counting:
        def render(self, *args, **kwargs):
            calls.append(args[3])
            return renderer.render(*args, **kwargs)

        def mesh(self, obj_id):
            return renderer.mesh(obj_id)

    starts = np.stack([_perturbed(GT[MUSTARD], 5.0, 0.01, 5), _perturbed(GT[DRILL], 5.0, 0.01, 6)])
    results = refine_poses_icp(starts, K, depth, masks, Counting(), [MUSTARD, DRILL])
    # one call for ICP, one for the agreement check of the results; windows smaller than the image
    assert len(calls) == 2 and all(c[0] < SIZE[0] and c[1] < SIZE[1] for c in calls)
    for res, obj_id in zip(results, [MUSTARD, DRILL]):
        e_t, e_r = _errors(res.TCO, GT[obj_id])
        print(f"obj {obj_id}: {e_t:.3f} mm, {e_r:.3f} deg, {res.seconds * 1000:.1f} ms")
        assert res.accepted and e_t < 2.0 and e_r < 1.0 and res.seconds > 0


def test_windows_of_different_sizes_are_rendered_on_canvases_of_their_size(renderer):
    """A large and a small window: two render calls, each canvas at most twice its window, and each
    window's depth that of one render of both on the large canvas (to float32 rounding)."""
    from cosy_lite.inference.icp import _render_windows

    calls = []

    class Counting:
        def render(self, *args, **kwargs):
            calls.append(args[3])
            return renderer.render(*args, **kwargs)

    TCO = np.stack([GT[MUSTARD], GT[DRILL], GT[MUSTARD]])
    windows = {0: (100, 60, 400, 380), 1: (131, 261, 211, 341), 2: (90, 50, 390, 360)}  # 1: about the drill's origin
    out = _render_windows(Counting(), [MUSTARD, DRILL, MUSTARD], TCO, K, windows, [0, 1, 2])
    assert sorted(calls) == [(80, 80), (320, 300)]
    K_big = np.repeat(K[None], 3, axis=0)
    K_big[:, 0, 2] -= [w[0] for w in windows.values()]
    K_big[:, 1, 2] -= [w[1] for w in windows.values()]
    big = renderer.render([MUSTARD, DRILL, MUSTARD], TCO, K_big, (320, 300), depth_only=True).depth
    for j, (x0, y0, x1, y1) in windows.items():
        assert out[j].shape[0] >= y1 - y0 and out[j].shape[1] >= x1 - x0
        np.testing.assert_allclose(out[j][: y1 - y0, : x1 - x0], big[j][: y1 - y0, : x1 - x0], rtol=0, atol=1e-5)
    assert (out[0] > 0).mean() > 0.05 and (out[1] > 0).mean() > 0.2


def test_windows_rendered_every_stride_pixels_are_the_full_render_sampled(renderer):
    """ICP samples every pixel_stride-th pixel: a window rendered at stride 2 is the full-resolution
    render's ``[::2, ::2]`` (same rays), at a quarter of the pixels; odd window sides round up."""
    from cosy_lite.inference.icp import _render_windows

    TCO = np.stack([GT[MUSTARD], GT[DRILL]])
    windows = {0: (101, 61, 400, 381), 1: (131, 261, 212, 342)}
    full = _render_windows(renderer, [MUSTARD, DRILL], TCO, K, windows, [0, 1])
    half = _render_windows(renderer, [MUSTARD, DRILL], TCO, K, windows, [0, 1], {0: 2, 1: 2})
    for j, (x0, y0, x1, y1) in windows.items():
        want = full[j][: y1 - y0 : 2, : x1 - x0 : 2]
        got = half[j][: want.shape[0], : want.shape[1]]
        assert want.shape == (-(-(y1 - y0) // 2), -(-(x1 - x0) // 2))
        both = (want > 0) & (got > 0)
        assert both.sum() > 100 and (want > 0).sum() - both.sum() <= 0.02 * (want > 0).sum()
        np.testing.assert_allclose(got[both], want[both], rtol=0, atol=1e-4)  # depth at the same rays (m)


def test_relative_tolerance_ends_a_stage_early(renderer):
    """One 3 cm stage of up to 30 iterations from 1 cm / 5 deg off: run to 1e-6 it ends within 0.5 mm
    (measured 0.06 mm; 0.12 mm at the default 1e-4); stopped once fitness and RMSE change by under 1 %,
    it ends millimetres off (measured 2.9 mm): the tolerance reaches Open3D."""
    depth, masks = _scene(renderer, [MUSTARD])
    start = _perturbed(GT[MUSTARD], 5.0, 0.01, seed=1)
    errors = {}
    for tol in (1e-6, 1e-2):
        cfg = IcpConfig(max_correspondence_distances=[0.03], iterations=[30], relative_tolerance=tol)
        res = refine_pose_icp(start, K, depth, masks[0], renderer, MUSTARD, cfg)
        errors[tol] = _errors(res.TCO, GT[MUSTARD])[0]
    assert errors[1e-6] < 0.5 and errors[1e-2] > 1.0, errors


def test_symmetric_object(renderer):
    """A cylinder: the turn about its axis is free; given the symmetries, the pose closest to the start is returned."""
    depth, masks = _scene(renderer, [CAN])
    start = _perturbed(GT[CAN], 5.0, 0.01, 7)
    res = refine_pose_icp(start, K, depth, masks[0], renderer, CAN, symmetries=CAN_SYMMETRIES)
    axis_err = np.degrees(np.arccos(np.clip(res.TCO[:3, 2] @ GT[CAN][:3, 2], -1.0, 1.0)))
    e_t = np.linalg.norm(res.TCO[:3, 3] - GT[CAN][:3, 3]) * 1000
    print(f"cylinder: {e_t:.3f} mm, axis {axis_err:.3f} deg, update {res.delta_rotation_deg:.2f} deg")
    assert res.accepted and e_t < 2.0 and axis_err < 1.0
    assert res.delta_rotation_deg <= 5.0 + 1.0  # the turn about the axis is not counted
    with pytest.raises(ValueError, match="symmetries must hold one"):
        refine_poses_icp(start[None], K, depth, masks, renderer, [CAN], symmetries=[])


def test_rejects_without_data(renderer):
    depth, masks = _scene(renderer, [MUSTARD])
    start = _perturbed(GT[MUSTARD], 5.0, 0.01, 1)
    empty = refine_pose_icp(start, K, depth, np.zeros(SIZE, bool), renderer, MUSTARD)
    assert not empty.accepted and empty.reason == "empty mask" and np.array_equal(empty.TCO, start)
    no_depth = refine_pose_icp(start, K, np.zeros(SIZE, np.float32), masks[0], renderer, MUSTARD)
    assert not no_depth.accepted and no_depth.reason.startswith("too few measured depth points in the mask (0 < 50)")
    nan_depth = refine_pose_icp(start, K, np.full(SIZE, np.nan, np.float32), masks[0], renderer, MUSTARD)
    assert not nan_depth.accepted and "too few measured" in nan_depth.reason
    behind = start.copy()
    behind[2, 3] = -0.5
    res = refine_pose_icp(behind, K, depth, masks[0], renderer, MUSTARD)
    assert not res.accepted and "in front of the camera" in res.reason


LIMITS = IcpConfig(max_rotation_deg=15.0, max_translation=0.05, min_fitness=0.5, max_inlier_rmse=0.004,
                   check_agreement=False)  # the first version's limits, without the agreement check


@pytest.mark.parametrize(
    "offset, reason",
    [((0.2, 0.0, 0.0), "fitness"), ((0.0, 0.0, 0.2), "max_translation"), ((0.0, 0.05, 0.0), "")],
)
def test_far_start_never_accepts_a_wild_pose(renderer, offset, reason):
    """With the limits: 20 cm to the side: no correspondences; 20 cm deeper: the depth pre-alignment
    would move it back, beyond max_translation. 5 cm (beyond the first stage's range): rejected or
    refined, never wild. With the defaults (no limits, agreement check): never worse than the start,
    and the two within reach of the pre-alignment and the 4 cm first stage are brought back."""
    depth, masks = _scene(renderer, [MUSTARD])
    start = GT[MUSTARD].copy()
    start[:3, 3] += offset
    res = refine_pose_icp(start, K, depth, masks[0], renderer, MUSTARD, LIMITS)
    print(offset, res.accepted, res.reason, f"fitness {res.fitness:.3f}", _errors(res.TCO, GT[MUSTARD]))
    if reason:
        assert not res.accepted and reason in res.reason and np.array_equal(res.TCO, start)
    if res.accepted:
        assert _errors(res.TCO, GT[MUSTARD])[0] < 5.0
    res = refine_pose_icp(start, K, depth, masks[0], renderer, MUSTARD)
    print("defaults:", res.accepted, res.reason, _errors(res.TCO, GT[MUSTARD]))
    assert _errors(res.TCO, GT[MUSTARD])[0] <= _errors(start, GT[MUSTARD])[0] + 1e-6
    if offset[0] == 0.0:
        assert res.accepted and _errors(res.TCO, GT[MUSTARD])[0] < 2.0  # measured 0.07-0.09 mm


def test_rotation_limit(renderer):
    depth, masks = _scene(renderer, [MUSTARD])
    start = _perturbed(GT[MUSTARD], 5.0, 0.0, 2)
    res = refine_pose_icp(start, K, depth, masks[0], renderer, MUSTARD, IcpConfig(max_rotation_deg=2.0))
    assert not res.accepted and "max_rotation_deg 2.0" in res.reason and res.delta_rotation_deg == pytest.approx(5.0, abs=1.0)


def test_input_errors(renderer):
    depth, masks = _scene(renderer, [MUSTARD])
    bad = GT[MUSTARD].copy()
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match=r"TCO is not finite .* index \[0\]"):
        refine_pose_icp(bad, K, depth, masks[0], renderer, MUSTARD)
    with pytest.raises(ValueError, match="masks must be"):
        refine_pose_icp(GT[MUSTARD], K, depth, masks[0, :100], renderer, MUSTARD)
    with pytest.raises(ValueError, match="TCO must be"):
        refine_poses_icp(GT[MUSTARD][None], K, depth, masks, renderer, [MUSTARD, DRILL])
    with pytest.raises(ValueError, match="same length"):
        IcpConfig(max_correspondence_distances=[0.01], iterations=[5, 5])
    with pytest.raises(ValueError, match="robust_kernel"):
        IcpConfig(robust_kernel="tukee")
    assert refine_poses_icp(np.zeros((0, 4, 4)), K, depth, np.zeros((0, *SIZE), bool), renderer, []) == []


def test_config_loads_from_yaml(tmp_path):
    from cosy_lite.config import load_config

    path = tmp_path / "icp.yaml"
    path.write_text("max_correspondence_distances: [0.03, 0.01]\niterations: [20, 10]\nrobust_kernel: huber\n")
    cfg = load_config(IcpConfig, path, ["voxel_size=0.005"])
    assert cfg.max_correspondence_distances == [0.03, 0.01] and cfg.robust_kernel == "huber" and cfg.voxel_size == 0.005
    assert isinstance(IcpResult(np.eye(4), True).timings, dict)
    assert load_config(IcpConfig, path, ["relative_tolerance=1e-6"]).relative_tolerance == 1e-6
    with pytest.raises(ValueError, match="relative_tolerance"):
        IcpConfig(relative_tolerance=1.0)


def test_depth_agreement_ranks_the_true_pose_first(renderer):
    """The GT pose explains mask and depth (score ~1, occluded part included); a 1 cm shift, a turn of
    the drill, a pose floating 5 cm in front, and an empty mask score lower, in that order of harm."""
    depth, masks = _scene(renderer, [MUSTARD, DRILL], occluder=True)
    gt = np.stack([GT[MUSTARD], GT[DRILL]])
    ids = [MUSTARD, DRILL]
    s_gt = depth_agreement(gt, K, depth, masks, renderer, ids)
    assert s_gt.min() > 0.95, s_gt  # measured 1.0 (the masks come from the same renders)
    shifted = gt.copy()
    shifted[:, 0, 3] += 0.01
    turned = np.stack([_perturbed(gt[k], 30.0, 0.0, seed=k) for k in range(2)])
    floating = gt.copy()
    floating[:, :3, 3] *= ((gt[:, 2, 3] - 0.05) / gt[:, 2, 3])[:, None]  # 5 cm nearer along the ray: same place in the image
    scores = {name: depth_agreement(T, K, depth, masks, renderer, ids)
              for name, T in (("shifted", shifted), ("turned", turned), ("floating", floating))}
    for name, s in scores.items():
        assert (s < s_gt - 0.1).all(), (name, s, s_gt)
    assert (scores["floating"] < 0.2).all(), scores["floating"]  # no pixel within 2 cm
    empty = masks.copy()
    empty[1] = False
    assert depth_agreement(gt, K, depth, empty, renderer, ids)[1] == 0.0
    behind = gt.copy()
    behind[0, 2, 3] = -0.5
    assert depth_agreement(behind, K, depth, masks, renderer, ids)[0] == 0.0


def test_rejection_kinds_name_the_limit(renderer):
    from cosy_lite.inference.icp import icp_rejection_kind

    depth, masks = _scene(renderer, [MUSTARD])
    start = GT[MUSTARD].copy()
    start[2, 3] += 0.2
    res = refine_pose_icp(start, K, depth, masks[0], renderer, MUSTARD, LIMITS)
    assert icp_rejection_kind(res.reason) == "max_translation"
    assert icp_rejection_kind("too few measured depth points in the mask (3 < 50)") == "too few measured depth points in the mask"
    assert icp_rejection_kind("empty mask") == "empty mask"
    assert icp_rejection_kind("fitness 0.100 < min_fitness 0.5") == "min_fitness"


def test_an_icp_result_that_agrees_less_than_its_start_is_rejected(renderer):
    """The agreement check on real renders: a result 3 cm off, from the GT start, is put back (reason
    and agreement of the start); a result at GT, from a start 3 cm off, stays."""
    from cosy_lite.inference.icp import _check_agreement, _window

    depth, masks = _scene(renderer, [MUSTARD, DRILL])
    gt = np.stack([GT[MUSTARD], GT[DRILL]])
    off = gt.copy()
    off[:, 0, 3] += 0.03
    starts = np.stack([gt[0], off[1]])
    results = [IcpResult(off[0].copy(), True), IcpResult(gt[1].copy(), True)]
    cfg = IcpConfig()
    from cosy_lite.geometry.depth import mask_box
    from cosy_lite.inference.icp import _box_corners, _render_windows, pixel_stride

    ids = [MUSTARD, DRILL]
    windows = [_window(starts[i], K, _box_corners(renderer.mesh(o)), mask_box(masks[i]), SIZE, cfg.window_margin)
               for i, o in enumerate(ids)]
    strides = {i: pixel_stride(cfg.voxel_size, K, starts[i, 2, 3]) for i in range(2)}  # as ICP renders them
    assert strides == {0: 2, 1: 2}
    rendered = dict(enumerate(_render_windows(renderer, ids, starts, K, dict(enumerate(windows)), [0, 1], strides)))
    _check_agreement(results, rendered, strides, windows, starts, K, depth, masks, renderer, ids, cfg)
    assert not results[0].accepted and "agrees less with the depth than its start" in results[0].reason
    np.testing.assert_array_equal(results[0].TCO, gt[0])
    assert results[0].agreement > 0.95
    assert results[1].accepted and results[1].agreement > 0.95
    np.testing.assert_array_equal(results[1].TCO, gt[1])
    assert set(results[0].timings) == {"agreement"}
