"""Silhouette-template start poses (``models/silhouette_templates.py``) and the Predictor's
``start="templates"``: a mask rendered at a known pose is matched back to that pose (on and off the
optical axis), empty masks give no pose, and the candidate choice by flow confidence gives the same
poses in the torch loop and the numpy (onnxruntime) loop."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cosy_lite.inference.predictor import Predictor  # noqa: E402

# torchvision before any rendering (see cosy_lite.inference.predictor)
from cosy_lite.inference.settings import InferenceConfig
from cosy_lite.nets.silhouette_templates import (  # noqa: E402
    SilhouetteTemplates,
    mask_boxes,
    occupancy_grids,
    random_rotations,
    ray_rotations,
)
from cosy_lite.weights.loaders import PoseModel  # noqa: E402

H, W = 480, 640
K = np.array([[600.0, 0.0, 318.4], [0.0, 605.0, 241.7], [0.0, 0.0, 1.0]])
CROP = (96, 128)


def _meshes() -> dict[int, object]:
    import trimesh

    rng = np.random.default_rng(0)
    box = trimesh.creation.box(extents=(0.12, 0.07, 0.03))  # no symmetric look-alike within 20 deg
    box.apply_translation([0.01, 0.0, 0.0])  # origin off the box centre: its projection is not the box's centre
    cone = trimesh.creation.cone(radius=0.035, height=0.1, sections=24)
    for m in (box, cone):
        m.visual.vertex_colors = rng.integers(40, 256, size=(len(m.vertices), 4)).astype(np.uint8)
    return {1: box, 2: cone}


def _rotation_error_deg(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    c = (np.trace(np.swapaxes(A, -1, -2) @ B, axis1=-2, axis2=-1) - 1) / 2
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


@pytest.fixture(scope="module")
def scene():
    from cosy_lite.render.renderer import GlRenderer

    meshes = _meshes()
    renderer = GlRenderer(meshes=meshes)
    ids = [1, 2, 1, 1]
    # 0-17 deg off-axis, inside the image
    t = np.array([[0.0, 0.0, 0.6], [0.13, -0.08, 0.7], [-0.17, 0.1, 0.65], [0.1, 0.08, 0.55]])
    R_allo = random_rotations(len(ids), seed=11)
    T_true = np.tile(np.eye(4), (len(ids), 1, 1))
    T_true[:, :3, 3] = t
    T_true[:, :3, :3] = ray_rotations(t) @ R_allo
    masks = renderer.render(ids, T_true, K, (H, W), depth_only=True).depth > 0
    diameters = [float(np.linalg.norm(meshes[i].extents)) for i in (1, 2)]
    return dict(meshes=meshes, renderer=renderer, ids=ids, T_true=T_true, R_allo=R_allo, masks=masks,
                diameters=diameters)


def _templates(scene, extra: int = 300) -> SilhouetteTemplates:
    """Templates with the true allocentric rotations among ``extra`` random ones."""
    rotations = np.concatenate([random_rotations(extra, seed=3), scene["R_allo"]])
    return SilhouetteTemplates(scene["renderer"], [1, 2], scene["diameters"], rotations=rotations)


def test_occupancy_grid_of_a_box_mask():
    m = np.zeros((1, 50, 80), dtype=bool)
    m[0, 10:30, 20:60] = True  # 40 x 20 px: the square of side 42 + 2 is centred on it
    b = mask_boxes(m)
    assert b.tolist() == [[20.0, 10.0, 60.0, 30.0]]
    g = occupancy_grids(m, b, 16)[0].astype(float) / 255
    assert g[:, 0].max() < 0.5 and g[:, -1].max() < 0.5  # margin left and right
    assert g[8, 1:-1].min() > 0.5  # a full row through the middle
    assert abs(g.mean() - 40 * 20 / 44.0 ** 2) < 0.04  # occupied fraction of the square
    assert g[:4].max() < 0.3 and g[-4:].max() < 0.3  # the box is wider than tall: empty top and bottom
    assert np.isnan(mask_boxes(np.zeros((1, 5, 5), dtype=bool))).all()


def test_matching_recovers_the_pose_on_and_off_the_optical_axis(scene):
    st = _templates(scene)
    m = st.match(scene["masks"], scene["ids"], K, top_k=3)
    assert m.TCO.shape == (4, 3, 4, 4) and m.scores.shape == (4, 3) and m.found.all()
    assert (np.diff(m.scores, axis=1) <= 0).all() and (m.scores[:, 0] > 0.9).all()
    T, G = m.TCO[:, 0], scene["T_true"]
    assert _rotation_error_deg(T[:, :3, :3], G[:, :3, :3]).max() < 1.0
    ray = lambda t: t / np.linalg.norm(t, axis=-1, keepdims=True)  # noqa: E731
    off = np.linalg.norm(ray(T[:, :3, 3]) - ray(G[:, :3, 3]), axis=-1)  # rad (x 600 = px)
    assert off[0] < 0.001 and off.max() < 0.005  # measured 0.6 mrad on the axis, at most 2.9 at 12-17 deg off it
    assert (np.abs(T[:, 2, 3] - G[:, 2, 3]) / G[:, 2, 3]).max() < 0.02  # depth from the box sizes: measured <= 0.7 %
    rot = T[:, :3, :3]
    assert np.allclose(rot @ np.swapaxes(rot, 1, 2), np.eye(3), atol=1e-9)


def test_random_templates_place_a_matching_silhouette(scene):
    """2,048 random templates (none is the true rotation; the box's silhouette has look-alikes 180 deg
    away): the best template, rendered where the matcher put it, covers the mask (IoU > 0.8)."""
    st = SilhouetteTemplates(scene["renderer"], [1, 2], scene["diameters"], n_rotations=2048)
    m = st.match(scene["masks"], scene["ids"], K)
    seen = scene["renderer"].render(scene["ids"], m.TCO[:, 0], K, (H, W), depth_only=True).depth > 0
    iou = (seen & scene["masks"]).sum(axis=(1, 2)) / (seen | scene["masks"]).sum(axis=(1, 2))
    assert iou.min() > 0.8, iou


def test_empty_mask_and_bad_arguments(scene):
    st = _templates(scene, extra=10)
    masks = scene["masks"][:2].copy()
    masks[1] = False
    m = st.match(masks, scene["ids"][:2], K, top_k=2)
    assert m.found.tolist() == [True, False] and np.isnan(m.TCO[1]).all() and np.isfinite(m.TCO[0]).all()
    with pytest.raises(KeyError, match="obj_id 7"):
        st.match(scene["masks"][:1], [7], K)
    with pytest.raises(ValueError, match="rotations"):
        SilhouetteTemplates(scene["renderer"], [1], [0.1], rotations=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="diameters"):
        SilhouetteTemplates(scene["renderer"], [1, 2], [0.1])


def _image(scene) -> np.ndarray:
    out = scene["renderer"].render(scene["ids"], scene["T_true"], K, (H, W))
    image = np.random.default_rng(1).integers(0, 90, size=(H, W, 3)).astype(np.uint8)
    for i in np.argsort(-scene["T_true"][:, 2, 3]):
        image[out.mask[i]] = out.rgb[i][out.mask[i]]
    return image


def _detections(scene, with_masks: bool = True):
    from cosy_lite.bop.detections import Detections

    boxes = torch.from_numpy(mask_boxes(scene["masks"])).float()
    return Detections(boxes, torch.tensor(scene["ids"]), torch.tensor([0.9, 0.8, 0.7, 0.6]),
                      torch.from_numpy(scene["masks"].copy()) if with_masks else None)


def _predictor(scene, refiner, n_refiner_iterations: int, n_candidates: int, **settings) -> Predictor:
    from cosy_lite.nets.object_table import ObjectTable

    points = torch.stack([torch.from_numpy(np.asarray(scene["meshes"][i].sample(200, seed=5))).float() for i in (1, 2)])
    objects = ObjectTable([1, 2], points, torch.eye(4).repeat(2, 1, 1, 1), torch.ones(2, 1, dtype=torch.bool),
                          torch.tensor(scene["diameters"]))
    config = InferenceConfig(start="templates", n_candidates=n_candidates, n_refiner_iterations=n_refiner_iterations,
                             **settings)
    return Predictor(None, refiner, objects, scene["renderer"], config=config, templates=_templates(scene))


def test_predictor_starts_from_the_matched_template(scene):
    """No refiner iteration: predict returns the best template's pose, as the matcher computes it."""
    from cosy_lite.nets.flow_pose_net import FlowPoseNet

    torch.manual_seed(0)
    refiner = PoseModel(FlowPoseNet(pretrained=False, radius=2, descriptor=16).eval(), "refiner", CROP, [1, 2],
                        output="flow")
    p = _predictor(scene, refiner, 0, 1)
    est = p.predict(_image(scene), K, detections=_detections(scene))
    want = _templates(scene).match(scene["masks"], scene["ids"], K).TCO[:, 0]
    assert bool(est.valid.all())
    np.testing.assert_allclose(est.TCO.numpy(), want, atol=1e-7)  # orthonormalised
    np.testing.assert_allclose(est.TCO_coarse.numpy(), want, atol=1e-7)
    with pytest.warns(RuntimeWarning, match="boxes only: the boxes stand in for their masks"):
        boxes_only = p.predict(_image(scene), K, detections=_detections(scene, with_masks=False))
    assert bool(boxes_only.valid.all())  # a start from every box (the box-filled silhouette matched)
    det = _detections(scene)
    det.masks[1] = False  # the detector's mask can be empty: its box stands in
    est = p.predict(_image(scene), K, detections=det)
    assert bool(est.valid.all())
    np.testing.assert_allclose(est.TCO[[0, 2, 3]].numpy(), want[[0, 2, 3]], atol=1e-7)
    assert abs(est.TCO[1, 2, 3].item() / want[1, 2, 3] - 1) < 0.3  # from the box: about the right depth


