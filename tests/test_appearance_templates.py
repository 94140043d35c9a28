"""Appearance start: the print tells an upright box from its flipped twin, which the silhouette cannot."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from scorer_files import scorer_file

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.geometry.symmetries import rotation_errors_deg
from cosy_lite.inference.settings import InferenceConfig
from cosy_lite.nets.appearance_templates import AppearanceTemplates, square_crops, textured_obj_ids
from cosy_lite.nets.silhouette_templates import SilhouetteTemplates
from cosy_lite.render.renderer import GlRenderer

K = np.array([[572.4, 0.0, 320.0], [0.0, 573.6, 240.0], [0.0, 0.0, 1.0]])
CRACKER_BOX = 2  # textured (YCB 003): a box whose silhouette is the same upside down


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


@pytest.fixture(scope="module")
def scene(tiny_synth_root):
    ds = BopDataset(tiny_synth_root)
    renderer = GlRenderer.from_dataset(ds, shading="headlight")
    upright = _rot("y", 90)  # the printed front towards the camera
    flipped = _rot("z", 180) @ upright  # the same silhouette turned about the viewing axis
    yield renderer, upright, flipped, float(ds.models_info[CRACKER_BOX].diameter)
    renderer.close()


def _image(renderer, R):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, (0.0, 0.0, 0.6)
    r = renderer.render([CRACKER_BOX], T[None], K, (480, 640))
    return r.rgb[0], r.mask[0], T


def _matcher(renderer, rotations, diameter, **kw):
    sil = SilhouetteTemplates(renderer, [CRACKER_BOX], [diameter], rotations=np.stack(rotations))
    return sil, AppearanceTemplates(sil, renderer, **kw)


def test_appearance_picks_the_upright_box_and_silhouettes_cannot(scene):
    renderer, upright, flipped, diameter = scene
    sil, app = _matcher(renderer, [upright, flipped], diameter)
    assert sil.appearance is app  # attached: match ranks by appearance when given the image
    for truth in (upright, flipped):
        rgb, mask, T = _image(renderer, truth)
        view = sil.observe(mask, _box(mask), K)
        iou = sil.silhouette_iou(sil.templates(CRACKER_BOX), view.grid)
        assert abs(iou[0] - iou[1]) < 0.05 and iou.min() > 0.85  # the silhouette cannot tell them apart
        scores = app.score(CRACKER_BOX, rgb, view, K, iou)
        picked = np.argmax(scores)
        assert np.allclose(sil.rotations[picked], truth) and scores.max() - scores.min() > 0.1, scores
        matched = sil.match(mask[None], [CRACKER_BOX], K, top_k=2, rgb=rgb)
        err = rotation_errors_deg(matched.TCO[0, :, :3, :3], T[:3, :3], np.eye(3)[None])
        assert err[0] < 3.0 and err[1] > 170.0, err  # the right one first, the twin second
    # without the image the ranking is the silhouettes' (the template order decides a near tie)
    assert sil.match(mask[None], [CRACKER_BOX], K, top_k=2).scores[0, 0] == pytest.approx(iou.max())


def _box(mask):
    from cosy_lite.nets.silhouette_templates import mask_boxes

    return mask_boxes(mask[None])[0]


def test_a_mirrored_crop_would_be_caught(scene):
    """The crops of the image and of the templates must be cut alike: mirrored, the upright print
    no longer matches the upright template better than its twin."""
    renderer, upright, flipped, diameter = scene
    sil, app = _matcher(renderer, [upright, flipped], diameter)
    rgb, mask, _ = _image(renderer, upright)
    view = sil.observe(mask, _box(mask), K)
    iou = sil.silhouette_iou(sil.templates(CRACKER_BOX), view.grid)
    good = app.score(CRACKER_BOX, rgb, view, K, iou)
    bad = app.score(CRACKER_BOX, rgb[:, ::-1].copy(), type(view)(view.R, view.mask[:, ::-1].copy(), _box(view.mask[:, ::-1]),
                                                                   view.grid), K, iou)
    assert good[0] - good[1] > 0.1 and bad[0] - bad[1] < good[0] - good[1] - 0.05


def test_square_crops_cut_the_box_square_on_black():
    img = np.zeros((40, 60, 3), np.uint8)
    img[10:20, 20:40] = (255, 0, 0)
    mask = np.zeros((40, 60), bool)
    mask[10:20, 20:40] = True
    crop = square_crops(img[None], mask[None], np.array([[20.0, 10.0, 40.0, 20.0]]), size=21)[0]
    # a 20 x 10 box in a square of side 2 x (20 / 2 x 1.05 + 1) = 23 px cut to 21 px: an area of
    # 200 x (21 / 23)^2 = 166.7 crop px of red, centred on the crop, nothing green or blue
    red = crop[0].double()
    ys, xs = torch.meshgrid(torch.arange(21.0), torch.arange(21.0), indexing="ij")
    assert float(red.sum()) == pytest.approx(200 * (21 / 23) ** 2, abs=1.5) and float(crop[1:].abs().max()) == 0
    assert float((red * xs).sum() / red.sum()) == pytest.approx(10.0, abs=0.05)
    assert float((red * ys).sum() / red.sum()) == pytest.approx(10.0, abs=0.05)
    assert float(red[:, 10].sum()) == pytest.approx(10 * 21 / 23, abs=0.3)  # half the height: 9.1 px


def test_descriptor_cache_is_reused_and_a_damaged_file_is_described_again(scene, tmp_path):
    renderer, _, _, diameter = scene
    sil = SilhouetteTemplates(renderer, [CRACKER_BOX], [diameter], n_rotations=2, seed=3)
    app = AppearanceTemplates(sil, renderer, cache_dir=tmp_path, model_keys={CRACKER_BOX: "mesh-hash"})
    first = app.descriptors(CRACKER_BOX)
    files = list(tmp_path.glob("appearance_obj000002_*.npz"))
    assert len(files) == 1 and first.shape[0] == 2 and torch.isfinite(first).all()
    again = AppearanceTemplates(SilhouetteTemplates(renderer, [CRACKER_BOX], [diameter], n_rotations=2, seed=3),
                                renderer, cache_dir=tmp_path, model_keys={CRACKER_BOX: "mesh-hash"})
    torch.testing.assert_close(again.descriptors(CRACKER_BOX), first, rtol=0, atol=0)  # float16 both ways
    files[0].write_bytes(b"not an npz")
    third = AppearanceTemplates(SilhouetteTemplates(renderer, [CRACKER_BOX], [diameter], n_rotations=2, seed=3),
                                renderer, cache_dir=tmp_path, model_keys={CRACKER_BOX: "mesh-hash"})
    with pytest.warns(RuntimeWarning, match="appearance cache unreadable"):
        torch.testing.assert_close(third.descriptors(CRACKER_BOX), first, rtol=0, atol=0)


def test_textured_objects_are_the_ones_with_a_print(scene, tiny_synth_root):
    renderer = scene[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert textured_obj_ids(renderer, [1, 2, 5, 8]) == [2, 5, 8]  # cracker box, mustard, gelatin box


def test_score_start_measures_the_start_stage(tiny_synth_root):
    """cosy-lite score-start on the tiny test split: GT masks through the start stage of infer (two
    appearance candidates, the refiner's confidence choosing); the numbers are shares and agree."""
    from cosy_lite.reference.score_start import score_start
    from cosy_lite.weights.reference_models import reference_models

    out = score_start(tiny_synth_root, "appearance", n_candidates=2, refiner=reference_models("ycbvsynth").path("refiner"),
                      min_visib=0.3, n=3, progress=False)
    assert out["instances"] == 3 and out["candidates"] == 2
    assert 0 <= out["within_30deg"] <= out["any_candidate_within_30deg"] <= 1 and out["median_deg"] >= 0
    assert out["textured_instances"] <= 3 and out["seconds_per_instance"] > 0
    assert sum(x["instances"] for x in out["per_object"].values()) == 3


def test_start_errors_summary_counts_flips_on_textured_objects_only():
    # Errors (deg) of 6 instances: object 1 (textured) 10, 170, 40; object 2 (untextured) 175, 5, 20.
    from cosy_lite.reference.score_start import start_errors_summary

    chosen = np.array([10.0, 170.0, 40.0, 175.0, 5.0, 20.0])
    best = np.array([10.0, 12.0, 40.0, 3.0, 5.0, 20.0])
    out = start_errors_summary(chosen, best, np.array([1, 1, 1, 2, 2, 2]), {1})
    assert out["instances"] == 6 and out["textured_instances"] == 3
    assert out["within_30deg"] == pytest.approx(3 / 6) and out["flipped_textured"] == pytest.approx(1 / 3)
    assert out["median_deg"] == pytest.approx(30.0) and out["any_candidate_within_30deg"] == pytest.approx(5 / 6)
    one, two = out["per_object"]["1"], out["per_object"]["2"]
    assert (one["instances"], one["within_30deg"], one["flipped_textured"], one["median_deg"]) == (3, 1 / 3, 1 / 3, 40.0)
    assert two["flipped_textured"] is None and two["within_30deg"] == pytest.approx(2 / 3)
    assert two["any_candidate_within_30deg"] == 1.0


def test_a_trained_scorer_describes_the_detection_and_brings_its_iou_weight(scene, tmp_path):
    from cosy_lite.weights.loaders import load_scorer

    renderer, upright, flipped, diameter = scene
    rgb, mask, _ = _image(renderer, upright)
    frozen_sil, frozen = _matcher(renderer, [upright, flipped], diameter)
    # the ImageNet weights unchanged: the same descriptor as the frozen one, the scorer's IoU weight
    same = load_scorer(scorer_file(tmp_path / "same.pt")).net
    sil, app = _matcher(renderer, [upright, flipped], diameter, scorer=same)
    view = sil.observe(mask, _box(mask), K)
    assert app.iou_weight == 0.25 and not app.scorer.training
    assert torch.allclose(app.describe(rgb, view, K), frozen.describe(rgb, view, K), atol=1e-5)
    iou = np.array([1.0, 0.0])
    assert np.allclose(app.score(CRACKER_BOX, rgb, view, K, iou) - frozen.score(CRACKER_BOX, rgb, view, K, iou),
                       [-0.25, 0.0], atol=1e-4)
    # other weights: another descriptor of the detection; the templates' descriptors stay the frozen ones
    other = load_scorer(scorer_file(tmp_path / "other.pt", scale=0.5)).net
    _, changed = _matcher(renderer, [upright, flipped], diameter, scorer=other)
    assert not torch.allclose(changed.describe(rgb, view, K), frozen.describe(rgb, view, K), atol=1e-3)
    assert torch.equal(changed.descriptors(CRACKER_BOX), frozen.descriptors(CRACKER_BOX))


@pytest.mark.parametrize("problem", ["start", "objects", "shading"])
def test_a_scorer_that_does_not_fit_the_pipeline_is_refused_by_name(tiny_synth_root, tmp_path, problem):
    from cosy_lite.inference.predictor import Predictor, SetupError

    path = scorer_file(tmp_path / "s.pt", obj_ids=(1,) if problem == "objects" else (1, 2, 5, 8),
                        shading="flat" if problem == "shading" else "headlight")
    refiner = tmp_path / "refiner.pt"
    _refiner_file(tiny_synth_root, refiner)
    start = "templates" if problem == "start" else "appearance"
    with pytest.raises(SetupError, match={"start": "start='appearance'", "objects": r"obj_ids \[2, 5, 8\]",
                                          "shading": "'flat' shading"}[problem]) as e:
        Predictor.from_checkpoints(refiner=refiner, dataset=tiny_synth_root, config=InferenceConfig(start=start),
                                   scorer=path)
    assert str(path) in str(e.value)


def _refiner_file(root, path):
    from cosy_lite.config import load_config
    from cosy_lite.train.pose_task import PoseTask, PoseTrainConfig
    from cosy_lite.weights.checkpoint import Checkpoint, save_checkpoint

    cfg = load_config(PoseTrainConfig, None, ["net.arch=flow", "net.backbone=efficientnet_lite0", "net.render_shading=headlight",
                                              "net.crop_resolution=[64,96]",
                                              "data.val_images=1", "dataset=tiny", "data.n_points=300"])
    task = PoseTask(cfg, root)
    save_checkpoint(path, Checkpoint("refiner", task.build_model(load_pretrained=False).state_dict(), {}, 0,
                                     meta=task.checkpoint_meta()))


def test_the_frozen_descriptor_runs_batchnorm_folded_and_describes_alike():
    from cosy_lite.nets.appearance_templates import CROP_SIZE, AppearanceDescriptor
    from cosy_lite.nets.batchnorm_folding import batchnorm_folded

    plain = AppearanceDescriptor()  # ImageNet weights: trained BatchNorm statistics
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # folded outputs equal: no fallback to the plain network
        folded = batchnorm_folded(plain, (2, 3, CROP_SIZE, CROP_SIZE))
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in plain.modules()) > 20  # the plain one is untouched
    crops = torch.rand(4, 3, CROP_SIZE, CROP_SIZE)
    with torch.no_grad():
        a, b = plain(crops), folded(crops)
    assert float((a * b).sum(dim=1).min()) > 1.999  # unit-norm cell descriptors (two maps): the same to 1e-3
    torch.testing.assert_close(b, a, rtol=0, atol=1e-4)
