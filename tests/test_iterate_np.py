"""The onnxruntime path's numpy render-and-compare loop (``inference/iterate_np.py``): the torch
loop's poses, no torch op per iteration in ``Predictor.predict``, and it runs where torch cannot be
imported. A small "pose network" (image moments -> 9 numbers) stands in for
PoseNet: the same function in torch and, exported, in onnxruntime."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn
from torch.overrides import TorchFunctionMode

pytest.importorskip("onnxruntime")

# torchvision before any rendering (see cosy_lite.inference.predictor)
from cosy_lite.inference.predictor import Predictor  # noqa: E402
from cosy_lite.inference import iterate_np  # noqa: E402
from cosy_lite.inference.loaders import PoseModel  # noqa: E402
from cosy_lite.models.render_and_compare import iterate_poses  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CROP = (48, 64)
H, W = 240, 320
K = np.array([[300.0, 0.0, 161.3], [0.0, 310.0, 118.7], [0.0, 0.0, 1.0]])


class _MomentNet(nn.Module):
    """``[B,6,h,w]`` -> ``[B,9]``: tanh of a fixed random map of each channel's mean and first moments
    (so the output follows the crop and the rendering), times 0.1."""

    def __init__(self, seed: int = 0):
        super().__init__()
        self.register_buffer("M", torch.randn(18, 9, generator=torch.Generator().manual_seed(seed)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[2], x.shape[3]
        u = (torch.arange(w, dtype=x.dtype) + 0.5) / w - 0.5
        v = (torch.arange(h, dtype=x.dtype) + 0.5) / h - 0.5
        f = torch.cat([x.mean(dim=(2, 3)), (x * u).mean(dim=(2, 3)), (x * v[:, None]).mean(dim=(2, 3))], dim=1)
        return torch.tanh(f @ self.M.to(x.dtype)) * 0.1


def _meshes() -> dict[int, object]:
    import trimesh

    rng = np.random.default_rng(0)
    box = trimesh.creation.box(extents=(0.08, 0.05, 0.03))
    cyl = trimesh.creation.cylinder(radius=0.025, height=0.09, sections=24)
    for m in (box, cyl):
        m.visual.vertex_colors = rng.integers(40, 256, size=(len(m.vertices), 4)).astype(np.uint8)
    return {1: box, 2: cyl}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Meshes, their renderer, an image of them on noise, poses near the true ones, and the
    exported moment net (``coarse.onnx``)."""
    from cosy_lite.export.onnx_export import export_pose_net
    from cosy_lite.render.renderer import PyrenderRenderer

    d = tmp_path_factory.mktemp("iterate_np")
    meshes = _meshes()
    renderer = PyrenderRenderer(meshes=meshes)
    ids = [1, 2, 1]
    T_true = np.tile(np.eye(4), (3, 1, 1))
    T_true[:, :3, 3] = [[-0.08, 0.02, 0.6], [0.05, -0.03, 0.55], [0.1, 0.06, 0.7]]
    c, s = np.cos(0.5), np.sin(0.5)
    T_true[1, :3, :3] = [[1, 0, 0], [0, c, -s], [0, s, c]]
    T_true[2, :3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    out = renderer.render(ids, T_true, K, (H, W))
    image = np.random.default_rng(1).integers(0, 90, size=(H, W, 3)).astype(np.uint8)
    order = np.argsort(-T_true[:, 2, 3])  # far to near: nearer objects painted last
    for i in order:
        image[out.mask[i]] = out.rgb[i][out.mask[i]]
    T_init = T_true.copy()
    T_init[:, :3, 3] += [[0.01, -0.005, 0.04], [-0.008, 0.004, -0.03], [0.0, 0.01, 0.05]]
    points = np.stack([np.asarray(meshes[i].sample(200, seed=7 + k)) for k, i in enumerate(ids)])
    net = _MomentNet().eval()
    export_pose_net(net, d / "coarse.onnx", "coarse", CROP, [1, 2])
    return dict(dir=d, meshes=meshes, renderer=renderer, ids=ids, image=image, T_init=T_init, points=points,
                net=net)


def test_numpy_loop_gives_the_torch_loops_poses(scene):
    from cosy_lite.export.onnx_models import OnnxPoseNet

    session = OnnxPoseNet(scene["dir"] / "coarse.onnx", threads=1)
    image = iterate_np.image_array(scene["image"])
    K_b = np.tile(K, (3, 1, 1))
    out = iterate_np.iterate_poses(session.run, image, K_b, scene["T_init"], scene["ids"], scene["points"],
                                   scene["renderer"], 3, CROP, batch_size=2)
    with torch.no_grad():
        images = torch.from_numpy(image).permute(2, 0, 1)[None].expand(3, -1, -1, -1).contiguous()
        T_init, points = torch.from_numpy(scene["T_init"]), torch.from_numpy(scene["points"])
        ref = iterate_poses(scene["net"], images, torch.from_numpy(K_b), T_init, scene["ids"], points,
                            scene["renderer"], 3, CROP, batch_size=2)
    assert len(out) == len(ref) == 3
    for a, b in zip(out, ref):
        assert a.dtype == np.float64 and a.shape == (3, 4, 4)
        # measured: 5e-8 m and 2e-7 (onnxruntime's float32 network vs torch's; crops ~1e-5 apart)
        np.testing.assert_allclose(a, b.numpy(), rtol=0, atol=1e-6)
    assert np.abs(out[-1] - scene["T_init"]).max() > 1e-3  # the net did move the poses
    inputs = iterate_np.make_inputs(image, K_b, scene["T_init"], scene["ids"], scene["points"], scene["renderer"], CROP)
    assert inputs.images.shape == (3, 6, *CROP) and inputs.images.dtype == np.float32
    assert 0.0 <= inputs.images.min() and inputs.images.max() <= 1.0 and inputs.images[:, 3:].max() > 0.1


def _predictor(scene, net, n_refiner_iterations: int) -> Predictor:
    from cosy_lite.models.object_table import ObjectTable

    meshes = scene["meshes"]
    points = torch.from_numpy(np.stack([np.asarray(meshes[i].sample(300, seed=i)) for i in (1, 2)])).float()
    diameters = torch.tensor([float(meshes[i].bounding_sphere.primitive.radius) * 2 for i in (1, 2)])
    objects = ObjectTable([1, 2], points, torch.eye(4)[None, None].repeat(2, 1, 1, 1),
                          torch.ones(2, 1, dtype=torch.bool), diameters)
    return Predictor(PoseModel(net, "coarse", CROP, [1, 2]), PoseModel(net, "refiner", CROP, [1, 2]), objects,
                     scene["renderer"], n_refiner_iterations=n_refiner_iterations)


def _detections(scene):
    from cosy_lite.bop.detections import Detections

    boxes = torch.tensor([[95.0, 95.0, 150.0, 140.0], [180.0, 60.0, 215.0, 105.0], [205.0, 140.0, 262.0, 190.0]])
    return Detections(boxes, torch.tensor(scene["ids"]), torch.tensor([0.9, 0.8, 0.7]))


class _CountTorchCalls(TorchFunctionMode):
    """Counts every torch function and Tensor method called inside the ``with`` block."""

    def __init__(self):
        super().__init__()
        self.calls: list[str] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        self.calls.append(getattr(func, "__name__", str(func)))
        return func(*args, **(kwargs or {}))


def test_onnx_predictor_runs_no_torch_op_per_iteration(scene):
    """``predict`` with 1 and with 4 refiner iterations calls torch equally often: torch only wraps
    the detections and the results, once per image. The torch backend, for contrast, calls it in
    every iteration; both give the same poses."""
    from cosy_lite.export.onnx_models import OnnxPoseNet

    session = OnnxPoseNet(scene["dir"] / "coarse.onnx", threads=1)
    det = _detections(scene)
    counts, poses = {}, {}
    for backend, net in (("onnx", session), ("torch", scene["net"])):
        for n in (1, 4):
            p = _predictor(scene, net, n)
            assert p.numpy_loop == (backend == "onnx")
            p.predict(scene["image"], K, detections=det)  # warm-up: meshes uploaded, caches filled
            with _CountTorchCalls() as count:
                est = p.predict(scene["image"], K, detections=det)
            counts[backend, n], poses[backend, n] = len(count.calls), est
    # per image (measured 69): input checks, the detections' selection and order, the final validity
    # flags and the result tensors
    assert counts["onnx", 1] == counts["onnx", 4] < 100
    assert counts["torch", 4] > counts["torch", 1] + 100
    for n in (1, 4):
        a, b = poses["onnx", n], poses["torch", n]
        assert bool(a.valid.all()) and torch.equal(a.obj_ids, b.obj_ids)
        # the torch loop runs in float32, this one in float64: measured 4e-8 m and 1e-7 after 5 iterations
        assert float((a.TCO - b.TCO).abs().max()) <= 1e-6
        assert float((a.TCO_coarse - b.TCO_coarse).abs().max()) <= 1e-6
        assert a.timings["render"] > 0 and a.timings["networks"] > 0 and a.timings["crops"] > 0


def test_numpy_loop_runs_without_torch(scene, tmp_path):
    """In a process where ``import torch`` fails: onnxruntime session + renderer + numpy loop give
    the poses of this process. (The EGL context imports torchvision first as a guard against an
    LLVM clash, see ``render/gl.py``; an empty stand-in module lets that import pass here.)"""
    from cosy_lite.export.onnx_models import OnnxPoseNet

    np.savez(tmp_path / "inputs.npz", image=scene["image"], K=K, T_init=scene["T_init"], points=scene["points"],
             ids=np.array(scene["ids"]), **{f"v{i}": m.vertices for i, m in scene["meshes"].items()},
             **{f"f{i}": m.faces for i, m in scene["meshes"].items()},
             **{f"c{i}": m.visual.vertex_colors for i, m in scene["meshes"].items()})
    code = f"""
import sys, types; sys.modules["torch"] = None; sys.modules["torchvision"] = types.ModuleType("torchvision")
import numpy as np, trimesh
from cosy_lite.export.onnx_models import OnnxPoseNet
from cosy_lite.inference import iterate_np
from cosy_lite.render.renderer import PyrenderRenderer
d = np.load({str(tmp_path / "inputs.npz")!r})
meshes = {{i: trimesh.Trimesh(d[f"v{{i}}"], d[f"f{{i}}"], vertex_colors=d[f"c{{i}}"], process=False) for i in (1, 2)}}
net = OnnxPoseNet({str(scene["dir"] / "coarse.onnx")!r}, threads=1)
K = np.broadcast_to(d["K"], (3, 3, 3))
out = iterate_np.iterate_poses(net.run, iterate_np.image_array(d["image"]), K, d["T_init"], d["ids"].tolist(),
                               d["points"], PyrenderRenderer(meshes=meshes), 2, {CROP})
np.save({str(tmp_path / "out.npy")!r}, out[-1])
"""
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    session = OnnxPoseNet(scene["dir"] / "coarse.onnx", threads=1)
    here = iterate_np.iterate_poses(session.run, iterate_np.image_array(scene["image"]), np.tile(K, (3, 1, 1)),
                                    scene["T_init"], scene["ids"], scene["points"], scene["renderer"], 2, CROP)[-1]
    np.testing.assert_allclose(np.load(tmp_path / "out.npy"), here, rtol=0, atol=1e-12)
    assert np.abs(here - scene["T_init"]).max() > 1e-3