def test_candidates_are_chosen_alike_by_the_torch_and_the_onnx_backend(scene, tmp_path):
    """3 candidates per detection, one refiner iteration each, the most confident goes on for one
    more: the start pose is one of the candidates, and both backends agree."""
    pytest.importorskip("onnxruntime")
    from cosy_lite.export.onnx_export import export_pose_net
    from cosy_lite.inference.onnx_runtime import OnnxPoseNet
    from cosy_lite.inference.predictor import SetupError
    from cosy_lite.nets.flow_pose_net import FlowPoseNet

    torch.manual_seed(0)
    net = FlowPoseNet(pretrained=False, radius=2, descriptor=16).eval()
    export_pose_net(net, tmp_path / "refiner.onnx", "refiner", CROP, [1, 2], config={"arch": "flow"})
    image, det = _image(scene), _detections(scene)
    candidates = _templates(scene).match(scene["masks"], scene["ids"], K, top_k=3).TCO
    poses = {}
    for backend, model in (("torch", net), ("onnx", OnnxPoseNet(tmp_path / "refiner.onnx", threads=1))):
        p = _predictor(scene, PoseModel(model, "refiner", CROP, [1, 2], output="flow"), 2, 3)
        assert p.backend == backend
        poses[backend] = est = p.predict(image, K, detections=det)
        assert bool(est.valid.all())
        for i in range(len(det)):
            d = np.abs(candidates[i] - est.TCO_coarse[i].numpy()[None]).max(axis=(1, 2))
            assert d.min() < 1e-5  # the chosen start is one of the candidates
    # the chosen one is the most confident: refine_and_score of all 12 candidates, directly
    from cosy_lite.nets.render_and_compare import refine_and_score

    p = _predictor(scene, PoseModel(net, "refiner", CROP, [1, 2], output="flow"), 2, 3)
    flat = torch.from_numpy(candidates.reshape(-1, 4, 4)).float()
    with torch.no_grad():
        _, conf = refine_and_score(net, torch.from_numpy(image).permute(2, 0, 1)[None].float().div(255).expand(12, -1, -1, -1),
                                   torch.from_numpy(K).float().expand(12, 3, 3), flat, np.repeat(scene["ids"], 3).tolist(),
                                   p.objects.points[p.objects.index(np.repeat(scene["ids"], 3).tolist())], scene["renderer"],
                                   CROP)
    best = candidates[np.arange(4), conf.view(4, 3).argmax(dim=1).numpy()]
    assert float(conf.view(4, 3).std(dim=1).min()) > 0  # the candidates are told apart
    np.testing.assert_allclose(poses["torch"].TCO_coarse.numpy(), best, atol=1e-5)
    a, b = poses["torch"], poses["onnx"]
    np.testing.assert_allclose(a.TCO_coarse.numpy(), b.TCO_coarse.numpy(), atol=1e-5)
    # an untrained flow net: onnxruntime's and torch's flows differ by ~1e-3 px, which the PnP of its
    # near-uniform confidences turns into up to 4.4e-3 (measured) after the second iteration
    np.testing.assert_allclose(a.TCO.numpy(), b.TCO.numpy(), atol=1e-2)
    with pytest.raises(SetupError, match="flow refiner"):
        _predictor(scene, PoseModel(net, "refiner", CROP, [1, 2], output="delta"), 2, 3)


