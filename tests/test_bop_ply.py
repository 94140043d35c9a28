"""The numpy PLY geometry reader: the same arrays as trimesh on binary triangle meshes (either byte
order, extra properties, texture-coordinate lists), None for every other shape of file (which
trimesh then reads), and the metres and checks of ``io.load_model_geometry``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from cosy_lite.bop import io
from cosy_lite.bop.ply import read_triangles
from cosy_lite.errors import BopFormatError


def _box() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=[40.0, 30.0, 20.0]).subdivide()


def _binary_ply(path: Path, vertices: np.ndarray, faces: np.ndarray, order: str = "<",
                texcoords: bool = False, counts: np.ndarray | None = None) -> Path:
    """A PLY written by hand: vertex x, y, z (float), nx (double), red (uchar); face vertex_indices
    (uchar count, int), optionally a texcoord list (uchar count, 6 floats)."""
    fmt = {"<": "binary_little_endian", ">": "binary_big_endian"}[order]
    head = ["ply", f"format {fmt} 1.0", "comment made by hand", f"element vertex {len(vertices)}",
            "property float x", "property float y", "property float z", "property double nx", "property uchar red",
            f"element face {len(faces)}", "property list uchar int vertex_indices"]
    if texcoords:
        head.append("property list uchar float texcoord")
    head.append("end_header")
    vdt = np.dtype([("x", order + "f4"), ("y", order + "f4"), ("z", order + "f4"), ("nx", order + "f8"), ("red", "u1")])
    v = np.zeros(len(vertices), vdt)
    v["x"], v["y"], v["z"], v["nx"], v["red"] = vertices[:, 0], vertices[:, 1], vertices[:, 2], 0.5, 7
    fields = [("n", "u1"), ("idx", order + "i4", (faces.shape[1],))]
    if texcoords:
        fields += [("m", "u1"), ("uv", order + "f4", (6,))]
    f = np.zeros(len(faces), np.dtype(fields))
    f["n"] = faces.shape[1] if counts is None else counts
    f["idx"] = faces
    if texcoords:
        f["m"], f["uv"] = 6, 0.25
    path.write_bytes(("\n".join(head) + "\n").encode() + v.tobytes() + f.tobytes())
    return path


@pytest.mark.parametrize("order", ["<", ">"])
@pytest.mark.parametrize("texcoords", [False, True])
def test_binary_triangle_meshes_read_as_trimesh_reads_them(tmp_path: Path, order: str, texcoords: bool):
    box = _box()
    path = _binary_ply(tmp_path / "m.ply", np.asarray(box.vertices), np.asarray(box.faces), order, texcoords)
    got = read_triangles(path)
    assert got is not None
    ref = trimesh.load(path, force="mesh", process=False)
    np.testing.assert_array_equal(got[0], np.asarray(ref.vertices))
    np.testing.assert_array_equal(got[1], np.asarray(ref.faces))
    assert got[0].dtype == np.float64 and got[1].shape == (len(box.faces), 3)
    # the file as trimesh itself exports it
    box.export(tmp_path / "t.ply")
    got = read_triangles(tmp_path / "t.ply")
    assert got is not None
    np.testing.assert_allclose(got[0], box.vertices, rtol=1e-6)
    np.testing.assert_array_equal(got[1], box.faces)


def test_other_files_are_left_to_trimesh(tmp_path: Path):
    box = _box()
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    ascii_path = tmp_path / "ascii.ply"
    box.export(ascii_path, encoding="ascii")
    quads = np.array([[0, 1, 2, 3], [4, 5, 6, 7]])
    cases = {
        "ascii": ascii_path,
        "quads": _binary_ply(tmp_path / "quads.ply", v, quads),
        "mixed list lengths": _binary_ply(tmp_path / "mixed.ply", v, f, counts=np.where(np.arange(len(f)) == 5, 4, 3)),
        "truncated": tmp_path / "short.ply",
        "not a ply": tmp_path / "text.ply",
    }
    data = _binary_ply(tmp_path / "full.ply", v, f).read_bytes()
    cases["truncated"].write_bytes(data[: len(data) - 10])
    cases["not a ply"].write_text("solid cube\nendsolid\n")
    # hostile list counts: negative, 4e9, a float type
    head = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 1\nproperty list %s int vertex_indices\nend_header\n")
    body = np.zeros(9, "<f4").tobytes()
    for name, ctype, count in (("negative count", b"char", np.int8(-3)), ("huge count", b"uint", np.uint32(4e9)),
                               ("float count", b"float", np.float32(3.0))):
        cases[name] = tmp_path / f"{name}.ply"
        cases[name].write_bytes(head % ctype + body + count.tobytes() + np.arange(3, dtype="<i4").tobytes())
    for name, path in cases.items():
        assert read_triangles(path) is None, name
    # through io, the fallback gives trimesh's arrays (quads split in two) or its error, named
    got_v, got_f = io.load_model_geometry(ascii_path)
    np.testing.assert_allclose(got_v, v * 1e-3)
    np.testing.assert_array_equal(got_f, f)
    assert io.read_model_arrays(cases["quads"])[1].shape == (4, 3)
    with pytest.raises(BopFormatError, match="cannot read mesh"):
        io.load_model_geometry(cases["not a ply"])


def test_geometry_in_metres_with_the_model_checks(tmp_path: Path):
    box = _box()
    path = _binary_ply(tmp_path / "m.ply", np.asarray(box.vertices), np.asarray(box.faces))
    vertices, faces = io.load_model_geometry(path)
    mesh = io.load_model(path)
    np.testing.assert_array_equal(vertices, np.asarray(mesh.vertices))
    np.testing.assert_array_equal(faces, np.asarray(mesh.faces))
    assert np.ptp(vertices, axis=0).max() == pytest.approx(0.04)
    bad = _binary_ply(tmp_path / "bad.ply", np.asarray(box.vertices), np.asarray(box.faces) + 1000)
    with pytest.raises(BopFormatError, match="face vertex indices") as info:
        io.load_model_geometry(bad)
    assert info.value.field == "face" and info.value.path == str(bad)
    metres = _binary_ply(tmp_path / "metres.ply", np.asarray(box.vertices) * 1e-3, np.asarray(box.faces))
    with pytest.raises(BopFormatError, match="implausibly small"):
        io.load_model_geometry(metres)
    nan = np.asarray(box.vertices).copy()
    nan[3, 1] = np.nan
    with pytest.raises(BopFormatError, match="NaN"):
        io.load_model_geometry(_binary_ply(tmp_path / "nan.ply", nan, np.asarray(box.faces)))
    with pytest.raises(BopFormatError, match="not found"):
        io.load_model_geometry(tmp_path / "missing.ply")
