"""The coarse scorer: it learns to rank the templates of the training instances, the loop trains and
resumes it, the file it writes loads for inference, and the loss is the listwise one."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from cosy_lite.config import load_config
from cosy_lite.nets.appearance_scorer import flip_loss, listwise_loss
from cosy_lite.train.loop import train
from cosy_lite.train.scorer_task import ScorerTask, ScorerTrainConfig, augment_crops
from cosy_lite.weights.checkpoint import CheckpointError, load_checkpoint
from cosy_lite.weights.loaders import load_scorer

SMALL = ["data.val_images=1", "data.n_templates=64", "loop.batch_size=8", "loop.num_workers=0", "loop.device=cpu",
         "loop.log_every=2", "loop.checkpoint_every=2", "loop.val_every=0", "optim.warmup_steps=1", "optim.lr=1e-3"]


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("scorer_cache")


def _task(root, cache, extra=()):
    cfg = load_config(ScorerTrainConfig, None, [*SMALL, "dataset=tiny", f"data.cache_dir={cache}", *extra])
    return cfg, ScorerTask(cfg, root, progress=False)


def test_listwise_loss_by_hand():
    scores = torch.tensor([[1.0, 0.0, 0.0]])
    errors = torch.tensor([[40.0, 10.0, 5.0]])  # positives (< 15 deg): templates 1 and 2
    log_p = torch.log_softmax(2.0 * scores, dim=1)[0]
    expected = -(log_p[1] + log_p[2]) / 2
    assert listwise_loss(scores, errors, torch.tensor(2.0)) == pytest.approx(float(expected))
    # no template within 15 deg: the closest one is the positive
    far = torch.tensor([[40.0, 90.0, 30.0]])
    assert listwise_loss(scores, far, torch.tensor(2.0)) == pytest.approx(float(-log_p[2]))


def test_flip_loss_by_hand():
    scores = torch.tensor([[0.5, 0.9, 0.2, 0.7], [0.1, 0.3, 0.2, 0.0]])
    errors = torch.tensor([[5.0, 170.0, 160.0, 90.0], [20.0, 100.0, 140.0, 10.0]])
    # row 0: closest (5 deg) scores 0.5, the best flipped (> 150 deg) 0.9; row 1 has no flipped hypothesis
    expected = torch.nn.functional.softplus(torch.tensor(3.0 * (0.9 - 0.5)))
    assert flip_loss(scores, errors, torch.tensor(3.0), 150.0) == pytest.approx(float(expected))
    assert flip_loss(scores[1:], errors[1:], torch.tensor(3.0), 150.0) == 0.0


def test_observations_are_the_instances_of_the_split_with_their_template_errors(tiny_synth_root, cache):
    _, task = _task(tiny_synth_root, cache)
    obs = task.train_obs
    assert len(obs) > 10 and obs.crops.shape[1:] == (3, 64, 64) and obs.crops.dtype == torch.uint8
    assert obs.iou.shape == obs.errors_deg.shape == (len(obs), 64)
    assert set(obs.obj_ids.tolist()) <= {1, 2, 5, 8}
    # errors are angles in [0, 180]; the best of 64 random rotations is within ~60 deg of any pose
    assert float(obs.errors_deg.min()) >= 0 and float(obs.errors_deg.max()) <= 180.01
    assert float(obs.errors_deg.float().min(dim=1).values.max()) < 75
    # crops show the object: pixels inside, black corners
    assert float(obs.crops.float().mean()) > 5 and int(obs.crops[:, :, 0, 0].max()) == 0
    # a second task reads the cache and gets the same numbers
    _, again = _task(tiny_synth_root, cache)
    assert torch.equal(again.train_obs.errors_deg, obs.errors_deg) and torch.equal(again.val_obs.crops, task.val_obs.crops)


def test_observations_described_again_when_the_split_gains_a_scene(tiny_synth_root, tmp_path, monkeypatch):
    import json
    import shutil

    from cosy_lite.train import start_observations

    described = []
    observe_all = start_observations.observe_all
    monkeypatch.setattr(start_observations, "observe_all",
                        lambda instances, *a, **k: described.append(len(instances)) or observe_all(instances, *a, **k))
    root = tmp_path / "tiny"
    shutil.copytree(tiny_synth_root, root)
    cache_dir = tmp_path / "cache"
    _, before = _task(root, cache_dir)
    n_before = len(before.train_obs) + len(before.val_obs)
    shutil.copytree(root / "train_pbr" / "000000", root / "train_pbr" / "000001")  # a second scene, same images
    _, after = _task(root, cache_dir)
    # the new scene's instances are described too (a stale cache would give the old count), and only they
    assert len(after.train_obs) + len(after.val_obs) == 2 * n_before
    assert described == [n_before, n_before]
    assert len(list(cache_dir.glob("start_observations_scene000000_*.npz"))) == 1
    assert len(list(cache_dir.glob("start_observations_scene000001_*.npz"))) == 1
    # each part assembled from the scenes' files equals the part described on its own, item for item
    assert {s for s, _ in after.train_instances.image_keys()} == {0, 1}
    for obs, part in ((after.train_obs, after.train_instances), (after.val_obs, after.val_instances)):
        direct = observe_all(part, after.templates, after.symmetries, progress=False)
        assert len(direct) == len(part) and torch.equal(direct.items, torch.arange(len(part)))
        for f in start_observations.FIELDS:
            assert torch.equal(getattr(obs, f), getattr(direct, f)), f
    # a regenerated scene (a pose changed) is described again, the other one is not
    path = root / "train_pbr" / "000001" / "scene_gt.json"
    gt = json.loads(path.read_text())
    first = next(iter(gt))
    gt[first][0]["cam_t_m2c"][0] += 5.0
    path.write_text(json.dumps(gt))
    described.clear()
    _task(root, cache_dir)
    assert described == [n_before]
    assert len(list(cache_dir.glob("start_observations_scene000001_*.npz"))) == 2


def test_observations_described_by_two_processes_equal_one(tiny_synth_root, cache, monkeypatch):
    from cosy_lite.data.pose_dataset import PoseDataset
    from cosy_lite.train import start_observations

    monkeypatch.setattr(start_observations, "_CHUNK", 5)  # several chunks per worker, out of order if unsorted
    observe_all = start_observations.observe_all

    _, task = _task(tiny_synth_root, cache)
    instances = PoseDataset(task.dataset, "train_pbr", obj_ids=task.obj_ids, min_visib_fract=0.0)
    one = observe_all(instances, task.templates, task.symmetries, progress=False, workers=1)
    two = observe_all(instances, task.templates, task.symmetries, progress=False, workers=2)
    assert len(one) >= 20
    for f in ("obj_ids", "crops", "iou", "errors_deg", "items"):
        assert torch.equal(getattr(one, f), getattr(two, f)), f


def test_augmented_crops_stay_black_outside_and_in_range():
    x = torch.zeros(16, 3, 64, 64)
    x[:, :, 20:44, 20:44] = 0.5
    torch.manual_seed(0)
    y = augment_crops(x, ScorerTrainConfig().augmentation)
    assert y.shape == x.shape and float(y.min()) >= 0 and float(y.max()) <= 1
    assert float(y[:, :, :4, :4].abs().max()) == 0  # far outside the object: black
    assert not torch.allclose(y, x)


def test_loss_drops_when_fitting_one_batch(tiny_synth_root, cache):
    _, task = _task(tiny_synth_root, cache, ["augmentation.noise_std=0", "augmentation.blur_probability=0",
                                             "augmentation.occluder_probability=0"])
    ds = task.train_dataset()
    batch = task.collate([ds[i] for i in range(8)])
    net = task.build_model().train()
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    losses = []
    for _ in range(15):
        torch.manual_seed(0)
        total = task.compute_losses(net, batch, 0, torch.device("cpu"))["total"]
        opt.zero_grad()
        total.backward()
        opt.step()
        losses.append(total.item())
    assert losses[-1] < 0.7 * losses[0], losses


def test_trained_scorer_resumes_exactly_and_loads_for_inference(tiny_synth_root, cache, tmp_path):
    def run(out, steps, resume=False):
        cfg, task = _task(tiny_synth_root, cache, [f"loop.steps={steps}", "loop.val_every=4"])
        return train(task, cfg.loop, cfg.optim, out, config=dataclasses.asdict(cfg), resume=resume, progress=False)

    run(tmp_path / "a", 4)
    run(tmp_path / "b", 2)
    summary = run(tmp_path / "b", 4, resume=True)
    a, b = (load_checkpoint(tmp_path / x / "checkpoint.pt", kind="scorer") for x in "ab")
    assert a.step == b.step == 4 and a.meta["obj_ids"] == [1, 2, 5, 8] and a.meta["templates"]["shading"] == "headlight"
    for k in a.model:
        assert torch.equal(a.model[k], b.model[k]), k
    assert 0.0 <= summary.last_val["within_30deg"] <= 1.0 and "flipped_textured" in summary.last_val
    scorer = load_scorer(tmp_path / "a" / "checkpoint.pt")
    assert scorer.obj_ids == [1, 2, 5, 8] and not scorer.net.training
    assert torch.equal(scorer.net.iou_weight.detach(), a.model["iou_weight"])
    with pytest.raises(CheckpointError, match="kind"):
        from cosy_lite.weights.loaders import load_pose_model

        load_pose_model(tmp_path / "a" / "checkpoint.pt", "refiner")
