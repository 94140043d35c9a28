"""Hostile and broken checkpoints: a pickle payload never runs (load_checkpoint, infer.py --coarse,
train.py --resume, cosy-lite export), every broken file gives one message naming it and exit 2,
and what save_checkpoint writes loads weights-only (dataclasses and paths stored as plain data).
Reference-model sets whose files disagree with their cards (missing, extra, resized or altered
weights files, mistyped card fields) and weights files with mistyped metadata are one message
naming the file and the field."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from bop_fixtures import write_tiny_bop

from cosy_lite.weights.checkpoint import CHECKPOINT_FORMAT, Checkpoint, CheckpointError, load_checkpoint, save_checkpoint

ROOT = Path(__file__).resolve().parents[1]


class Payload:
    """Unpickling this runs ``open(marker, "w")``: it creates the marker file."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _evil(path: Path, marker: Path, kind: str = "coarse", legacy: bool = False) -> Path:
    """A checkpoint-looking file whose unpickling creates ``marker`` (plain torch.save, as an attacker would)."""
    payload = {"format": CHECKPOINT_FORMAT, "kind": kind, "model": {"w": torch.ones(2)}, "config": {},
               "step": 0, "meta": {"obj_ids": [1], "hook": Payload(marker)}}
    torch.save(payload, path, _use_new_zipfile_serialization=not legacy)
    return path


def _assert_refused(text: str, path: Path, marker: Path) -> None:
    assert str(path) in text and "refused" in text and "could run code" in text, text
    assert "Traceback" not in text
    assert not marker.exists(), "the payload ran"


@pytest.mark.parametrize("legacy", [False, True], ids=["zip-format", "legacy-format"])
def test_payload_does_not_run_in_load_checkpoint(tmp_path, legacy):
    marker = tmp_path / "PWNED"
    path = _evil(tmp_path / "evil.pt", marker, legacy=legacy)
    with pytest.raises(CheckpointError) as e:
        load_checkpoint(path)
    _assert_refused(str(e.value), path, marker)
    assert "Python object io.open" in str(e.value) or "builtins.open" in str(e.value)  # what was refused


def test_payload_does_not_run_in_infer(tmp_path, capsys):
    import infer

    marker = tmp_path / "PWNED"
    root = write_tiny_bop(tmp_path)
    evil = _evil(tmp_path / "coarse.pt", marker)
    rc = infer.main(["--dataset", str(root), "--coarse", str(evil), "--detections", "oracle",
                     "--out", str(tmp_path / "out"), "--no-progress"])
    assert rc == 2
    _assert_refused(capsys.readouterr().err, evil, marker)


def test_payload_does_not_run_in_export(tmp_path, capsys):
    from cosy_lite.cli import main

    marker = tmp_path / "PWNED"
    evil = _evil(tmp_path / "refiner.pt", marker, kind="refiner")
    assert main(["export", "--refiner", str(evil), "--out", str(tmp_path / "models")]) == 2
    _assert_refused(capsys.readouterr().err, evil, marker)
    assert not (tmp_path / "models" / "refiner.onnx").exists()


def test_payload_does_not_run_on_resume(tmp_path):
    """The training loop's --resume path (train.py --resume ends here, see test_train_py_resume_...)."""
    from toy_task import ToyTask

    from cosy_lite.train.loop import LoopConfig, train
    from cosy_lite.train.schedule import OptimConfig

    marker = tmp_path / "PWNED"
    evil = _evil(tmp_path / "checkpoint.pt", marker, kind="toy")
    loop = LoopConfig(steps=5, batch_size=4, num_workers=0, device="cpu")
    with pytest.raises(CheckpointError) as e:
        train(ToyTask(), loop, OptimConfig(), tmp_path, config={}, resume=True, progress=False)
    _assert_refused(str(e.value), evil, marker)