def _depth(scene) -> np.ndarray:
    """[H,W] float32 (m): the scene's depth, the objects before a wall 1 m away."""
    d = scene["renderer"].render(scene["ids"], scene["T_true"], K, (H, W), depth_only=True).depth
    d = np.where(d > 0, d, np.inf).min(axis=0)
    return np.where(np.isfinite(d), d, 1.0).astype(np.float32)


def _box_error(R: np.ndarray, G: np.ndarray) -> np.ndarray:
    """Rotation error (deg) of box poses: a box's depth is the same turned 180 deg about an axis."""
    flips = [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]
    return np.min([_rotation_error_deg(R @ f, G) for f in flips], axis=0)


def test_icp_keeps_the_candidate_the_depth_confirms(scene):
    """ICP of 3 template candidates per detection, the true rotation put last, ICP limited to 15 deg
    (here ICP without limits turns even the wrong candidates around): the one kept by depth agreement
    is the true pose, where ICP of the first candidate alone cannot turn it around."""
    from cosy_lite.inference.icp import IcpConfig, refine_poses_icp

    limited = IcpConfig(max_rotation_deg=15.0)
    p = _predictor(scene, None, 0, 1, icp=True, icp_settings=limited)
    depth, det = _depth(scene), _detections(scene)
    candidates = _templates(scene).match(scene["masks"], scene["ids"], K, top_k=3).TCO[:, ::-1].copy()
    boxes = [0, 2, 3]  # the cone (detection 1) turns freely about its axis
    G = scene["T_true"][boxes, :3, :3]
    assert (_box_error(candidates[boxes, 0, :3, :3], G) > 15).all()  # the first candidates are wrong (17-70 deg) ...
    assert (_box_error(candidates[boxes, -1, :3, :3], G) < 1).all()  # ... the last ones right
    TCO, results = p.depth_refinement.refine_hypotheses(torch.from_numpy(candidates), torch.from_numpy(K), depth, det, (H, W))
    assert len(results) == 4 and TCO.shape == (4, 4, 4)
    assert _box_error(TCO[boxes, :3, :3].numpy(), G).max() < 0.5
    first = refine_poses_icp(candidates[:, 0], K, depth, scene["masks"], scene["renderer"], scene["ids"], limited)
    assert (_box_error(np.stack([first[i].TCO[:3, :3] for i in boxes]), G) > 15).all()  # ICP alone: within 15 deg


