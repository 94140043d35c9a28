"""ONNX export and the onnxruntime backend: pose nets and detector agree with torch, metadata and
manifest round trip, clear errors for broken/mismatched exports, and the pipeline with
``--onnx DIR`` gives the torch backend's poses."""

from __future__ import annotations

import json
import shutil
import warnings
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn
from torchvision.ops import box_iou

ort = pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")

from scorer_files import scorer_file  # noqa: E402

from cosy_lite.export.manifest import Manifest, OnnxModelError  # noqa: E402
from cosy_lite.export.onnx_export import export_detector, export_pose_net  # noqa: E402
from cosy_lite.inference.onnx_runtime import OnnxDetector, OnnxPoseNet  # noqa: E402
from cosy_lite.inference.settings import InferenceConfig  # noqa: E402
from cosy_lite.weights.checkpoint import Checkpoint, save_checkpoint  # noqa: E402

OBJ_IDS = [1, 2, 5, 8]  # the tiny synthetic dataset's objects
CROP = (48, 64)
DETECTOR = dict(name="maskrcnn_mobilenet_v3_large_fpn", fpn_channels=32, mask_head_channels=16, box_head_size=64,
                min_size=120, max_size=160, rpn_pre_nms_top_n_test=100, rpn_post_nms_top_n_test=50,
                box_score_thresh=0.0, box_detections_per_img=8)


def _pose_net(seed: int, head_std: float = 0.01) -> nn.Module:
    """A resnet18 PoseNet with a random head and BatchNorm statistics (a fresh one outputs zeros)."""
    from cosy_lite.weights.pose_nets import PoseNetConfig, build_pose_net

    torch.manual_seed(seed)
    net = build_pose_net(PoseNetConfig(backbone="resnet18", crop_resolution=list(CROP))).eval()
    nn.init.normal_(net.head.weight, std=head_std)
    for m in net.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
    return net


def _save_pose_ckpt(path: Path, kind: str, seed: int, obj_ids=OBJ_IDS, head_std: float = 0.01) -> Path:
    from cosy_lite.weights.pose_nets import PoseNetConfig

    cfg = PoseNetConfig(backbone="resnet18", crop_resolution=list(CROP))
    meta = {"obj_ids": list(obj_ids), "net": asdict(cfg), "dataset": "tiny", "model": kind}
    net = _pose_net(seed, head_std)
    save_checkpoint(path, Checkpoint(kind, net.state_dict(), {"net": asdict(cfg)}, 0, meta=meta))
    return path


def _detector():
    from cosy_lite.nets.detector import Detector, DetectorConfig, LabelMap

    torch.manual_seed(0)
    return Detector(LabelMap(tuple(OBJ_IDS)), DetectorConfig(**DETECTOR)).eval()