def test_train_py_resume_with_a_payload_is_one_message(tiny_synth_root, tmp_path):
    """A real ``python train.py --resume`` process: exit 2, one line naming the file, no traceback."""
    marker = tmp_path / "PWNED"
    out = tmp_path / "run"
    out.mkdir()
    evil = _evil(out / "checkpoint.pt", marker, kind="refiner")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, str(ROOT / "train.py"), "--dataset", str(tiny_synth_root), "--model", "refiner",
                        "--out", str(out), "--resume", "loop.steps=1", "loop.num_workers=0", "loop.device=cpu",
                        "data.val_images=1", "data.n_points=300", "net.arch=early", "net.backbone=resnet18",
                        "net.crop_resolution=[60,80]"],
                       capture_output=True, text=True, env=env, timeout=300, cwd=ROOT)
    assert r.returncode == 2, r.stdout[-2000:] + r.stderr[-3000:]
    lines = [s for s in r.stderr.splitlines() if "error" in s]
    assert len(lines) == 1 and lines[0].startswith("train.py: error:"), r.stderr
    _assert_refused(r.stderr, evil, marker)


# ----------------------------------------------------------------------------- broken files


def _good(path: Path, **changes) -> Path:
    payload = {"format": CHECKPOINT_FORMAT, "kind": "coarse", "model": {"w": torch.ones(2)}, "config": {}, "step": 3,
               "train_state": {}, "meta": {}, "version": "0.1.0", **changes}
    torch.save(payload, path)
    return path


@pytest.mark.parametrize("make, words", [
    (lambda p: p.write_bytes(b""), "not a readable checkpoint"),
    (lambda p: p.write_bytes(b"definitely not a checkpoint"), "not a readable checkpoint"),
    (lambda p: p.write_bytes(_good(p).read_bytes()[:300]), "not a readable checkpoint"),
    (lambda p: torch.save([1, 2, 3], p), "expected a dict, found list"),
    (lambda p: torch.save({"model": {}}, p), "missing field(s)"),
    (lambda p: _good(p, format=99), "field 'format' is 99"),
    (lambda p: _good(p, step="3"), "field 'step' must be a non-negative integer"),
    (lambda p: _good(p, step=-1), "field 'step' must be a non-negative integer"),
    (lambda p: _good(p, kind=7), "field 'kind' must be a string"),
    (lambda p: _good(p, model={"w": [1.0, 2.0]}), "field 'model' must map parameter names to tensors"),
    (lambda p: _good(p, meta=[1]), "field 'meta' must be a dict"),
    (lambda p: _good(p, kind="detector"), "field 'kind' is 'detector', expected one of ['coarse']"),
    (lambda p: torch.save({"x": np.zeros(3)}, p), "refused"),  # numpy arrays are not weights-only data
], ids=["empty", "not-torch", "truncated", "a-list", "no-fields", "format", "step-str", "step-negative",
        "kind-int", "model-not-tensors", "meta-list", "wrong-kind", "numpy-array"])
def test_broken_checkpoint_names_the_file_and_the_problem(tmp_path, make, words):
    path = tmp_path / "bad.pt"
    make(path)
    with pytest.raises(CheckpointError) as e:
        load_checkpoint(path, kind="coarse")
    assert str(e.value).startswith(f"{path}: ") and words in str(e.value), str(e.value)


def test_a_folder_instead_of_a_checkpoint(tmp_path):
    with pytest.raises(CheckpointError, match="checkpoint file not found"):
        load_checkpoint(tmp_path)


def _truncated(path: Path) -> Path:
    save_checkpoint(path, Checkpoint("coarse", {"w": torch.ones(3)}, {}, 1))
    path.write_bytes(path.read_bytes()[:100])
    return path


@pytest.mark.parametrize("command", ["infer-coarse", "export-coarse", "export-detector", "export-missing"])
def test_entry_point_with_a_broken_checkpoint_is_one_message(tmp_path, capsys, command):
    import infer
    from cosy_lite.cli import main

    bad = tmp_path / "missing.pt" if command == "export-missing" else _truncated(tmp_path / "bad.pt")
    if command == "infer-coarse":
        rc = infer.main(["--dataset", str(write_tiny_bop(tmp_path)), "--coarse", str(bad), "--detections", "oracle",
                         "--out", str(tmp_path / "out"), "--no-progress"])
    else:
        flag = "--detector" if command == "export-detector" else "--coarse"
        rc = main(["export", flag, str(bad), "--out", str(tmp_path / "models")])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert f"{bad}: " in err and ("not a readable checkpoint" in err or "not found" in err), err
    assert not (tmp_path / "models").exists()  # nothing exported


