"""``cosy-lite generate --meshes DIR --units mm|m``: meshes made here (PLY, OBJ, GLB) -> a complete,
valid BOP dataset; units checked for plausibility; clear errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.bop.validate import check_dataset
from cosy_lite.cli import main
from cosy_lite.errors import BopFormatError
from cosy_lite.synth.custom_objects import find_meshes, load_user_mesh

TINY = ["train.n_images=2", "train.views_per_layout=2", "test.n_images=2", "test.views_per_layout=2",
        "objects_per_layout=[2,3]", "distractors_per_layout=[0,1]", "seed=3"]


@pytest.fixture(scope="module")
def meshes(tmp_path_factory) -> Path:
    """A box (PLY, red vertex colours), a cylinder (OBJ, no colours) and a cone (GLB), in mm."""
    d = tmp_path_factory.mktemp("meshes")
    box = trimesh.creation.box(extents=(100.0, 60.0, 40.0))
    box.visual.vertex_colors = np.tile([200, 30, 30, 255], (len(box.vertices), 1)).astype(np.uint8)
    box.export(d / "a_box.ply")
    trimesh.creation.cylinder(radius=30.0, height=80.0, sections=48).export(d / "b_can.obj")
    trimesh.creation.cone(radius=25.0, height=50.0, sections=32).export(d / "c_cone.glb")
    (d / "notes.txt").write_text("not a mesh")
    return d


def test_object_ids_and_units(meshes, tmp_path):
    assert {o: p.name for o, p in find_meshes(meshes).items()} == {1: "a_box.ply", 2: "b_can.obj", 3: "c_cone.glb"}
    m = load_user_mesh(meshes / "a_box.ply", "mm")
    assert np.ptp(m.vertices, axis=0) == pytest.approx([0.1, 0.06, 0.04])  # metres
    with pytest.raises(BopFormatError, match=r"diameter 123.3 m = 123.3 m is implausible.*with --units mm it would be 0.1233 m"):
        load_user_mesh(meshes / "a_box.ply", "m")
    trimesh.creation.box(extents=(0.1, 0.06, 0.04)).export(tmp_path / "small.ply")
    with pytest.raises(BopFormatError,
                       match=r"diameter 0.1233 mm = 0.0001233 m is implausible.*with --units m it would be 0.1233 m"):
        load_user_mesh(tmp_path / "small.ply", "mm")
    named = tmp_path / "named"
    named.mkdir()
    for i in (4, 9):
        trimesh.creation.box(extents=(50.0, 50.0, 50.0)).export(named / f"obj_{i:06d}.ply")
    assert sorted(find_meshes(named)) == [4, 9]  # BOP names keep their ids


def test_generate_a_complete_bop_dataset(meshes, tmp_path):
    out = tmp_path / "myobjects"
    assert main(["generate", "--meshes", str(meshes), "--units", "mm", "--out", str(out), *TINY]) == 0
    assert [p for p in check_dataset(out) if p.severity == "error"] == []
    ds = BopDataset(out)
    assert ds.obj_ids == [1, 2, 3]
    info = ds.models_info
    assert info[1].diameter == pytest.approx(np.linalg.norm([0.1, 0.06, 0.04]), rel=1e-5)
    assert info[2].diameter == pytest.approx(np.hypot(0.06, 0.08), rel=1e-3)  # rim to opposite rim
    assert info[2].symmetries_continuous  # a plain cylinder: rotations about its axis
    mesh = ds.load_model(1)
    assert np.ptp(mesh.vertices, axis=0) == pytest.approx([0.1, 0.06, 0.04], rel=1e-5)
    assert (np.asarray(mesh.visual.vertex_colors)[:, :3] == [200, 30, 30]).all()  # its own colours kept
    sources = json.loads((out / "models_sources.json").read_text())
    assert sources["2"]["file"].endswith("b_can.obj") and sources["2"]["units"] == "mm"
    assert len(list((out / "test").glob("*/rgb/*.png"))) == 2 and len(list((out / "train_pbr").glob("*/rgb/*.jpg"))) == 2
    gt_objs = {g.obj_id for rec in ds.images("test") for g in rec.gt}
    assert gt_objs and gt_objs <= {1, 2, 3}
    assert json.loads((out / "test_targets_bop24.json").read_text())


def test_bad_generate_arguments(meshes, tmp_path, capsys):
    assert main(["generate", "--meshes", str(meshes), "--out", str(tmp_path / "x")]) == 2
    assert "--units" in capsys.readouterr().err
    assert main(["generate", "--meshes", str(meshes), "--units", "mm", "--out", str(tmp_path / "my-objects")]) == 2
    assert "'my-objects' contains '-' or '_'" in capsys.readouterr().err
    assert main(["generate", "--meshes", str(meshes), "--units", "m", "--out", str(tmp_path / "big"), *TINY]) == 2
    err = capsys.readouterr().err
    assert "a_box.ply" in err and "[--units]" in err and "implausible" in err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["generate", "--meshes", str(empty), "--units", "mm", "--out", str(tmp_path / "none")]) == 2
    assert "no mesh files" in capsys.readouterr().err


def _obj_with_uvs(path: Path, header: str = "") -> Path:
    """A box written as OBJ with texture coordinates (as exporters write them) and ``header`` lines."""
    box = trimesh.creation.box(extents=(50.0, 40.0, 30.0))
    uv = np.random.default_rng(0).random((len(box.vertices), 2))
    lines = [header, *("v %f %f %f" % tuple(v) for v in box.vertices), *("vt %f %f" % tuple(t) for t in uv),
             *("f " + " ".join(f"{i + 1}/{i + 1}" for i in f) for f in box.faces)]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_meshes_without_colour_get_one_of_their_own_and_missing_textures_one_warning(tmp_path):
    """OBJ files with texture coordinates but no texture came out trimesh's placeholder grey
    (100, 100, 100), all alike; a missing material or texture file is one warning naming it."""
    import warnings

    from cosy_lite.synth.custom_objects import _colours

    plain = load_user_mesh(_obj_with_uvs(tmp_path / "a.obj"), "mm")
    with pytest.warns(UserWarning, match=r"b.obj: .*nothere.mtl not found") as record:
        missing = load_user_mesh(_obj_with_uvs(tmp_path / "b.obj", "mtllib nothere.mtl\nusemtl m"), "mm")
    assert len(record) == 1
    means = [_colours(m, i).mean(axis=0) for i, m in ((1, plain), (2, missing))]
    for m in means:
        assert np.abs(m - 100).max() > 20  # not the placeholder grey
    assert np.abs(means[0] - means[1]).max() > 30  # two objects, two colours
    (tmp_path / "red.mtl").write_text("newmtl m\nKd 0.8 0.2 0.2\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing is missing: no warning
        red = load_user_mesh(_obj_with_uvs(tmp_path / "c.obj", "mtllib red.mtl\nusemtl m"), "mm")
    assert np.allclose(_colours(red, 3).mean(axis=0), [204, 51, 51], atol=1)  # the material's colour


def test_contours_stay_visible_on_an_object_of_their_colour():
    from cosy_lite.vis.overlay import draw_contour

    image = np.full((40, 40, 3), 255, np.uint8)  # a white object
    mask = np.zeros((40, 40), bool)
    mask[10:30, 10:30] = True
    out = draw_contour(image, mask, (255, 255, 255))  # the GT colour
    assert (out.sum(axis=2) < 384).sum() > 100  # its dark halo, either side of the outline
