"""The YCB-V object library and the BOP models writer: round trip in mm/m, texture and colours,
models_info (diameter, box, symmetries), determinism and cheap resume. Four objects, a few seconds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.distance import cdist

from cosy_lite.bop.io import load_model, load_models_info
from cosy_lite.geometry.symmetries import find_symmetries
from cosy_lite.synth.objects import ASSETS_DIR, YCBV_OBJECTS, load_ycb_mesh, write_bop_models

IDS = [1, 2, 13, 16]  # untextured can, textured box, bowl, wood block


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("objects")
    return root, write_bop_models(IDS, root)


def _max_pairwise(v: np.ndarray, chunk: int = 1024) -> float:
    return max(float(cdist(v[i:i + chunk], v).max()) for i in range(0, len(v), chunk))


def test_table_is_ycbv():
    assert sorted(YCBV_OBJECTS) == list(range(1, 22))
    assert YCBV_OBJECTS[1].name == "002_master_chef_can" and YCBV_OBJECTS[21].name == "061_foam_brick"
    textured = {i for i, o in YCBV_OBJECTS.items() if o.texture_asset}
    assert textured == {2, 3, 4, 5, 8, 9}
    for i, o in YCBV_OBJECTS.items():
        assert o.obj_id == i and (o.texture_asset is None) != (o.appearance is None)
        if o.texture_asset:
            assert (ASSETS_DIR / o.texture_asset).is_file()


def test_meshes_are_centred_metres_with_visuals():
    tex = load_ycb_mesh(2)
    assert isinstance(tex.visual, trimesh.visual.TextureVisuals)
    assert tex.visual.uv.shape == (len(tex.vertices), 2) and tex.visual.material.baseColorTexture is not None
    col = load_ycb_mesh(1)
    assert col.visual.kind == "vertex"
    for m in (tex, col):
        assert np.abs(m.bounds.mean(axis=0)).max() < 1e-9
        assert 0.05 < np.ptp(m.vertices, axis=0).max() < 0.3  # metres
    assert np.ptp(tex.vertices, axis=0)[2] == pytest.approx(0.2134, abs=1e-3)  # z up: the box stands


def test_round_trip_metres(written):
    root, infos = written
    for i in IDS:
        ref = load_ycb_mesh(i)
        for folder in ("models", "models_eval"):
            m = load_model(root / folder / f"obj_{i:06d}.ply")
            assert len(m.vertices) == len(ref.vertices)
            assert np.abs(np.asarray(m.vertices) - ref.vertices).max() < 1e-6
            assert np.allclose(m.bounds, ref.bounds, atol=1e-6)
        info = infos[i]
        assert np.abs(info.mins + info.sizes / 2).max() < 1e-4  # box centre at the origin
        assert np.allclose(info.mins, ref.bounds[0], atol=1e-6)


def test_diameter_is_the_largest_vertex_distance(written):
    root, infos = written
    for i in IDS:
        v = np.asarray(load_model(root / "models_eval" / f"obj_{i:06d}.ply").vertices)
        assert infos[i].diameter == pytest.approx(_max_pairwise(v), abs=1e-3)  # within 1 mm


def test_texture_and_colours_come_back(written):
    root, _ = written
    header = (root / "models" / "obj_000002.ply").read_bytes()[:400].decode("ascii", "replace")
    assert "comment TextureFile obj_000002.png" in header and "property float texture_u" in header
    assert (root / "models" / "obj_000002.png").read_bytes() == (ASSETS_DIR / "003_cracker_box_textured.png").read_bytes()
    m = load_model(root / "models" / "obj_000002.ply")
    assert isinstance(m.visual, trimesh.visual.TextureVisuals)
    assert m.visual.material.image is not None and m.visual.material.image.size == (1024, 1024)
    assert np.allclose(m.visual.uv, load_ycb_mesh(2).visual.uv, atol=1e-6)
    c = load_model(root / "models" / "obj_000013.ply")
    assert np.array_equal(c.visual.vertex_colors, load_ycb_mesh(13).visual.vertex_colors)
    e = load_model(root / "models_eval" / "obj_000013.ply")
    assert e.visual.kind is None  # models_eval: geometry only
    assert b"red" not in (root / "models_eval" / "obj_000013.ply").read_bytes()[:400]


def test_models_info_files(written):
    root, infos = written
    a = (root / "models" / "models_info.json").read_bytes()
    assert a == (root / "models_eval" / "models_info.json").read_bytes()
    back = load_models_info(root / "models" / "models_info.json")
    assert sorted(back) == IDS
    assert back[13].diameter == pytest.approx(infos[13].diameter)


def test_symmetries(written):
    _, infos = written
    bowl = infos[13]
    assert len(bowl.symmetries_continuous) == 1
    assert abs(bowl.symmetries_continuous[0][0][2]) > 0.99  # about the vertical axis
    assert not infos[2].is_symmetric  # the printed cracker box texture resolves the flips
    mesh = load_ycb_mesh(2)
    discrete, continuous = find_symmetries(mesh.vertices, infos[2].diameter)  # geometry alone
    assert continuous == [] and len(discrete) == 3
    for S in discrete:
        assert np.trace(S[:3, :3]) == pytest.approx(-1.0, abs=1e-6)  # 180 deg flips
    axes = [np.linalg.eigh(S[:3, :3] + S[:3, :3].T)[1][:, -1] for S in discrete]
    assert np.allclose(np.abs(np.array(axes) @ np.array(axes).T), np.eye(3), atol=1e-6)  # about 3 orthogonal axes


def test_deterministic_and_cheap_resume(written, tmp_path):
    root, infos = written
    files = sorted(p for p in root.rglob("*") if p.is_file())
    before = {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in files}
    again = write_bop_models(IDS, root)
    assert sorted(p for p in root.rglob("*") if p.is_file()) == files
    for p in files:
        assert (p.stat().st_mtime_ns, p.read_bytes()) == before[p], p  # nothing rewritten
    assert np.allclose(again[16].symmetries_discrete, infos[16].symmetries_discrete)
    other = tmp_path / "other"
    write_bop_models([2, 13], other)
    for rel in ("models/obj_000002.ply", "models/obj_000013.ply", "models_eval/obj_000013.ply"):
        assert (other / rel).read_bytes() == (root / rel).read_bytes()


def test_a_reference_sets_meshes_come_from_the_package(tmp_path, monkeypatch):
    """``predict --pretrained ycbvsynth`` needs the set's meshes: without a generated dataset they are
    written once from the installed package into the cache (it stopped: "no models_info.json")."""
    from cosy_lite.errors import BopFormatError
    from cosy_lite.inference.command_predict import _reference_meshes
    from cosy_lite.synth.library_meshes import library_models

    monkeypatch.setenv("COSY_LITE_DATA", str(tmp_path / "data"))
    monkeypatch.setenv("COSY_LITE_CACHE", str(tmp_path / "cache"))
    models = _reference_meshes("ycbvsynth")
    assert models == tmp_path / "cache" / "meshes" / "ycbvsynth" / "models"
    assert len(list(models.glob("obj_*.ply"))) == 21 and (models / "models_info.json").is_file()
    stamp = (models / "obj_000001.ply").stat().st_mtime_ns
    assert library_models("ycbvsynth") == models and (models / "obj_000001.ply").stat().st_mtime_ns == stamp  # once
    (tmp_path / "data" / "ycbvsynth" / "models").mkdir(parents=True)
    (tmp_path / "data" / "ycbvsynth" / "models" / "models_info.json").write_text("{}")
    assert library_models("ycbvsynth") == tmp_path / "data" / "ycbvsynth" / "models"  # a generated dataset's first
    with pytest.raises(BopFormatError, match="not a dataset the package generates"):
        library_models("myobjects")


def test_predict_takes_the_meshes_of_the_pretrained_set(capsys):
    from cosy_lite.cli import main

    assert main(["predict", "--rgb", "x.png", "--camera", "c.json", "--out", "o"]) == 2
    assert "give --meshes NAME_OR_DIR" in capsys.readouterr().err