# ----------------------------------------------------------------------------- round trip


@dataclasses.dataclass
class _Net:
    crop_resolution: tuple[int, int] = (60, 80)
    backbone: str = "resnet18"


def test_save_stores_plain_data_that_loads_weights_only(tmp_path):
    model = torch.nn.Linear(3, 2)
    optimizer = torch.optim.Adam(model.parameters())
    model(torch.ones(1, 3)).sum().backward()
    optimizer.step()
    meta = {"net": _Net(), "dataset_root": Path("/data/ycbv"), "score": np.float32(0.5), "obj_ids": (1, 2)}
    path = tmp_path / "ck.pt"
    save_checkpoint(path, Checkpoint("coarse", model.state_dict(), {"run": tmp_path}, 7,
                                     {"optimizer": optimizer.state_dict()}, meta))
    payload = torch.load(path, weights_only=True)  # what an untrusting reader does
    assert payload["meta"] == {"net": {"crop_resolution": (60, 80), "backbone": "resnet18"},
                               "dataset_root": "/data/ycbv", "score": 0.5, "obj_ids": (1, 2)}
    assert payload["config"] == {"run": str(tmp_path)}
    ck = load_checkpoint(path, kind="coarse")
    restored = torch.nn.Linear(3, 2)
    restored.load_state_dict(ck.model)
    torch.optim.Adam(restored.parameters()).load_state_dict(ck.train_state["optimizer"])
    for k, v in model.state_dict().items():
        torch.testing.assert_close(restored.state_dict()[k], v, rtol=0, atol=0)
    assert not list(tmp_path.glob(".*tmp*"))


def test_save_refuses_what_cannot_be_loaded_weights_only(tmp_path):
    with pytest.raises(TypeError, match=r"checkpoint\.meta\.hook: a .*Payload cannot be stored"):
        save_checkpoint(tmp_path / "ck.pt", Checkpoint("coarse", {}, {}, 0, meta={"hook": Payload(tmp_path / "m")}))
    assert not list(tmp_path.iterdir())  # no checkpoint, no temporary file


# ----------------------------------------------------------------------------- reference-model cards and metadata

SET = "ycbvsynth"


def _edit_card(kind: str, change):
    def apply(folder: Path) -> None:
        card = json.loads((folder / f"{kind}.json").read_text())
        change(card)
        (folder / f"{kind}.json").write_text(json.dumps(card))
    return apply


def _flip_last_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF  # tensor data: the file stays readable, only its hash changes
    path.write_bytes(bytes(data))


# the shipped set's detector shards and refiner file, as its cards list them (they change when a set is published)
_SHIPPED = Path(__file__).resolve().parents[1] / "models" / "ycbvsynth"
_DET = json.loads((_SHIPPED / "detector.json").read_text())
_SHARDS = _DET["weights"]
_N = len(_SHARDS)
_REF_BYTES = json.loads((_SHIPPED / "refiner.json").read_text())["files"]["refiner.safetensors"]["bytes"]

# (change to a copy of the shipped set, the file the message names, its field, words of the problem)
CARD_PROBLEMS = {
    "weights-file-missing": (lambda f: (f / "refiner.safetensors").unlink(), "refiner.json", "weights",
                             "names refiner.safetensors, which is not in"),
    "shard-missing": (lambda f: (f / _SHARDS[1]).unlink(), "detector.json", "weights",
                      f"names {_SHARDS[1]}, which is not in"),
    "card-names-other-shards": (_edit_card("detector", lambda c: c.update(
        weights=[f"detector-{i:05d}-of-{_N + 1:05d}.safetensors" for i in range(1, _N + 2)])), "detector.json", "weights",
        f"names detector-00001-of-{_N + 1:05d}.safetensors, which is not in"),
    "extra-shard": (lambda f: shutil.copyfile(f / _SHARDS[-1], f / f"detector-{_N + 1:05d}-of-{_N + 1:05d}.safetensors"),
                    "detector.json", "weights", f"detector-{_N + 1:05d}-of-{_N + 1:05d}.safetensors is in"),
    "size-differs": (lambda f: (f / "refiner.safetensors").open("ab").write(b"\0"), "refiner.json",
                     "files[refiner.safetensors].bytes", f"is {_REF_BYTES + 1} bytes, the card says {_REF_BYTES}"),
    "sha256-differs": (lambda f: _flip_last_byte(f / _SHARDS[-1]), "detector.json",
                       f"files[{_SHARDS[-1]}].sha256", f"the card says {_DET['files'][_SHARDS[-1]]['sha256'][:8]}"),
    "obj-ids-a-string": (_edit_card("refiner", lambda c: c.update(obj_ids="1,2,3")), "refiner.json", "obj_ids",
                         "expected a list of positive integers, got str '1,2,3'"),
    "weights-a-string": (_edit_card("refiner", lambda c: c.update(weights="refiner.safetensors")), "refiner.json",
                         "weights", "expected a list of the weights file names, got str"),
    "files-field-missing": (_edit_card("refiner", lambda c: c.pop("files")), "refiner.json", "files", "missing"),
}


