"""Trained weights as safetensors: fp16 round trip, read by load_checkpoint, refusals name the file and field."""

from __future__ import annotations

import json

import pytest
import torch

from cosy_lite.weights.checkpoint import (
    Checkpoint,
    CheckpointError,
    load_checkpoint,
    load_weights,
    save_checkpoint,
    save_weights,
)


def _ckpt(kind: str = "refiner") -> Checkpoint:
    g = torch.Generator().manual_seed(0)
    model = {"conv.weight": torch.randn(8, 6, 3, 3, generator=g), "bn.running_var": torch.rand(8, generator=g) + 0.5,
             "bn.num_batches_tracked": torch.tensor(1234)}
    return Checkpoint(kind=kind, model=model, config={"net": {"arch": "flow", "crop_resolution": [144, 192]}}, step=736,
                      meta={"obj_ids": [1, 2, 5], "initialised_from": "efficientnet-lite0"}, train_state={"optimizer": {}})


def test_fp16_round_trip_halves_the_size_and_keeps_everything_else(tmp_path):
    ck = _ckpt()
    save_checkpoint(tmp_path / "run.pt", ck)
    save_weights(tmp_path / "refiner.safetensors", ck)
    back = load_checkpoint(tmp_path / "refiner.safetensors", kind="refiner")
    assert (back.kind, back.step, back.config, back.meta, back.train_state) == ("refiner", 736, ck.config, ck.meta, {})
    for k, v in ck.model.items():
        assert back.model[k].dtype == (torch.float32 if v.is_floating_point() else v.dtype)
        tol = 1e-3 * float(v.abs().max()) if v.is_floating_point() else 0
        torch.testing.assert_close(back.model[k], v, rtol=0, atol=tol)
    assert int(back.model["bn.num_batches_tracked"]) == 1234
    data_bytes = sum(v.numel() * 2 for v in ck.model.values() if v.is_floating_point())
    assert (tmp_path / "refiner.safetensors").stat().st_size < data_bytes + 4096
    with pytest.raises(CheckpointError, match="'kind' is 'refiner'"):
        load_checkpoint(tmp_path / "refiner.safetensors", kind="detector")


def test_unusable_weights_files_are_refused_by_name(tmp_path):
    ck = _ckpt()
    f = tmp_path / "w.safetensors"
    ck.model["conv.weight"][0, 0, 0, 0] = 1e6  # beyond fp16
    with pytest.raises(CheckpointError, match="not finite in torch.float16"):
        save_weights(f, ck)
    assert not f.exists() and not list(tmp_path.iterdir())
    with pytest.raises(CheckpointError, match="'meta' does not survive JSON"):
        save_weights(f, Checkpoint(kind="refiner", model={}, config={}, step=0, meta={1: "int key"}))
    save_weights(f, _ckpt())
    f.write_bytes(f.read_bytes()[:300])
    with pytest.raises(CheckpointError, match=r"w\.safetensors: not a readable safetensors file"):
        load_checkpoint(f)
    from safetensors.torch import save_file
    save_file({"x": torch.zeros(2)}, str(f), metadata={"format": "other"})
    with pytest.raises(CheckpointError, match="missing metadata field"):
        load_weights(f)
    meta = {"format": "cosy_lite-weights-1", "kind": "refiner", "step": "-3", "config": "{}", "meta": "{}", "version": "0"}
    save_file({"x": torch.zeros(2)}, str(f), metadata=meta)
    with pytest.raises(CheckpointError, match="'step' is '-3'"):
        load_weights(f)
    save_file({"x": torch.zeros(2)}, str(f), metadata={**meta, "step": "1", "config": json.dumps([1])})
    with pytest.raises(CheckpointError, match="'config' is not a JSON object"):
        load_weights(f)
    with pytest.raises(CheckpointError, match="weights file not found"):
        load_weights(tmp_path / "none.safetensors")


def test_sharded_weights_round_trip_and_a_missing_shard_is_named(tmp_path):
    ck = Checkpoint(kind="refiner", model={f"w{i}": torch.full((256,), float(i)) for i in range(5)},
                    config={"a": 1}, step=3, meta={"obj_ids": [1]})
    files = save_weights(tmp_path / "refiner.safetensors", ck, max_shard_bytes=1200)  # 512 B per fp16 tensor
    assert [f.name for f in files] == [f"refiner-0000{i}-of-00003.safetensors" for i in (1, 2, 3)]
    assert not (tmp_path / "refiner.safetensors").exists()
    back = load_weights(files[1])  # any shard names the whole set
    assert back.step == 3 and sorted(back.model) == sorted(ck.model)
    assert all(torch.equal(back.model[k], ck.model[k]) for k in ck.model)
    assert load_checkpoint(files[0], kind="refiner").step == 3
    files[2].unlink()
    with pytest.raises(CheckpointError, match=r"refiner-00003-of-00003.safetensors.*not found"):
        load_weights(files[0])