def test_icp_tries_the_other_candidates_only_where_the_first_one_disagrees(scene, monkeypatch):
    """``accept_agreement``: the first hypothesis of each detection is ICP'd, and the others only for
    the detections whose first result's depth agreement is under it (-1: never, above 1: always)."""
    from cosy_lite.inference import depth_refinement
    from cosy_lite.inference.icp import IcpConfig

    calls: list[int] = []  # poses per ICP call

    def counting(TCO, *args, **kwargs):
        calls.append(len(TCO))
        return refine_poses_icp(TCO, *args, **kwargs)

    refine_poses_icp = depth_refinement.refine_poses_icp
    monkeypatch.setattr(depth_refinement, "refine_poses_icp", counting)
    depth, det = _depth(scene), _detections(scene)
    hyps = torch.from_numpy(_templates(scene).match(scene["masks"], scene["ids"], K, top_k=3).TCO[:, ::-1].copy())
    hyps[0] = hyps[0].flip(0)  # detection 0 (a box): the true rotation first, the others' wrong ones first
    G = scene["T_true"][[0, 2, 3], :3, :3]

    def run(accept):
        calls.clear()
        p = _predictor(scene, None, 0, 1, icp=True, icp_settings=IcpConfig(max_rotation_deg=15.0, accept_agreement=accept))
        TCO, results = p.depth_refinement.refine_hypotheses(hyps, torch.from_numpy(K), depth, det, (H, W))
        return TCO, np.array([r.agreement for r in results]), list(calls)

    first, agreement, n = run(-1.0)  # never: ICP of the first hypotheses alone
    assert n == [4] and _box_error(first[0, :3, :3].numpy()[None], G[:1]).max() < 0.5
    assert (_box_error(first[[2, 3], :3, :3].numpy(), G[1:]) > 15).all()
    assert agreement[0] > agreement[[2, 3]].max() + 0.1, agreement  # the true pose explains the depth
    every, _, n = run(2.0)  # always: 3 x 2 others after the 4 first
    assert n == [4, 8] and _box_error(every[[0, 2, 3], :3, :3].numpy(), G).max() < 0.5
    gated, _, n = run(float(agreement[0]) - 1e-6)  # detection 0 agrees: its others are not tried
    assert n == [4, 6] and _box_error(gated[[0, 2, 3], :3, :3].numpy(), G).max() < 0.5
    np.testing.assert_allclose(gated[0].numpy(), first[0].numpy(), rtol=0, atol=1e-12)  # (Open3D: 1e-20 apart)