@pytest.fixture
def set_copy(tmp_path, monkeypatch) -> Path:
    """A copy of the shipped set ``ycbvsynth`` under ``$COSY_LITE_MODELS`` (the shipped files stay as they are)."""
    from cosy_lite.weights.reference_models import reference_root

    folder = tmp_path / "sets" / SET
    shutil.copytree(reference_root() / SET, folder)
    monkeypatch.setenv("COSY_LITE_MODELS", str(folder.parent))
    return folder


def _predict_pretrained(tmp_path: Path, capsys) -> tuple[int, list[str], str]:
    from cosy_lite.cli import main

    rc = main(["predict", "--pretrained", SET, "--rgb", str(tmp_path / "rgb.png"), "--camera", str(tmp_path / "K.json"),
               "--meshes", str(tmp_path), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    return rc, [line for line in err.splitlines() if line.strip()], err


@pytest.mark.parametrize("name", list(CARD_PROBLEMS))
def test_a_set_whose_files_disagree_with_its_card_is_one_message(set_copy, tmp_path, capsys, name):
    change, card, fld, words = CARD_PROBLEMS[name]
    change(set_copy)
    rc, lines, err = _predict_pretrained(tmp_path, capsys)
    assert rc == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"cosy-lite predict: error: {set_copy / card}: field '{fld}': ") and words in lines[0], lines[0]


def test_a_weights_file_without_its_card_is_refused(set_copy, tmp_path, capsys):
    (set_copy / "refiner.json").unlink()
    rc, lines, err = _predict_pretrained(tmp_path, capsys)
    assert rc == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"cosy-lite predict: error: {set_copy / 'refiner.safetensors'}: no card refiner.json"), lines[0]


@pytest.mark.parametrize("kind, meta, fld, words", [
    ("refiner", {"obj_ids": "1,2,3"}, "meta.obj_ids", "expected a list of positive integers, got str '1,2,3'"),
    ("refiner", {"obj_ids": [1, 0]}, "meta.obj_ids", "expected a list of positive integers, got list [1, 0]"),
    ("refiner", {"net": "flow"}, "meta.net", "expected a JSON object (the PoseNetConfig), got str 'flow'"),
    ("detector", {"label_map": {"obj_ids": "1,2"}}, "meta.label_map",
     "expected a JSON object {'obj_ids': a list of positive integers}, got dict"),
], ids=["obj-ids-a-string", "obj-id-zero", "net-a-string", "label-map-ids-a-string"])
def test_mistyped_metadata_of_a_weights_file_names_the_field(tmp_path, capsys, kind, meta, fld, words):
    from cosy_lite.cli import main
    from cosy_lite.weights.checkpoint import load_weights, save_weights
    from cosy_lite.weights.reference_models import reference_models

    ckpt = load_weights(reference_models(SET).path(kind))
    ckpt.meta.update(meta)
    bad = save_weights(tmp_path / f"{kind}.safetensors", ckpt)[0]
    rc = main(["export", f"--{kind}", str(bad), "--out", str(tmp_path / "onnx")])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"cosy-lite export: error: {bad}: field '{fld}': {words}"), lines[0]
    assert not (tmp_path / "onnx").exists()
