"""The disentangled symmetric loss, model points and symmetry tensors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cosy_lite.bop.io import ModelInfo
from cosy_lite.geometry.points import object_symmetries, sample_model_points, symmetry_tensor
from cosy_lite.geometry.rotations import axis_angle_to_matrix, random_rotations
from cosy_lite.nets.losses import closest_symmetric_pose, disentangled_loss
from cosy_lite.nets.pose_update import apply_pose_update, pose_update_targets, rotation_update

F64 = torch.float64


def _K(B: int, dtype=F64) -> torch.Tensor:
    return torch.tensor([[600.0, 0.0, 159.5], [0.0, 610.0, 119.5], [0.0, 0.0, 1.0]], dtype=dtype).expand(B, 3, 3)


def _poses(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    T = torch.eye(4, dtype=F64).repeat(n, 1, 1)
    T[:, :3, :3] = random_rotations(n, g)
    lo, size = torch.tensor([-0.1, -0.1, 0.6], dtype=F64), torch.tensor([0.2, 0.2, 0.5], dtype=F64)
    T[:, :3, 3] = lo + torch.rand(n, 3, generator=g, dtype=F64) * size
    return T


def _box_points(extents=(0.12, 0.07, 0.04), n_per_edge: int = 5) -> torch.Tensor:
    """Points on a grid through a box centred at the origin (m): [n^3,3]."""
    axes = [torch.linspace(-e / 2, e / 2, n_per_edge, dtype=F64) for e in extents]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _cylinder_points(radius=0.04, height=0.1, n_angles=36) -> torch.Tensor:
    """Two rings of points at angles k 2 pi / n_angles, z = +-h/2: invariant under the discretised
    rotations about z and the flip about x (so their centroid, the origin, is fixed)."""
    a = torch.arange(n_angles, dtype=F64) * (2 * math.pi / n_angles)
    ring = torch.stack([radius * torch.cos(a), radius * torch.sin(a)], 1)
    return torch.cat([torch.cat([ring, torch.full((n_angles, 1), z, dtype=F64)], 1) for z in (-height / 2, height / 2)])


def _info(discrete=(), continuous=()) -> ModelInfo:
    disc = np.asarray(discrete, dtype=np.float64).reshape(-1, 4, 4)
    return ModelInfo(1, 0.2, np.zeros(3), np.ones(3) * 0.1, disc, list(continuous))


def _flip(axis, angle=math.pi, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    S = np.eye(4)
    S[:3, :3] = axis_angle_to_matrix(torch.tensor([axis], dtype=F64) * angle)[0].numpy()
    S[:3, 3] = t
    return S


CYLINDER = _info(discrete=[_flip([1, 0, 0])], continuous=[(np.array([0.0, 0.0, 1.0]), np.zeros(3))])


def _batch(sym_sets, points, B_per_set=3, seed=0):
    """B items: poses, a symmetry tensor repeating each set, points expanded."""
    syms, mask = symmetry_tensor([s for s in sym_sets for _ in range(B_per_set)], dtype=F64)
    B = len(syms)
    return _poses(B, seed), _poses(B, seed + 100), syms, mask, points.expand(B, -1, 3)


def _random_delta(B: int, seed: int, scale=0.1) -> torch.Tensor:
    d = torch.randn(B, 9, generator=torch.Generator().manual_seed(seed), dtype=F64) * scale
    d[:, 6:8] *= 100.0  # pixels
    return d


# ----------------------------------------------------------------------------- the loss


def test_zero_at_gt_and_at_every_symmetric_gt():
    cyl = object_symmetries(CYLINDER, n_continuous=36)
    TCO_in, TCO_gt, syms, mask, pts = _batch([np.eye(4)[None], cyl], _cylinder_points())
    K = _K(len(TCO_in))
    terms = disentangled_loss(TCO_in, K, pose_update_targets(TCO_in, TCO_gt, K), TCO_gt, pts, syms, mask)
    assert float(terms.total) < 1e-12 and float(terms.per_item.max()) < 1e-12
    torch.testing.assert_close(terms.TCO_pred, TCO_gt)
    # Aiming at GT @ S for a symmetry S of the set (the 10th rotation, flipped) is also exact.
    S = torch.as_tensor(cyl[36 + 10])
    target = TCO_gt[3:] @ S
    delta = pose_update_targets(TCO_in[3:], target, K[3:])
    terms = disentangled_loss(TCO_in[3:], K[3:], delta, TCO_gt[3:], pts[3:], syms[3:], mask[3:])
    assert float(terms.per_item.max()) < 1e-12
    assert terms.sym_index.tolist() == [46, 46, 46]
    # float32 too.
    f = lambda x: x.float()  # noqa: E731
    terms = disentangled_loss(f(TCO_in), f(K), pose_update_targets(f(TCO_in), f(TCO_gt), f(K)), f(TCO_gt), f(pts), f(syms), mask)
    assert terms.total.dtype == torch.float32 and float(terms.total) < 2e-6


def test_by_hand():
    """Identity poses at z = 1, two points (+-0.1, 0, 0); vx = 6 px at f = 600 moves x by 1 cm;
    vz = e^0.1 moves z by 10.5 cm; a 90 deg turn about z moves the points by 0.1 in x and y."""
    TCO = torch.eye(4, dtype=F64)[None].clone()
    TCO[0, 2, 3] = 1.0
    pts = torch.tensor([[[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]]], dtype=F64)
    syms, mask = symmetry_tensor([np.eye(4)[None]], dtype=F64)
    delta = torch.zeros(1, 9, dtype=F64)
    delta[0, 6], delta[0, 8] = 6.0, 0.1
    delta[0, :6] = torch.tensor([0.0, 1.0, 0.0, -1.0, 0.0, 0.0], dtype=F64) - torch.tensor([1.0, 0, 0, 0, 1.0, 0], dtype=F64)
    t = disentangled_loss(TCO, _K(1), delta, TCO, pts, syms, mask)
    assert math.isclose(float(t.xy), 0.01 / 3, rel_tol=1e-12)
    assert math.isclose(float(t.depth), (math.exp(0.1) - 1) / 3, rel_tol=1e-12)
    assert math.isclose(float(t.rotation), 0.2 / 3, rel_tol=1e-12)  # each point: |dx| = |dy| = 0.1
    assert math.isclose(float(t.total), float(t.xy + t.depth + t.rotation), rel_tol=1e-12)


def _literal_cosypose(TCO_in, K, delta, TCO_gt, pts, syms, mask):
    """The terms as CosyPose writes them: partial poses from the unsymmetrised GT, points moved, L1
    per coordinate, minimum over the symmetric GT poses for each term separately."""
    cand = TCO_gt[:, None] @ syms
    dR = rotation_update(delta)
    f = torch.stack([K[:, 0, 0], K[:, 1, 1]], 1)
    z_gt, t_in = TCO_gt[:, 2:3, 3], TCO_in[:, :3, 3]
    T_rot, T_xy, T_z = TCO_gt.clone(), TCO_gt.clone(), TCO_gt.clone()
    T_rot[:, :3, :3] = dR @ TCO_in[:, :3, :3]
    T_xy[:, :2, 3] = (delta[:, 6:8] / f + t_in[:, :2] / t_in[:, 2:3]) * z_gt
    T_z[:, 2, 3] = torch.exp(delta[:, 8]) * t_in[:, 2]

    def term(T):
        p = pts @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]
        pc = torch.einsum("bsij,bnj->bsni", cand[..., :3, :3], pts) + cand[..., None, :3, 3]
        return (p[:, None] - pc).abs().mean((-1, -2)).masked_fill(~mask, float("inf")).min(1).values

    return term(T_rot), term(T_xy), term(T_z)


def test_equals_cosypose_for_symmetries_fixing_the_origin():
    """Box with a 180 deg flip and a cylinder (continuous + flip): same terms as CosyPose's per-term
    minima (symmetric point sets, so their centroid is fixed by the symmetries)."""
    cyl = object_symmetries(CYLINDER, n_continuous=36)
    box_pts = _box_points()
    for sym, pts in [(np.stack([np.eye(4), _flip([0, 0, 1])]), box_pts), (cyl, _cylinder_points())]:
        TCO_in, TCO_gt, syms, mask, P = _batch([sym], pts, B_per_set=6, seed=7)
        TCO_in = TCO_gt @ torch.as_tensor(sym[-1]) @ torch.as_tensor(_flip([0.3, 0.5, 0.8], 0.3))  # near a symmetric GT
        delta = _random_delta(6, 1, scale=0.05)
        t = disentangled_loss(TCO_in, _K(6), delta, TCO_gt, P, syms, mask)
        ref = _literal_cosypose(TCO_in, _K(6), delta, TCO_gt, P, syms, mask)
        torch.testing.assert_close(t.rotation, ref[0].mean())
        torch.testing.assert_close(t.xy, ref[1].mean())
        torch.testing.assert_close(t.depth, ref[2].mean())
        torch.testing.assert_close(t.per_item, ref[0] + ref[1] + ref[2])


@pytest.mark.parametrize("kind", ["box_flip", "cylinder_in_set", "offset_flip"])
def test_invariant_to_a_declared_symmetry(kind):
    """GT replaced by GT @ S (S a symmetry of the set) gives the same loss for any output."""
    if kind == "box_flip":
        sym, pts, S = np.stack([np.eye(4), _flip([0, 0, 1])]), _box_points(), _flip([0, 0, 1])
    elif kind == "cylinder_in_set":
        sym, pts = object_symmetries(CYLINDER, n_continuous=36), _cylinder_points()
        S = sym[36 + 7]  # rotation by 70 deg about z, then the flip
    else:  # 180 deg about x through (0, 0, 5 mm): moves the origin to (0, 0, 10 mm)
        S = _flip([1, 0, 0], t=(0.0, 0.0, 0.01))
        sym, pts = np.stack([np.eye(4), S]), _box_points()
    TCO_in, TCO_gt, syms, mask, P = _batch([sym], pts, B_per_set=8, seed=3)
    delta = _random_delta(8, 2)
    a = disentangled_loss(TCO_in, _K(8), delta, TCO_gt, P, syms, mask)
    b = disentangled_loss(TCO_in, _K(8), delta, TCO_gt @ torch.as_tensor(S), P, syms, mask)
    torch.testing.assert_close(a.per_item, b.per_item, rtol=1e-12, atol=1e-14)
    assert float(a.total) > 0.005  # a real, non-trivial loss
    if kind == "offset_flip":  # aiming at the flipped pose is exact too (per-term minima would not be)
        target = TCO_gt @ torch.as_tensor(S)
        t = disentangled_loss(TCO_in, _K(8), pose_update_targets(TCO_in, target, _K(8)), TCO_gt, P, syms, mask)
        assert float(t.per_item.max()) < 1e-12


def test_cylinder_rotation_between_discrete_steps_changes_the_loss_little():
    """A true continuous symmetry (GT turned 5 deg, half a 10 deg step) changes the loss by less
    than the discretisation error of 5 deg on the rim (r sin 5deg ~ 3.5 mm, /3 per coordinate)."""
    sym, pts = object_symmetries(CYLINDER, n_continuous=36), _cylinder_points(n_angles=72)
    TCO_in, TCO_gt, syms, mask, P = _batch([sym], pts, B_per_set=8, seed=4)
    delta = _random_delta(8, 5)
    a = disentangled_loss(TCO_in, _K(8), delta, TCO_gt, P, syms, mask)
    b = disentangled_loss(TCO_in, _K(8), delta, TCO_gt @ torch.as_tensor(_flip([0, 0, 1], math.radians(5.0))), P, syms, mask)
    assert float((a.per_item - b.per_item).abs().max()) < 0.04 * math.sin(math.radians(5.0))


def test_increases_monotonically_with_rotation_error():
    TCO_in, TCO_gt, syms, mask, P = _batch([np.eye(4)[None]], _box_points(), B_per_set=1, seed=9)
    K = _K(1)
    exact = pose_update_targets(TCO_in, TCO_gt, K)
    axis = torch.nn.functional.normalize(torch.tensor([[0.6, -0.3, 0.74]], dtype=F64), dim=1)
    losses = []
    for deg in range(0, 31, 3):
        wrong = TCO_gt.clone()
        wrong[:, :3, :3] = axis_angle_to_matrix(axis * math.radians(deg)) @ TCO_gt[:, :3, :3]
        delta = torch.cat([pose_update_targets(TCO_in, wrong, K)[:, :6], exact[:, 6:]], 1)
        t = disentangled_loss(TCO_in, K, delta, TCO_gt, P, syms, mask)
        assert float(t.xy) < 1e-12 and float(t.depth) < 1e-12
        losses.append(float(t.total))
    assert losses[0] < 1e-12
    assert all(b > a for a, b in zip(losses, losses[1:])), losses
    # Small angles: about linear (30 deg within 5% of 10 x 3 deg).
    assert abs(losses[-1] / (10 * losses[1]) - 1) < 0.05


def test_gradients_are_finite_and_reach_every_output():
    sets = [np.eye(4)[None], object_symmetries(CYLINDER, 8)]
    TCO_in, TCO_gt, syms, mask, P = _batch(sets, _cylinder_points(n_angles=8), B_per_set=2, seed=11)
    delta = _random_delta(4, 3).requires_grad_()
    disentangled_loss(TCO_in, _K(4), delta, TCO_gt, P, syms, mask).total.backward()
    g = delta.grad
    assert bool(torch.isfinite(g).all())
    assert bool((g.abs().sum(0) > 0).all()), g
    # And they are the true gradients (away from the kinks of |.| and min).
    d = _random_delta(4, 4).requires_grad_()
    torch.autograd.gradcheck(lambda x: disentangled_loss(TCO_in, _K(4), x, TCO_gt, P, syms, mask).per_item, (d,))


def test_padding_is_ignored():
    """A padded (masked) entry that would match the prediction exactly does not count."""
    TCO_in, TCO_gt, _, _, P = _batch([np.eye(4)[None]], _box_points(), B_per_set=2, seed=12)
    S_fake = torch.as_tensor(_flip([0, 1, 0]))
    syms = torch.stack([torch.eye(4, dtype=F64), S_fake])[None].repeat(2, 1, 1, 1)
    delta = pose_update_targets(TCO_in, TCO_gt @ S_fake, _K(2))
    masked = disentangled_loss(TCO_in, _K(2), delta, TCO_gt, P, syms, torch.tensor([[True, False]] * 2))
    unmasked = disentangled_loss(TCO_in, _K(2), delta, TCO_gt, P, syms, torch.tensor([[True, True]] * 2))
    assert float(unmasked.total) < 1e-12 and float(masked.total) > 0.01
    with pytest.raises(ValueError, match="sym_mask"):
        disentangled_loss(TCO_in, _K(2), delta, TCO_gt, P, syms, torch.tensor([[False, False]] * 2))
    with pytest.raises(ValueError, match="delta"):
        disentangled_loss(TCO_in, _K(2), delta[:, :7], TCO_gt, P, syms, torch.tensor([[True, False]] * 2))


def test_closest_symmetric_pose():
    sym = object_symmetries(CYLINDER, n_continuous=36)
    _, TCO_gt, syms, mask, P = _batch([sym], _cylinder_points(), B_per_set=4, seed=13)
    near = TCO_gt @ torch.as_tensor(sym[20]) @ torch.as_tensor(_flip([0.2, 0.9, 0.1], math.radians(2.0)))
    torch.testing.assert_close(closest_symmetric_pose(near, TCO_gt, P, syms, mask), TCO_gt @ torch.as_tensor(sym[20]))


# ----------------------------------------------------------------------------- points and symmetry sets


def test_sample_model_points_vertices_and_surface():
    v = _box_points((0.1, 0.06, 0.04), n_per_edge=3).numpy()  # 27 vertices
    a = sample_model_points(v, n=20, seed=1)
    assert a.shape == (20, 3) and a.dtype == torch.float32
    assert torch.equal(a, sample_model_points(v, n=20, seed=1))
    assert not torch.equal(a, sample_model_points(v, n=20, seed=2))
    assert len({tuple(p) for p in a.tolist()}) == 20  # a subset without repeats
    assert sample_model_points(v, n=40).shape == (40, 3)  # all 27, then repeats
    # Surface sampling of a box mesh: every point on a face (one coordinate at +-half extent).
    import trimesh

    box = trimesh.creation.box(extents=(0.1, 0.06, 0.04))
    s = sample_model_points(box.vertices, n=500, seed=0, faces=box.faces, dtype=F64)
    on_face = ((s.abs() - torch.tensor([0.05, 0.03, 0.02], dtype=F64)).abs() < 1e-9).any(1)
    assert bool(on_face.all())
    # Area-uniform: the two 0.1 x 0.06 faces (z = +-0.02) hold 2 * 0.006 / 0.0248 of the area.
    frac = float(((s[:, 2].abs() - 0.02).abs() < 1e-9).double().mean())
    assert abs(frac - 0.012 / 0.0248) < 0.06


def test_object_symmetries_and_padding():
    cyl = object_symmetries(CYLINDER, n_continuous=36)
    assert cyl.shape == (72, 4, 4) and np.allclose(cyl[0], np.eye(4))
    assert object_symmetries(CYLINDER, n_continuous=64).shape == (128, 4, 4)
    assert object_symmetries(_info()).shape == (1, 4, 4)
    # Rotation k of the continuous set is k * 10 deg about z.
    assert np.allclose(cyl[3, :3, :3], axis_angle_to_matrix(torch.tensor([[0.0, 0.0, math.radians(30.0)]], dtype=F64))[0].numpy())
    padded, mask = symmetry_tensor([np.eye(4)[None], cyl[:5]])
    assert padded.shape == (2, 5, 4, 4) and padded.dtype == torch.float32
    assert mask.tolist() == [[True, False, False, False, False], [True] * 5]
    assert torch.equal(padded[0, 1:], torch.eye(4).expand(4, 4, 4))
    with pytest.raises(ValueError, match="symmetry set 1"):
        symmetry_tensor([np.eye(4)[None], np.eye(3)])


# ----------------------------------------------------------------------------- precision and devices


def _float32_case():
    sym = object_symmetries(CYLINDER, n_continuous=36)
    TCO_in, TCO_gt, syms, mask, P = _batch([np.eye(4)[None], sym], _cylinder_points(), B_per_set=2, seed=21)
    f = lambda x: x.float()  # noqa: E731
    return f(TCO_in), f(_K(4)), f(_random_delta(4, 6)), f(TCO_gt), f(P), f(syms), mask


def test_autocast_does_not_reach_poses_or_loss():
    """Under bf16 autocast (the trainer's mixed precision) with a bf16 network output, the update
    and the loss are computed in float32 as without autocast."""
    TCO_in, K, delta, TCO_gt, P, syms, mask = _float32_case()
    ref = disentangled_loss(TCO_in, K, delta, TCO_gt, P, syms, mask)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        d16 = delta.bfloat16()
        out = disentangled_loss(TCO_in, K, d16, TCO_gt, P, syms, mask)
        T = apply_pose_update(TCO_in, K, d16)
    assert out.total.dtype == torch.float32 and T.dtype == torch.float32
    exact = disentangled_loss(TCO_in, K, d16.float(), TCO_gt, P, syms, mask)
    torch.testing.assert_close(out.per_item, exact.per_item)  # only the bf16 rounding of delta itself
    torch.testing.assert_close(T, exact.TCO_pred)
    assert float((out.per_item - ref.per_item).abs().max()) < 1e-3 * float(ref.per_item.max())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_same_numbers_on_cuda():
    from cosy_lite.geometry.crops import crop_boxes, crop_images, crop_intrinsics
    from cosy_lite.nets.initial_pose import add_pose_noise, initial_pose_from_boxes

    args = _float32_case()
    cpu = disentangled_loss(*args)
    gpu = disentangled_loss(*[a.cuda() for a in args])
    torch.testing.assert_close(gpu.per_item.cpu(), cpu.per_item, rtol=1e-5, atol=1e-7)
    TCO, K, P = args[0], args[1], args[4]
    img = torch.rand(4, 3, 60, 80, generator=torch.Generator().manual_seed(0))
    for dev in ("cpu", "cuda"):
        boxes = crop_boxes(TCO.to(dev), K.to(dev), P.to(dev), crop_resolution=(24, 32))
        out = (boxes, crop_intrinsics(K.to(dev), boxes, (24, 32)), crop_images(img.to(dev), boxes, (24, 32)),
               initial_pose_from_boxes(boxes, K.to(dev), torch.full((4,), 0.1, device=dev)),
               add_pose_noise(TCO.to(dev), generator=torch.Generator().manual_seed(1)))
        if dev == "cpu":
            ref = out
    for a, b in zip(out, ref):
        torch.testing.assert_close(a.cpu(), b, rtol=1e-4, atol=1e-4)