@pytest.mark.parametrize("backend", ["torch", "onnx"])
def test_icp_of_every_candidate_leaves_the_rgb_poses_alone(scene, tmp_path, backend):
    """3 candidates, one refiner iteration each (an untrained refiner): with ICP on and a depth image,
    the poses before ICP are those of the RGB-only run (the depth does not leak into them), and the
    pose kept explains the depth at least as well as ICP of the RGB choice alone."""
    from cosy_lite.inference.icp import IcpConfig, depth_agreement
    from cosy_lite.nets.flow_pose_net import FlowPoseNet

    torch.manual_seed(0)
    net = FlowPoseNet(pretrained=False, radius=2, descriptor=16).eval()
    if backend == "onnx":
        pytest.importorskip("onnxruntime")
        from cosy_lite.export.onnx_export import export_pose_net
        from cosy_lite.inference.onnx_runtime import OnnxPoseNet

        export_pose_net(net, tmp_path / "refiner.onnx", "refiner", CROP, [1, 2], config={"arch": "flow"})
        net = OnnxPoseNet(tmp_path / "refiner.onnx", threads=1)
    image, det, depth = _image(scene), _detections(scene), _depth(scene)
    agreement = {}
    for verify in (True, False):
        p = _predictor(scene, PoseModel(net, "refiner", CROP, [1, 2], output="flow"), 1, 3, icp=True,
                       icp_settings=IcpConfig(verify_candidates=verify))
        est = p.predict(image, K, depth=depth, detections=det)
        rgb_only = p.predict(image, K, detections=det)
        np.testing.assert_array_equal(est.TCO_before_icp.numpy(), rgb_only.TCO.numpy())
        agreement[verify] = depth_agreement(est.TCO.numpy(), K, depth, scene["masks"], scene["renderer"], scene["ids"])
    assert (agreement[True] >= agreement[False] - 1e-9).all(), agreement
    assert (agreement[True] > agreement[False] + 0.1).any(), agreement  # and better somewhere: the check acted