@pytest.fixture(scope="module")
def export(tmp_path_factory) -> dict[str, Path]:
    """Tiny checkpoints and their export through ``cosy-lite export`` (with int8 pose nets and a
    coarse scorer whose first convolution differs from the frozen trunk's)."""
    from cosy_lite.cli import main as cli

    d = tmp_path_factory.mktemp("export")
    det = _detector()
    save_checkpoint(d / "detector.pt", Checkpoint("detector", det.state_dict(), {}, 0, meta=det.meta()))
    ckpts = {"coarse": _save_pose_ckpt(d / "coarse.pt", "coarse", 1),
             "refiner": _save_pose_ckpt(d / "refiner.pt", "refiner", 2), "detector": d / "detector.pt",
             "scorer": scorer_file(d / "scorer.pt", scale=0.5)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = cli(["export", "--detector", str(ckpts["detector"]), "--coarse", str(ckpts["coarse"]),
                  "--refiner", str(ckpts["refiner"]), "--scorer", str(ckpts["scorer"]), "--quantize", "int8",
                  "--out", str(d / "models")])
    assert rc == 0
    return {**ckpts, "models": d / "models"}


def _copy_export(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


# ----------------------------------------------------------------------------- parity


def test_pose_nets_match_torch_at_batch_1_and_8(tmp_path):
    for kind, seed in (("coarse", 1), ("refiner", 2)):
        net = _pose_net(seed)
        entry = export_pose_net(net, tmp_path / f"{kind}.onnx", kind, CROP, OBJ_IDS, {"backbone": "resnet18"})
        assert entry.check["max_abs_diff"] <= 1e-4 and entry.input_shape == ["batch", 6, *CROP]
        session = OnnxPoseNet(tmp_path / f"{kind}.onnx", threads=1, kind=kind)
        assert (session.kind, session.obj_ids, session.crop_resolution) == (kind, OBJ_IDS, CROP)
        for batch in (1, 8):
            x = torch.rand(batch, 6, *CROP, generator=torch.Generator().manual_seed(batch))
            with torch.no_grad():
                ref = net(x)
            out = session(x)  # tensor in -> tensor out
            assert isinstance(out, torch.Tensor) and out.shape == (batch, 9)
            assert float(ref.abs().max()) > 0.05  # not the zero output of an untrained head
            assert float((out - ref).abs().max()) <= 1e-4
            np.testing.assert_array_equal(session.run(x.numpy()), out.numpy())


# Dynamic 8-bit quantisation (per-tensor uint8 activations from each call's range, 8-bit weights):
# each quantised Conv/MatMul input carries a rounding error of step/sqrt(12), step = range/255, i.e.
# ~1 % of the RMS of a ReLU activation whose range is ~8x its RMS, and its weights as much again. The
# errors of the ~20 quantised layers of this resnet18 add in quadrature through BatchNorm-scaled layers
# of gain ~1: sqrt(2 x 20) x 1 % ~ 6 % of the output's RMS. The bound is 4x that estimate (measured on
# this project's AVX-512 VNNI/AMX CPU: 3-11 % over 3 networks x 2 inputs x signed/unsigned weights), so
# kernels that round or saturate differently (AVX2's u8s8 pairs, ARM) stay inside it, while a wrong
# graph (another network's output: ~140 %, a dropped layer, zeros: 100 %) is far outside. The maximum
# difference is no statistic to bound: one outlier element of 8 x 9 decides it.
INT8_RELATIVE_RMS_BOUND = 0.25


def test_int8_pose_net_is_close_to_fp32(export):
    from cosy_lite.export.quantize import relative_rms_error

    entry = Manifest.read(export["models"]).models["refiner.int8"]
    assert entry.quantization == "int8" and entry.check["batch"] == 8
    assert entry.check["relative_rms_error"] <= INT8_RELATIVE_RMS_BOUND
    fp32 = OnnxPoseNet(export["models"] / "refiner.onnx", threads=1)
    int8 = OnnxPoseNet(export["models"] / "refiner.int8.onnx", threads=1)
    coarse = OnnxPoseNet(export["models"] / "coarse.onnx", threads=1)  # another network of the same shape
    assert int8.quantization == "int8" and int8.obj_ids == fp32.obj_ids
    for seed in range(3):
        x = np.random.default_rng(seed).random((8, 6, *CROP), dtype=np.float32)
        ref, out = fp32.run(x), int8.run(x)
        assert np.abs(ref).max() > 0.05  # not the zero output of an untrained head
        assert relative_rms_error(out, ref) <= INT8_RELATIVE_RMS_BOUND, seed
        # the statistic separates a wrong network: the bound is no formality
        assert relative_rms_error(coarse.run(x), ref) > 3 * INT8_RELATIVE_RMS_BOUND, seed


def _images() -> list[np.ndarray]:
    """Two uint8 images (coloured rectangles on noise) at the detector's size and at twice it."""
    rng = np.random.default_rng(0)
    out = []
    for h, w in ((120, 160), (240, 320)):
        im = (rng.random((h, w, 3)) * 80).astype(np.uint8)
        im[h // 6: h // 2, w // 8: w // 3] = (230, 20, 20)
        im[h // 2: 5 * h // 6, w // 2: 7 * w // 8] = (20, 200, 40)
        out.append(im)
    return out


def test_separable_mask_paste_equals_torchvision():
    from torchvision.models.detection.roi_heads import paste_masks_in_image

    from cosy_lite.export.onnx_export import paste_masks_separable

    g = torch.Generator().manual_seed(0)
    H, W = 90, 120
    masks = torch.rand(30, 1, 28, 28, generator=g)
    xy = torch.rand(30, 2, generator=g) * torch.tensor([W - 1.0, H - 1.0])
    boxes = torch.cat([xy, torch.minimum(xy + torch.rand(30, 2, generator=g) * 60 + 0.2, torch.tensor([W, H]))], 1)
    boxes[0] = torch.tensor([5.0, 6.0, 5.3, 6.2])  # below one pixel
    ref, out = paste_masks_in_image(masks, boxes, (H, W)), paste_masks_separable(masks, boxes, (H, W))
    assert out.shape == ref.shape == (30, 1, H, W)
    assert float((out - ref).abs().max()) <= 1e-5
    assert torch.equal(out > 0.5, ref > 0.5)


def test_detector_matches_torch(tmp_path):
    from cosy_lite.nets.detector import detect

    model = _detector()
    entry = export_detector(model, tmp_path / "detector.onnx")
    assert entry.obj_ids == OBJ_IDS and entry.input_shape == [3, "height", "width"]
    session = OnnxDetector(tmp_path / "detector.onnx", threads=1)
    assert session.obj_ids == OBJ_IDS and session.config["min_size"] == 120
    for rgb in _images():
        ref = detect(model, [torch.from_numpy(rgb).permute(2, 0, 1).float() / 255.0])[0]
        boxes, obj_ids, scores, masks = session.run(rgb)
        assert len(boxes) == len(ref) == DETECTOR["box_detections_per_img"]
        np.testing.assert_array_equal(obj_ids, ref.obj_ids.numpy())  # obj_ids, not labels
        assert float(box_iou(ref.boxes, torch.from_numpy(boxes)).diag().min()) >= 0.99
        np.testing.assert_allclose(scores, ref.scores.numpy(), atol=1e-4)
        assert masks.shape == (len(ref), *rgb.shape[:2]) and masks.dtype == bool
        assert (masks == ref.masks.numpy()).mean() >= 0.999
        det = session.detect(rgb)
        assert det.time_s > 0 and torch.equal(det.obj_ids, ref.obj_ids)


# ----------------------------------------------------------------------------- manifest and metadata


def test_manifest_and_metadata_round_trip(export):
    from cosy_lite.inference.onnx_runtime import load_onnx_models

    manifest = Manifest.read(export["models"])
    assert set(manifest.models) == {"detector", "coarse", "refiner", "coarse.int8", "refiner.int8", "scorer"}
    for name, e in manifest.models.items():
        model = onnx.load(str(export["models"] / e.file))
        onnx.checker.check_model(model)
        meta = {p.key: p.value for p in model.metadata_props}
        assert meta["cosy_lite.kind"] == e.kind == name.split(".")[0]
        assert json.loads(meta["cosy_lite.obj_ids"]) == e.obj_ids == OBJ_IDS
        assert meta["cosy_lite.quantization"] == e.quantization and meta["cosy_lite.version"]
        assert json.loads(meta["cosy_lite.input"])["shape"] == e.input_shape
        assert e.bytes == (export["models"] / e.file).stat().st_size and len(e.sha256) == 64
        if e.kind == "detector":
            assert json.loads(meta["cosy_lite.config"])["name"] == DETECTOR["name"]
        elif e.kind == "scorer":
            assert json.loads(meta["cosy_lite.crop_resolution"]) == e.crop_resolution == [64, 64]
            assert json.loads(meta["cosy_lite.config"]) == {"trunk": "efficientnet_lite0", "iou_weight": 0.25,
                                                            "template_shading": "headlight"}
            assert e.input_shape == ["batch", 3, 64, 64] and str(export["scorer"]) in meta["cosy_lite.source"]
        else:
            assert json.loads(meta["cosy_lite.crop_resolution"]) == e.crop_resolution == list(CROP)
            assert json.loads(meta["cosy_lite.config"])["backbone"] == "resnet18"
            assert str(export[e.kind]) in meta["cosy_lite.source"]
    assert manifest.models["coarse"].check["max_abs_diff"] <= 1e-4
    assert manifest.models["scorer"].check["max_abs_diff"] <= 1e-5
    loaded = load_onnx_models(export["models"], threads=1)
    assert loaded.coarse.crop_resolution == CROP and loaded.refiner.kind == "refiner"
    assert (loaded.scorer.obj_ids, loaded.scorer.crop_size, loaded.scorer.iou_weight) == (OBJ_IDS, 64, 0.25)
    assert loaded.detector.label_map.obj_ids == tuple(OBJ_IDS)
    assert load_onnx_models(export["models"], threads=1, precision="int8").coarse.net.quantization == "int8"
    assert load_onnx_models(export["models"], detector=False).detector is None


def test_broken_files_give_errors_naming_file_and_field(export, tmp_path):
    from cosy_lite.inference.onnx_runtime import load_onnx_models

    def error(root: Path, **kwargs) -> OnnxModelError:
        with pytest.raises(OnnxModelError) as e:
            load_onnx_models(root, threads=1, **kwargs)
        return e.value

    # Truncated: the manifest's size check names the file.
    root = _copy_export(export["models"], tmp_path / "truncated")
    data = (root / "refiner.onnx").read_bytes()
    (root / "refiner.onnx").write_bytes(data[: len(data) // 3])
    e = error(root)
    assert e.path.endswith("refiner.onnx") and e.field == "bytes" and "truncated" in str(e)
    # A truncated / garbage file opened on its own: onnxruntime cannot load it.
    (tmp_path / "half.onnx").write_bytes(data[: len(data) // 3])
    (tmp_path / "text.onnx").write_text("not a model")
    for name in ("half.onnx", "text.onnx"):
        with pytest.raises(OnnxModelError, match=rf"{name}: not a loadable ONNX model"):
            OnnxPoseNet(tmp_path / name)
    # Missing file listed in the manifest.
    root = _copy_export(export["models"], tmp_path / "missing")
    (root / "coarse.onnx").unlink()
    e = error(root)
    assert e.path.endswith("coarse.onnx") and "not found" in str(e) and "models.coarse.file" in str(e)
    # Same size, other content (e.g. weights of another export): sha256.
    root = _copy_export(export["models"], tmp_path / "replaced")
    data = bytearray((root / "coarse.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (root / "coarse.onnx").write_bytes(bytes(data))
    e = error(root)
    assert e.path.endswith("coarse.onnx") and e.field == "sha256" and "replaced" in str(e)
    # No manifest / unreadable manifest / int8 not exported.
    e = error(tmp_path / "nowhere")
    assert "nowhere" in e.path and "not found" in str(e)
    root = _copy_export(export["models"], tmp_path / "badjson")
    (root / "manifest.json").write_text("{")
    assert error(root).path.endswith("manifest.json")
    root = _copy_export(export["models"], tmp_path / "fp32only")
    m = json.loads((root / "manifest.json").read_text())
    del m["models"]["coarse.int8"]
    (root / "manifest.json").write_text(json.dumps(m))
    e = error(root, precision="int8")
    assert e.field == "models.coarse.int8" and "--quantize int8" in str(e)


def test_mismatched_manifest_gives_errors_naming_file_and_field(export, tmp_path):
    from cosy_lite.inference.onnx_runtime import load_onnx_models

    def edited(name: str, edit) -> Path:
        root = _copy_export(export["models"], tmp_path / name)
        m = json.loads((root / "manifest.json").read_text())
        edit(m["models"])
        (root / "manifest.json").write_text(json.dumps(m))
        return root

    root = edited("ids", lambda m: m["refiner"].update(obj_ids=[1, 2]))
    with pytest.raises(OnnxModelError) as e:
        load_onnx_models(root, threads=1)
    assert e.value.path.endswith("refiner.onnx") and e.value.field == "metadata_props[cosy_lite.obj_ids]"
    assert "[1, 2, 5, 8]" in str(e.value) and "models.refiner.obj_ids says [1, 2]" in str(e.value)
    root = edited("crop", lambda m: m["coarse"].update(crop_resolution=[96, 128], input_shape=["batch", 6, 96, 128]))
    with pytest.raises(OnnxModelError) as e:
        load_onnx_models(root, threads=1)
    assert e.value.field == "metadata_props[cosy_lite.crop_resolution]" and "[96, 128]" in str(e.value)
    root = edited("channels", lambda m: m["coarse"].update(input_shape=["batch", 3, 48, 64]))
    with pytest.raises(OnnxModelError) as e:
        load_onnx_models(root, threads=1)
    assert e.value.path.endswith("manifest.json") and e.value.field == "models.coarse.input_shape"
    root = edited("kind", lambda m: m["coarse"].update(kind="detector"))
    with pytest.raises(OnnxModelError, match=r"manifest.json \[models.coarse.kind\]"):
        load_onnx_models(root, threads=1)
    root = edited("scorer_ids", lambda m: m["scorer"].update(obj_ids=[1, 2]))
    with pytest.raises(OnnxModelError) as e:
        load_onnx_models(root, threads=1)
    assert e.value.path.endswith("scorer.onnx") and e.value.field == "metadata_props[cosy_lite.obj_ids]"
    root = edited("scorer_shape", lambda m: m["scorer"].update(input_shape=["batch", 6, 64, 64]))
    with pytest.raises(OnnxModelError, match=r"manifest.json \[models.scorer.input_shape\]"):
        load_onnx_models(root, threads=1)
    # the scorer file's own metadata: no iou_weight, a NaN one, a crop size that is not a square
    from cosy_lite.export.manifest import write_metadata
    from cosy_lite.inference.onnx_runtime import OnnxScorer

    model = onnx.load(str(export["models"] / "scorer.onnx"))
    meta = {p.key: p.value for p in model.metadata_props}
    for key, value, field in [("cosy_lite.config", '{"template_shading": "headlight"}', "config"),
                              ("cosy_lite.config", '{"template_shading": "headlight", "iou_weight": NaN}', "config"),
                              ("cosy_lite.crop_resolution", "[64, 48]", "crop_resolution")]:
        path = tmp_path / f"scorer_{field}_{len(value)}.onnx"
        shutil.copy(export["models"] / "scorer.onnx", path)
        write_metadata(path, {**meta, key: value})
        with pytest.raises(OnnxModelError) as e:
            OnnxScorer(path, threads=1)
        assert e.value.path == str(path) and e.value.field == f"metadata_props[cosy_lite.{field}]"


def test_a_graph_with_three_input_channels_is_refused(tmp_path):
    from cosy_lite.export.manifest import ModelEntry, metadata_of, write_metadata
    from cosy_lite.nets.pose_net import PoseNet

    net = PoseNet("resnet18", in_channels=3).eval()
    path = tmp_path / "rgb_only.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(net, (torch.rand(1, 3, *CROP),), str(path), dynamo=False, input_names=["images"],
                          output_names=["delta"], dynamic_axes={"images": {0: "batch"}})
    entry = ModelEntry("rgb_only.onnx", "coarse", OBJ_IDS, "images", ["batch", 6, *CROP], list(CROP))
    write_metadata(path, metadata_of(entry, {}))  # metadata claims 6 channels, the graph takes 3
    with pytest.raises(OnnxModelError, match=r"rgb_only.onnx \[input images shape\]: \['batch', 3, 48, 64\], "
                                             r"expected \[batch, 6, 48, 64\]"):
        OnnxPoseNet(path)
    with pytest.raises(OnnxModelError, match=r"metadata_props\[cosy_lite.kind\]\]: 'coarse', expected 'refiner'"):
        OnnxPoseNet(path, kind="refiner")


# ----------------------------------------------------------------------------- the pipeline


def test_the_objects_are_those_with_a_mesh(tiny_synth_root, tmp_path):
    """An export of objects 1 and 30 on a dataset with 1 (not 30) estimates 1; with none of its objects
    it is refused, naming the manifest, the field and the models file."""
    from cosy_lite.export.onnx_export import export_models
    from cosy_lite.inference.predictor import Predictor

    export_models(tmp_path / "some", coarse=_save_pose_ckpt(tmp_path / "c1.pt", "coarse", 1, obj_ids=[1, 30]))
    assert Predictor.from_onnx(tmp_path / "some", dataset=tiny_synth_root).obj_ids == [1]
    export_models(tmp_path / "none", coarse=_save_pose_ckpt(tmp_path / "c2.pt", "coarse", 1, obj_ids=[30, 31]))
    with pytest.raises(OnnxModelError) as e:
        Predictor.from_onnx(tmp_path / "none", dataset=tiny_synth_root)
    assert e.value.path.endswith("manifest.json") and e.value.field == "models.coarse.obj_ids"
    assert "[30, 31]" in str(e.value) and "models_info.json" in str(e.value)


def test_onnx_backend_gives_the_torch_poses(tiny_synth_root, export, tmp_path, capsys):
    """infer.py with the checkpoints and with their export, oracle detections, coarse + 1 refiner
    iteration: the same rows, translations within 0.3 mm, rotation matrices within 3e-4 per entry."""
    import infer
    from cosy_lite.bop.results import read_results_csv
    from cosy_lite.nets.initial_pose import CANONICAL_ROTATIONS

    common = ["--dataset", str(tiny_synth_root), "--detections", "oracle", "--n-refiner-iters", "1",
              "--no-progress", "--threads", "1"]
    assert infer.main([*common, "--coarse", str(export["coarse"]), "--refiner", str(export["refiner"]),
                       "--out", str(tmp_path / "torch")]) == 0
    assert infer.main([*common, "--onnx", str(export["models"]),
                       "--out", str(tmp_path / "onnx")]) == 0
    ref = read_results_csv(next((tmp_path / "torch").glob("*.csv")))
    out = read_results_csv(next((tmp_path / "onnx").glob("*.csv")))
    assert len(ref) == len(out) > 0
    moved = 0.0
    for a, b in zip(ref, out):
        assert (a.scene_id, a.im_id, a.obj_id, a.score) == (b.scene_id, b.im_id, b.obj_id, b.score)
        # Measured: <= 0.09 mm and 3e-5 (torch's BatchNorm-folded nets vs onnxruntime, ~1e-6 apart,
        # amplified by the second iteration's crop and rendering edges); BOP's finest threshold is mm.
        assert np.abs(a.TCO[:3, 3] - b.TCO[:3, 3]).max() <= 3e-4  # m
        assert np.abs(a.TCO[:3, :3] - b.TCO[:3, :3]).max() <= 3e-4
        moved = max(moved, float(np.abs(a.TCO[:3, :3] - CANONICAL_ROTATIONS["z_up"].numpy()).max()))
    assert moved > 1e-3  # the random heads did move the poses: the comparison is not of identities
    capsys.readouterr()
    # Errors: a torch-only argument with the onnx backend; a folder that is not an export.
    assert infer.main([*common, "--onnx", str(export["models"]), "--coarse", "x.pt"]) == 2
    assert "--coarse not used with --onnx" in capsys.readouterr().err
    assert infer.main(["--dataset", str(tiny_synth_root), "--onnx", str(tmp_path / "none"),
                       "--detections", "oracle", "--out", str(tmp_path / "x")]) == 2
    assert "none" in capsys.readouterr().err


def test_exported_scorer_describes_the_detections_as_the_torch_scorer(tiny_synth_root, export, tmp_path):
    """The scorer's graph gives the torch scorer's descriptors (batch 1 and 5); ``from_onnx`` with
    ``start="appearance"`` describes a detection with it (the torch pipeline's descriptor with the
    same checkpoint, not the frozen trunk's), brings its iou_weight, and refuses by name a scorer
    trained against other shading than the refiner renders."""
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.detections import oracle_detections
    from cosy_lite.export.onnx_export import export_models
    from cosy_lite.inference.onnx_runtime import OnnxScorer
    from cosy_lite.inference.predictor import Predictor, SetupError
    from cosy_lite.weights.loaders import load_scorer

    torch_net = load_scorer(export["scorer"]).net
    config = InferenceConfig(start="appearance")
    ds = BopDataset(tiny_synth_root)
    onnx_pipeline = Predictor.from_onnx(export["models"], dataset=ds, threads=1, config=config)
    scorer = onnx_pipeline.templates.appearance.scorer
    assert isinstance(scorer, OnnxScorer) and onnx_pipeline.templates.appearance.iou_weight == 0.25
    for batch in (1, 5):
        crops = torch.rand(batch, 3, 64, 64, generator=torch.Generator().manual_seed(batch))
        with torch.no_grad():
            ref = torch_net(crops)
        assert scorer(crops).shape == ref.shape and float((scorer(crops) - ref).abs().max()) <= 1e-5
    with pytest.raises(ValueError, match=r"scorer.onnx: crops must be \[B,3,64,64\]"):
        scorer(torch.rand(1, 3, 32, 32))
    # one detection of a generated image, described by each pipeline's appearance start
    torch_pipeline = Predictor.from_checkpoints(refiner=export["refiner"], dataset=ds, config=config,
                                                scorer=export["scorer"])
    frozen = Predictor.from_checkpoints(refiner=export["refiner"], dataset=ds, config=config)
    rec = next(ds.images("test"))
    rgb, det, K = ds.load_rgb(rec), oracle_detections(ds, rec), np.asarray(rec.camera.K)
    view = onnx_pipeline.templates.observe(det.masks[0].numpy(), det.boxes[0].numpy(), K)
    onnx_d, torch_d, frozen_d = (p.templates.appearance.describe(rgb, view, K)
                                 for p in (onnx_pipeline, torch_pipeline, frozen))
    assert float((onnx_d - torch_d).abs().max()) <= 1e-5
    assert float((onnx_d - frozen_d).abs().max()) >= 1e-3  # the checkpoint's own weights, not the frozen trunk
    # a scorer trained against flat-shaded templates, the refiner rendering with headlight shading
    export_models(tmp_path / "flat", refiner=export["refiner"], scorer=scorer_file(tmp_path / "flat.pt", shading="flat"))
    with pytest.raises(SetupError, match=r"scorer.onnx: the scorer was trained against templates rendered with 'flat'"):
        Predictor.from_onnx(tmp_path / "flat", dataset=ds, threads=1, config=config)
    # other starts do not use it
    assert Predictor.from_onnx(tmp_path / "flat", dataset=ds, threads=1,
                               config=InferenceConfig(start="templates")).templates.appearance is None
    # an export without a scorer (made before there was one): the frozen trunk, and a warning naming the manifest
    export_models(tmp_path / "none", refiner=export["refiner"])
    with pytest.warns(UserWarning, match=r"none/manifest.json: no scorer.onnx, so the frozen ImageNet trunk"):
        old = Predictor.from_onnx(tmp_path / "none", dataset=ds, threads=1, config=config)
    assert old.templates.appearance.scorer is None
    assert float((old.templates.appearance.describe(rgb, view, K) - frozen_d).abs().max()) <= 1e-5


def test_fine_refiner_iterations_need_a_refiner_graph_of_any_crop_size(tiny_synth_root, export):
    """A regression refiner takes its own crop size only: refiner_fine_iterations on it is an error
    (naming the file for the ONNX graph) when the pipeline is built, not in the middle of a split."""
    from cosy_lite.inference.predictor import Predictor, SetupError

    config = InferenceConfig(refiner_fine_iterations=[2], refiner_fine_resolution=[96, 128])
    with pytest.raises(SetupError, match=r"refiner\.onnx: refiner_fine_iterations \[2\] run it on \[96, 128\] crops"):
        Predictor.from_onnx(export["models"], dataset=tiny_synth_root, threads=1, config=config)
    with pytest.raises(SetupError, match=r"refiner_fine_iterations \[2\] run it on"):  # the torch backend alike
        Predictor.from_checkpoints(coarse=export["coarse"], refiner=export["refiner"], dataset=tiny_synth_root, config=config)


def test_onnx_detector_feeds_the_predictor(tiny_synth_root, export):
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.inference.predictor import Predictor

    ds = BopDataset(tiny_synth_root)
    rec = next(ds.images("test"))
    rgb = ds.load_rgb(rec)
    ref = Predictor.from_checkpoints(detector=export["detector"], coarse=export["coarse"], dataset=ds)
    p = Predictor.from_onnx(export["models"], dataset=ds, threads=1, config=InferenceConfig(n_refiner_iterations=0))
    assert p.backend == "onnx" and ref.backend == "torch" and p.obj_ids == OBJ_IDS
    det_ref, det = ref.detect(rgb), p.detect(rgb)
    assert torch.equal(det.obj_ids, det_ref.obj_ids) and len(det) > 0
    assert float(box_iou(det_ref.boxes, det.boxes).diag().min()) >= 0.99
    est_ref, est = ref.predict(rgb, rec.camera.K), p.predict(rgb, rec.camera.K)
    assert torch.equal(est.obj_ids, est_ref.obj_ids) and est.timings["detection"] > 0
    assert float((est.TCO - est_ref.TCO).abs().max()) <= 1e-4
    # the setting mask_threshold reaches both detectors' masks: the session's own at that threshold
    low = InferenceConfig(n_refiner_iterations=0, mask_threshold=0.2)
    p_low = Predictor.from_onnx(export["models"], dataset=ds, threads=1, config=low)
    ref_low = Predictor.from_checkpoints(detector=export["detector"], coarse=export["coarse"], dataset=ds, config=low)
    _, _, scores, masks_low = p_low.detector.run(rgb, 0.2)
    masks_low = masks_low[np.argsort(-scores, kind="stable")]  # the predictor's order: by decreasing score
    assert np.array_equal(p_low.detect(rgb).masks.numpy(), masks_low)
    torch_low = ref_low.detect(rgb).masks.numpy()
    assert (torch_low == masks_low).mean() >= 0.999
    assert masks_low.sum() > det.masks.numpy().sum()  # more pixels above 0.2 than above 0.5 ...
    assert torch_low.sum() > det_ref.masks.numpy().sum()  # ... in the torch detector's masks as well


def test_infer_runs_a_split_with_the_exported_detector(tiny_synth_root, export, tmp_path):
    """``infer --onnx DIR`` without --detections: the export's detector finds the objects, and its
    obj_ids are checked against the split's targets as the torch detector's are."""
    import infer
    from cosy_lite.bop.results import read_results_csv

    rc = infer.main(["--dataset", str(tiny_synth_root), "--onnx", str(export["models"]), "--n-refiner-iters", "0",
                     "--limit-images", "1", "--no-progress", "--threads", "1", "--out", str(tmp_path / "o")])
    assert rc == 0
    rows = read_results_csv(next((tmp_path / "o").glob("*.csv")))
    assert {r.obj_id for r in rows} <= set(OBJ_IDS)


@pytest.mark.parametrize("stride", [8, 4])
def test_flow_refiner_exports_and_gives_the_torch_poses(tiny_synth_root, tmp_path, stride):
    """A flow refiner (net.arch=flow, net.flow_stride 8 or 4) through infer.py: checkpoints vs their ONNX
    export (the numpy solver on the onnxruntime path), oracle boxes, coarse + 1 refiner iteration: the
    same poses (a random flow network's field is rough, so the solver amplifies the ~1e-6 network
    differences)."""
    import infer
    from cosy_lite.bop.results import read_results_csv
    from cosy_lite.weights.pose_nets import PoseNetConfig, build_pose_net

    cfg = PoseNetConfig(arch="flow", backbone="efficientnet_lite0", crop_resolution=[48, 64], corr_radius=2, width=16,
                        flow_stride=stride)
    torch.manual_seed(3)
    net = build_pose_net(cfg, "refiner", load_weights=False).eval()
    for m in net.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 2.0)
    meta = {"obj_ids": OBJ_IDS, "net": asdict(cfg), "dataset": "tiny", "model": "refiner"}
    refiner = tmp_path / "refiner.pt"
    save_checkpoint(refiner, Checkpoint("refiner", net.state_dict(), {"net": asdict(cfg)}, 0, meta=meta))
    coarse = _save_pose_ckpt(tmp_path / "coarse.pt", "coarse", 1)
    from cosy_lite.export.onnx_export import export_models

    export_models(tmp_path / "models", coarse=coarse, refiner=refiner)
    entry = Manifest.read(tmp_path / "models").models["refiner"]
    assert entry.check["max_abs_diff"] < 1e-2 * max(1.0, entry.check["max_abs_output"])
    assert OnnxPoseNet(tmp_path / "models" / entry.file, 1, "refiner").output == "flow"
    common = ["--dataset", str(tiny_synth_root), "--detections", "oracle", "--no-progress", "--threads", "1"]
    assert infer.main([*common, "--coarse", str(coarse), "--refiner", str(refiner), "--n-refiner-iters", "1",
                       "--out", str(tmp_path / "t")]) == 0
    assert infer.main([*common, "--onnx", str(tmp_path / "models"), "--n-refiner-iters", "1",
                       "--out", str(tmp_path / "o")]) == 0
    assert infer.main([*common, "--coarse", str(coarse), "--refiner", str(refiner), "--n-refiner-iters", "0",
                       "--out", str(tmp_path / "c")]) == 0  # coarse only
    ref, out, co = (read_results_csv(next((tmp_path / x).glob("*.csv"))) for x in "toc")
    assert len(ref) == len(out) == len(co) > 0
    moved = 0.0
    for a, b, c in zip(ref, out, co):
        assert (a.scene_id, a.im_id, a.obj_id) == (b.scene_id, b.im_id, b.obj_id)
        assert np.abs(a.TCO[:3, 3] - b.TCO[:3, 3]).max() <= 1e-3  # m
        assert np.abs(a.TCO[:3, :3] - b.TCO[:3, :3]).max() <= 3e-3
        moved = max(moved, float(np.abs(a.TCO[:3, 3] - c.TCO[:3, 3]).max()))
    assert moved > 1e-4  # the refiner's flow did move the poses: not a comparison of identities
