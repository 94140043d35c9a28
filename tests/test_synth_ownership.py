"""The generator never replaces a mesh: it writes only into a folder it made for the same objects
(``cosy_lite/synth/ownership.py``), and the demo uses a dataset of your meshes as it is."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cosy_lite.cli import main
from cosy_lite.errors import BopFormatError
from cosy_lite.synth.ownership import LIBRARY_MANIFEST, MESH_SOURCES, check_can_write, meshes_command

TINY = ["train.n_images=2", "train.views_per_layout=2", "test.n_images=2", "test.views_per_layout=2",
        "objects_per_layout=[2,2]", "distractors_per_layout=[0,0]", "seed=3"]


def _tree(root: Path) -> dict[str, str]:
    """Every file under ``root`` -> its SHA-256."""
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def my_dataset(tmp_path_factory) -> tuple[Path, Path]:
    """(meshes folder, the dataset generated from it): a box and a can, in mm."""
    d = tmp_path_factory.mktemp("own")
    meshes = d / "my_meshes"
    meshes.mkdir()
    box = trimesh.creation.box(extents=(100.0, 60.0, 40.0))
    box.visual.vertex_colors = np.tile([200, 30, 30, 255], (len(box.vertices), 1)).astype(np.uint8)
    box.export(meshes / "a_box.ply")
    trimesh.creation.cylinder(radius=30.0, height=80.0, sections=48).export(meshes / "b_can.obj")
    out = d / "data" / "myobjects"
    assert main(["generate", "--meshes", str(meshes), "--units", "mm", "--out", str(out), *TINY]) == 0
    return meshes, out


def test_the_library_is_never_written_over_your_meshes(my_dataset, capsys):
    meshes, out = my_dataset
    before, inputs = _tree(out), _tree(meshes)
    capsys.readouterr()
    assert main(["generate", "--out", str(out), *TINY]) == 2  # the default objects: the YCB-V library
    err = capsys.readouterr().err
    assert str(out / MESH_SOURCES) in err and "your meshes" in err
    assert f"--meshes {meshes}" in err and "--units mm" in err  # the command that continues it
    assert _tree(out) == before and _tree(meshes) == inputs  # not a byte changed, no file added


def test_other_meshes_or_units_are_refused(my_dataset, tmp_path, capsys):
    meshes, out = my_dataset
    before = _tree(out)
    assert main(["generate", "--meshes", str(meshes), "--units", "m", "--out", str(out), *TINY]) == 2
    assert "other meshes (or units)" in capsys.readouterr().err
    other = tmp_path / "other"
    other.mkdir()
    trimesh.creation.box(extents=(50.0, 50.0, 50.0)).export(other / "a_box.ply")
    assert main(["generate", "--meshes", str(other), "--units", "mm", "--out", str(out), *TINY]) == 2
    assert _tree(out) == before
    # the same meshes continue it (here: nothing missing, nothing rewritten)
    assert main(["generate", "--meshes", str(meshes), "--units", "mm", "--out", str(out), *TINY]) == 0
    assert _tree(out) == before


def _library_folder(root: Path, changed: bool = False, listed: bool = True) -> Path:
    """A folder as the library generator leaves it: one mesh and the manifest with its SHA-256."""
    (root / "models").mkdir(parents=True)
    mesh = root / "models" / "obj_000001.ply"
    mesh.write_bytes(b"ply written by the generator")
    files = {"models/obj_000001.ply": hashlib.sha256(mesh.read_bytes()).hexdigest()} if listed else {}
    (root / LIBRARY_MANIFEST).write_text(json.dumps({"1": {"key": "k", "files": files, "info": {}}}))
    if changed:
        mesh.write_bytes(b"ply edited by a person")
    return mesh


def test_library_folders(tmp_path):
    check_can_write(tmp_path / "new", None, [1, 2])  # a new folder
    _library_folder(tmp_path / "ok")
    check_can_write(tmp_path / "ok", None, [1, 2])  # its own meshes, unchanged: rebuilt only if their inputs changed
    mesh = _library_folder(tmp_path / "edited", changed=True)
    with pytest.raises(BopFormatError, match="changed since cosy-lite generate wrote it") as e:
        check_can_write(tmp_path / "edited", None, [1])
    assert e.value.path == str(mesh)
    mesh = _library_folder(tmp_path / "unlisted", listed=False)
    with pytest.raises(BopFormatError, match="not written by cosy-lite generate") as e:
        check_can_write(tmp_path / "unlisted", None, [1])
    assert e.value.path == str(mesh)
    with pytest.raises(BopFormatError, match="holds the generated YCB-V objects"):
        check_can_write(tmp_path / "ok", {1: ("/x/a.ply", "mm")})


def test_a_dataset_the_generator_did_not_make_is_refused(tmp_path):
    (tmp_path / "ycbv" / "models").mkdir(parents=True)
    (tmp_path / "ycbv" / "models" / "obj_000001.ply").write_bytes(b"an official BOP mesh")
    for sources in (None, {1: ("/x/a.ply", "mm")}):
        with pytest.raises(BopFormatError, match="not written by cosy-lite generate") as e:
            check_can_write(tmp_path / "ycbv", sources, [1])
        assert e.value.path == str(tmp_path / "ycbv" / "models")
    (tmp_path / "damaged" / "models").mkdir(parents=True)
    (tmp_path / "damaged" / "models" / "obj_000001.ply").write_bytes(b"x")
    (tmp_path / "damaged" / MESH_SOURCES).write_text("{not json")
    with pytest.raises(BopFormatError, match="unreadable"):
        check_can_write(tmp_path / "damaged", None, [1])


def test_meshes_command_names_folder_and_unit():
    cmd = meshes_command(Path("data/x"), {1: ("/m/a.ply", "mm"), 2: ("/m/b.obj", "mm")})
    assert cmd == "cosy-lite generate --meshes /m --units mm --out data/x"


def test_demo_uses_your_dataset_as_it_is(my_dataset, tmp_path):
    """The demo's dataset step on a dataset of your meshes: complete -> used as it is (nothing written
    into it); a split missing -> stops, naming it and the command that adds it."""
    import shutil

    from cosy_lite.demo import DemoConfig, prepare_dataset

    meshes, out = my_dataset
    root = tmp_path / "data" / "myobjects"
    shutil.copytree(out, root)
    cfg = DemoConfig(dataset="myobjects", data_root=tmp_path / "data", out=tmp_path / "outputs", runs=tmp_path / "runs")
    before = _tree(root)
    assert prepare_dataset(cfg) == root
    assert _tree(root) == before
    shutil.rmtree(root / "test")
    (root / "test_targets_bop19.json").unlink()
    before = _tree(root)
    with pytest.raises(SystemExit, match=r"(?s)has no test split.*--meshes .* --units mm .* --splits test"):
        prepare_dataset(cfg)
    assert _tree(root) == before


@pytest.mark.slow
def test_your_objects_end_to_end_leave_your_meshes_alone(my_dataset, tmp_path):
    """The README's path for your own objects at toy size: generate from two meshes (the fixture), the
    demo trains on them, infers and evaluates (AR reported), predict poses one image; the meshes, given
    and generated, are byte-identical afterwards and no foreign object appeared (the demo regenerated
    the YCB-V library into such a folder, overwriting obj_000001/2.ply)."""
    import json
    import subprocess
    import sys

    meshes, _ = my_dataset
    data = tmp_path / "data"
    sizes = ["train.n_images=8", "train.views_per_layout=8", "test.n_images=2", "test.views_per_layout=2",
             "objects_per_layout=[2,2]", "distractors_per_layout=[0,0]"]  # the demo's --quick sizes
    assert main(["generate", "--meshes", str(meshes), "--units", "mm", "--out", str(data / "myobjects"), *sizes]) == 0
    inputs, before = _tree(meshes), _tree(data / "myobjects" / "models")
    env = {**__import__("os").environ, "OMP_NUM_THREADS": "1"}
    demo = subprocess.run([sys.executable, "-m", "cosy_lite.cli", "demo", "--dataset", "myobjects", "--data-root", str(data),
                           "--runs", str(tmp_path / "runs"), "--out", str(tmp_path / "outputs"), "--quick"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=1500)
    assert demo.returncode == 0, demo.stdout[-3000:] + demo.stderr[-3000:]
    assert "your meshes" in demo.stdout and "AR" in (tmp_path / "outputs" / "demo_summary.md").read_text()
    rec = json.loads((data / "myobjects" / "test" / "000000" / "scene_camera.json").read_text())["0"]
    (tmp_path / "camera.json").write_text(json.dumps({"K": np.asarray(rec["cam_K"]).reshape(3, 3).tolist()}))
    runs = tmp_path / "runs"
    assert main(["predict", "--rgb", str(data / "myobjects" / "test" / "000000" / "rgb" / "000000.png"),
                 "--camera", str(tmp_path / "camera.json"), "--meshes", str(data / "myobjects"),
                 "--detector", str(runs / "detector" / "checkpoint.pt"), "--start", "templates",
                 "--refiner", str(runs / "refiner" / "checkpoint.pt"), "--min-score", "0",
                 "--out", str(tmp_path / "pred")]) == 0
    assert (tmp_path / "pred" / "predictions.json").is_file()
    assert _tree(meshes) == inputs and _tree(data / "myobjects" / "models") == before