def test_start_choice_keeps_the_start_stages_best_and_icp_verifies_the_others(scene):
    """``candidate_choice="start"``: the RGB poses are those of one candidate (the start stage's best),
    no other candidate is refined (with ICP or without), and with ICP the pose kept explains the depth
    at least as well as ICP of that candidate alone."""
    from cosy_lite.inference.icp import IcpConfig, depth_agreement
    from cosy_lite.nets.flow_pose_net import FlowPoseNet

    torch.manual_seed(0)
    refiner = PoseModel(FlowPoseNet(pretrained=False, radius=2, descriptor=16).eval(), "refiner", CROP, [1, 2],
                        output="flow")
    image, det, depth = _image(scene), _detections(scene), _depth(scene)
    one = _predictor(scene, refiner, 2, 1).predict(image, K, detections=det)
    by_start = _predictor(scene, refiner, 2, 3, candidate_choice="start")
    rgb = by_start.predict(image, K, detections=det)
    np.testing.assert_allclose(rgb.TCO.numpy(), one.TCO.numpy(), atol=1e-6)
    np.testing.assert_allclose(rgb.TCO_coarse.numpy(), one.TCO_coarse.numpy(), atol=1e-7)
    n_crops = []
    for choice in ("start", "confidence"):
        p = _predictor(scene, refiner, 2, 3, candidate_choice=choice)
        calls = []
        p.renderer = _CountingRenderer(scene["renderer"], calls)
        p.predict(image, K, detections=det)
        n_crops.append(sum(calls))
    assert n_crops == [2 * 4, 3 * 4 + 4], n_crops  # start: 2 iterations of 4 objects; confidence: 3 candidates + 1
    agreement = {}
    for choice, k in (("start", 3), ("start", 1)):
        p = _predictor(scene, refiner, 2, k, candidate_choice=choice, icp=True, icp_settings=IcpConfig(accept_agreement=2))
        calls = []
        p.renderer = _CountingRenderer(scene["renderer"], calls)
        est = p.predict(image, K, depth=depth, detections=det)
        assert sum(calls) == 2 * 4, calls  # the other candidates go to ICP as the start stage made them
        np.testing.assert_allclose(est.TCO_before_icp.numpy(), one.TCO.numpy(), atol=1e-6)
        agreement[k] = depth_agreement(est.TCO.numpy(), K, depth, scene["masks"], scene["renderer"], scene["ids"])
    assert (agreement[3] >= agreement[1] - 1e-9).all(), agreement


class _CountingRenderer:
    """A renderer that counts the crops it renders (``calls``: one entry per call, its crop count)."""

    def __init__(self, inner, calls: list[int]):
        self.inner, self.calls = inner, calls

    def render_tensors(self, obj_ids, *args, **kwargs):
        self.calls.append(len(obj_ids))
        return self.inner.render_tensors(obj_ids, *args, **kwargs)

    def __getattr__(self, name):
        return getattr(self.inner, name)


def test_templates_cache_is_read_back_and_a_damaged_file_is_rendered_again(scene, tmp_path):
    keys = {1: "mesh-a", 2: "mesh-b"}
    first = SilhouetteTemplates(scene["renderer"], [1, 2], scene["diameters"], n_rotations=64, cache_dir=tmp_path,
                                model_keys=keys)
    want = first.templates(1)
    files = list(tmp_path.glob("templates_obj000001_*.npz"))
    assert len(files) == 1
    again = SilhouetteTemplates(None, [1, 2], scene["diameters"], n_rotations=64, cache_dir=tmp_path, model_keys=keys)
    got = again.templates(1)  # no renderer: read from the file
    assert np.array_equal(got.grids, want.grids) and np.array_equal(got.boxes, want.boxes) and got.depth == want.depth
    other = SilhouetteTemplates(scene["renderer"], [1, 2], scene["diameters"], n_rotations=64, cache_dir=tmp_path,
                                model_keys={1: "another mesh", 2: "mesh-b"})
    other.templates(1)
    assert len(list(tmp_path.glob("templates_obj000001_*.npz"))) == 2  # another mesh: another file
    files[0].write_bytes(b"not a zip file")
    damaged = SilhouetteTemplates(scene["renderer"], [1, 2], scene["diameters"], n_rotations=64, cache_dir=tmp_path,
                                  model_keys=keys)
    with pytest.warns(RuntimeWarning, match="template cache unreadable"):
        assert np.array_equal(damaged.templates(1).grids, want.grids)


def test_fine_refiner_iterations_run_on_larger_crops_keep_their_depth_and_match_onnx(scene, tmp_path):
    """refiner_fine_iterations: those iterations see crops of refiner_fine_resolution (the others the
    network's own size), leave the depth of their input pose as it was, and the onnxruntime refiner
    (exported at the network's size, run at both) gives the torch poses."""
    pytest.importorskip("onnxruntime")
    from cosy_lite.export.onnx_export import export_pose_net
    from cosy_lite.inference.onnx_runtime import OnnxPoseNet
    from cosy_lite.nets.flow_pose_net import FlowPoseNet
    from cosy_lite.nets.render_and_compare import FineCrops, iterate_poses

    fine = (192, 256)
    torch.manual_seed(0)
    net = FlowPoseNet(pretrained=False, radius=2, descriptor=16).eval()
    export_pose_net(net, tmp_path / "refiner.onnx", "refiner", CROP, [1, 2], config={"arch": "flow"})
    onnx_net = OnnxPoseNet(tmp_path / "refiner.onnx", threads=1)
    sizes: list[tuple[int, int]] = []
    run = onnx_net.run
    onnx_net.run = lambda x: (sizes.append(tuple(x.shape[2:])), run(x))[1]  # type: ignore[method-assign]
    image, det = _image(scene), _detections(scene)
    settings = dict(refiner_fine_iterations=[2], refiner_fine_resolution=list(fine))
    a = _predictor(scene, PoseModel(net, "refiner", CROP, [1, 2], output="flow"), 3, 1, **settings).predict(
        image, K, detections=det)
    b = _predictor(scene, PoseModel(onnx_net, "refiner", CROP, [1, 2], output="flow"), 3, 1, **settings).predict(
        image, K, detections=det)
    assert sizes == [CROP, fine, CROP]  # one network call per iteration (4 crops in a batch)
    assert bool(a.valid.all()) and bool(b.valid.all())
    np.testing.assert_allclose(a.TCO.numpy(), b.TCO.numpy(), atol=1e-2)  # (an untrained net, as above)
    # the engine itself: the fine iteration keeps the depth, and is not the iteration at the network's size
    p = _predictor(scene, PoseModel(net, "refiner", CROP, [1, 2], output="flow"), 0, 1)
    start = p.predict(image, K, detections=det).TCO.float()
    args = (torch.from_numpy(image).permute(2, 0, 1)[None].float().div(255).expand(4, -1, -1, -1).contiguous(),
            torch.from_numpy(K).float().expand(4, 3, 3), start, scene["ids"], p.objects.points[p.objects.index(scene["ids"])],
            scene["renderer"], 2, CROP)
    with torch.no_grad():
        plain = iterate_poses(net, *args, output="flow")
        with_fine = iterate_poses(net, *args, output="flow", fine=FineCrops(fine, frozenset({2})))
    torch.testing.assert_close(with_fine[0], plain[0])  # iteration 1 at the network's size, as before
    torch.testing.assert_close(with_fine[1][:, 2, 3], with_fine[0][:, 2, 3])  # the depth kept
    assert float((with_fine[1][:, :3, :3] - plain[1][:, :3, :3]).abs().max()) > 1e-4  # another crop, another update
    assert float((plain[1][:, 2, 3] - plain[0][:, 2, 3]).abs().max()) > 1e-5  # (which would have moved the depth)


def test_keep_depth_moves_the_object_along_its_line_of_sight_only():
    from cosy_lite.nets.render_and_compare import keep_depth

    T_in = torch.eye(4).repeat(3, 1, 1)
    T_in[:, :3, 3] = torch.tensor([[0.1, -0.05, 0.8], [0.0, 0.02, 0.5], [0.0, 0.0, 0.6]])
    T_out = T_in.clone()
    T_out[:, :3, :3] = torch.from_numpy(random_rotations(1, seed=2)[0]).float()
    T_out[:, :3, 3] = torch.tensor([[0.12, -0.04, 0.9], [0.01, 0.03, 0.4], [0.0, 0.0, -0.1]])
    kept = keep_depth(T_in, T_out)
    torch.testing.assert_close(kept[:2, 2, 3], T_in[:2, 2, 3])
    torch.testing.assert_close(kept[:2, :2, 3] / kept[:2, 2:3, 3], T_out[:2, :2, 3] / T_out[:2, 2:3, 3])  # same pixel
    torch.testing.assert_close(kept[:, :3, :3], T_out[:, :3, :3])
    torch.testing.assert_close(kept[2], T_out[2])  # behind the camera: left for the validity check
