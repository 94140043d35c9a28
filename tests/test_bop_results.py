"""BOP19 results CSV: exact format, round trip in metres, the time rule, file names, and one test
per malformed file (strict reader and validator both name the file and the line/column)."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import pytest
from bop_fixtures import GT, write_tiny_bop

from cosy_lite.bop import command_check_results
from cosy_lite.bop.results import (
    HEADER,
    PoseEstimate,
    parse_results_filename,
    read_results_csv,
    results_filename,
    write_results_csv,
)
from cosy_lite.bop.validate import check_results
from cosy_lite.errors import BopFormatError

ROW = "0,1,2,0.5,1.0 0.0 0.0 0.0 1.0 0.0 0.0 0.0 1.0,100.0 -20.0 500.0,0.25"


def _pose(rvec: tuple[float, float, float], t_m: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array(rvec, dtype=np.float64).reshape(3, 1))[0]
    T[:3, 3] = t_m
    return T


def _random_estimates(n: int, seed: int = 0) -> list[PoseEstimate]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        scene, im = i % 2, i // 3
        T = _pose(tuple(rng.normal(size=3)), tuple(rng.uniform(-0.3, 0.3, 2)) + (rng.uniform(0.4, 1.5),))
        out.append(PoseEstimate(scene, im, int(rng.integers(1, 22)), float(rng.random()), T, time=0.1 * im + scene))
    return out


def _csv(tmp_path: Path, *rows: str, name: str = "cosylite_tiny-test.csv", end: str = "") -> Path:
    path = tmp_path / name
    path.write_text("\n".join([HEADER, *rows]) + end)
    return path


def _strict_error(path: Path) -> BopFormatError:
    with pytest.raises(BopFormatError) as info:
        read_results_csv(path)
    return info.value


def _fields(problems) -> list[tuple[str, str, str]]:
    return [(Path(p.path).name, p.field, p.severity) for p in problems]


# ----------------------------------------------------------------------------- writing and reading


def test_round_trip_in_metres(tmp_path: Path):
    ests = _random_estimates(12)
    path = tmp_path / results_filename("cosylite", "tiny", "test")
    write_results_csv(path, ests)
    back = read_results_csv(path)
    assert len(back) == len(ests)
    for a, b in zip(back, ests):
        assert (a.scene_id, a.im_id, a.obj_id, a.score, a.time) == (b.scene_id, b.im_id, b.obj_id, b.score, b.time)
        np.testing.assert_allclose(a.TCO[:3, :3], b.TCO[:3, :3], atol=1e-9, rtol=0)
        np.testing.assert_allclose(a.TCO[:3, 3], b.TCO[:3, 3], atol=1e-6, rtol=0)
        np.testing.assert_array_equal(a.TCO[3], [0, 0, 0, 1])
    assert check_results(path) == []


def test_exact_text_header_and_no_trailing_newline(tmp_path: Path):
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.02, 0.5]
    path = tmp_path / "a_tiny-test.csv"
    write_results_csv(path, [PoseEstimate(0, 1, 2, 0.5, T, 0.25), PoseEstimate(3, 4, 5, 1.0, T, -1.0)])
    text = path.read_text()
    assert text == "\n".join([HEADER, ROW, "3,4,5,1.0,1.0 0.0 0.0 0.0 1.0 0.0 0.0 0.0 1.0,100.0 -20.0 500.0,-1.0"])
    assert text.splitlines()[0] == "scene_id,im_id,obj_id,score,R,t,time"
    assert not text.endswith("\n")
    assert not list(tmp_path.glob(".*"))  # no temp file left by the atomic write


def test_time_rule_on_write(tmp_path: Path):
    T = _pose((0.1, 0.2, 0.3), (0.0, 0.0, 0.8))
    ok = [PoseEstimate(0, 0, 1, 0.9, T, 0.5), PoseEstimate(0, 0, 2, 0.8, T, 0.5),
          PoseEstimate(0, 1, 1, 0.9, T, 0.7), PoseEstimate(1, 0, 1, 0.9, T, -1.0)]
    write_results_csv(tmp_path / "a_tiny-test.csv", ok)  # one time per image, -1 = unknown
    with pytest.raises(ValueError, match=r"scene_id 0, im_id 0, obj_id 2: time 0.6 differs"):
        write_results_csv(tmp_path / "b_tiny-test.csv", ok[:1] + [PoseEstimate(0, 0, 2, 0.8, T, 0.6)])
    assert not (tmp_path / "b_tiny-test.csv").exists()


@pytest.mark.parametrize("change, match", [
    (lambda T: T.__setitem__((0, 3), np.nan), "NaN"),
    (lambda T: T.__setitem__((slice(0, 3), 0), 2 * T[:3, 0]), "not a rotation"),
    (lambda T: T.__setitem__((slice(0, 3), 0), -T[:3, 0]), "det = -1"),
    (lambda T: T.__setitem__((slice(0, 3), 3), T[:3, 3] / 1000), "metres"),
], ids=["nan", "not-orthonormal", "reflection", "t-too-small"])
def test_write_refuses_bad_pose(tmp_path: Path, change, match):
    T = _pose((0.1, 0.2, 0.3), (0.05, 0.0, 0.8))
    change(T)
    with pytest.raises(ValueError, match=rf"scene_id 3, im_id 4, obj_id 5: .*{match}"):
        write_results_csv(tmp_path / "a_tiny-test.csv", [PoseEstimate(3, 4, 5, 0.9, T, 0.1)])


# ----------------------------------------------------------------------------- file names


def test_results_filename():
    assert results_filename("cosylite", "ycbv", "test") == "cosylite_ycbv-test.csv"
    assert parse_results_filename("/x/cosylite_ycbv-test.csv") == ("cosylite", "ycbv", "test")
    assert parse_results_filename("m-v2_ycbvsynth-test.csv") == ("m-v2", "ycbvsynth", "test")
    assert parse_results_filename("m_tless-test-primesense.csv") == ("m", "tless", "test-primesense")


def test_method_with_underscore(tmp_path: Path):
    with pytest.raises(ValueError, match="method 'cosy_lite'.*'_'"):
        results_filename("cosy_lite", "ycbv", "test")
    with pytest.raises(ValueError, match="method ''"):
        results_filename("", "ycbv", "test")
    with pytest.raises(BopFormatError) as info:
        parse_results_filename(tmp_path / "cosy_lite_ycbv-test.csv")
    e = info.value
    assert e.field == "file name" and "exactly one '_'" in e.problem
    path = _csv(tmp_path, ROW, name="cosy_lite_tiny-test.csv")
    assert _fields(check_results(path)) == [("cosy_lite_tiny-test.csv", "file name", "error")]


def test_dataset_and_split_must_match_the_given_ones(tmp_path: Path):
    path = _csv(tmp_path, ROW)
    assert check_results(path, name="tiny", split="test") == []
    probs = check_results(path, name="ycbv", split="val")
    assert _fields(probs) == [(path.name, "file name", "error")] * 2
    assert "'tiny'" in probs[0].message and "'val'" in probs[1].message


# ----------------------------------------------------------------------------- malformed files


def test_wrong_column_order(tmp_path: Path):
    path = tmp_path / "a_tiny-test.csv"
    path.write_text("scene_id,im_id,obj_id,score,t,R,time\n0,1,2,0.5,100 -20 500,1 0 0 0 1 0 0 0 1,0.25")
    e = _strict_error(path)
    assert (e.path, e.field) == (str(path), "line 1: header") and "wrong order" in e.problem
    assert _fields(check_results(path)) == [(path.name, "line 1: header", "error")]  # rows still read by name


def test_missing_header(tmp_path: Path):
    path = tmp_path / "a_tiny-test.csv"
    path.write_text(ROW)
    assert _strict_error(path).field == "line 1: header"


def test_nan(tmp_path: Path):
    path = _csv(tmp_path, ROW, "0,1,3,0.5,1 0 0 0 1 0 0 0 1,100 nan 500,0.25")
    e = _strict_error(path)
    assert (e.path, e.field) == (str(path), "line 3: t") and "NaN" in e.problem
    path = _csv(tmp_path, ROW.replace("0.5,", "inf,", 1), name="b_tiny-test.csv")
    assert _fields(check_results(path)) == [(path.name, "line 2: score", "error")]


def test_inconsistent_time_per_image(tmp_path: Path):
    path = _csv(tmp_path, ROW, ROW.replace(",2,", ",3,", 1), ROW.replace(",2,", ",4,", 1)[:-4] + "0.5")
    e = _strict_error(path)
    assert (e.path, e.field) == (str(path), "line 4: time") and "line 2" in e.problem
    assert _fields(check_results(path)) == [(path.name, "line 4: time", "error")]


def test_t_in_metres(tmp_path: Path):
    path = _csv(tmp_path, "0,1,2,0.5,1 0 0 0 1 0 0 0 1,0.1 -0.02 0.5,0.25")
    e = _strict_error(path)
    assert (e.path, e.field) == (str(path), "line 2: t") and "t looks like metres, BOP expects mm" in e.problem
    assert _fields(check_results(path)) == [(path.name, "line 2: t", "error")]


def test_trailing_blank_line(tmp_path: Path):
    path = _csv(tmp_path, ROW, end="\n\n")
    e = _strict_error(path)
    assert (e.path, e.field) == (str(path), "line 3: row") and "empty line" in e.problem
    assert (path.name, "line 3: row", "error") in _fields(check_results(path))
    middle = _csv(tmp_path, ROW, "", ROW.replace(",2,", ",3,", 1), name="b_tiny-test.csv")
    assert _fields(check_results(middle)) == [(middle.name, "line 3: row", "error")]


def test_single_final_newline_is_only_a_warning(tmp_path: Path):
    path = _csv(tmp_path, ROW, end="\n")
    assert len(read_results_csv(path)) == 1  # the BOP toolkit reads it too
    assert _fields(check_results(path)) == [(path.name, "line 2: row", "warning")]


def test_header_only_is_a_warning(tmp_path: Path):
    path = _csv(tmp_path)
    assert read_results_csv(path) == []
    assert _fields(check_results(path)) == [(path.name, "", "warning")]


def test_bad_rows_each_reported(tmp_path: Path):
    path = _csv(
        tmp_path,
        "0,1,2,0.5,1 0 0 0 1 0 0 0 1,100 -20 500",  # 6 columns
        "x,1,2,0.5,1 0 0 0 1 0 0 0 1,100 -20 500,0.25",  # scene_id not an integer
        "0,1,2,0.5,1 0 0 0 1 0 0 0 2,100 -20 500,0.25",  # R not orthonormal
        "0,1,2,0.5,1 0 0 0 1 0 0 0,100 -20 500,-3",  # R 8 numbers and bad time
    )
    assert _fields(check_results(path)) == [
        (path.name, "line 2: row", "error"), (path.name, "line 3: scene_id", "error"),
        (path.name, "line 4: R", "error"), (path.name, "line 5: R", "error"), (path.name, "line 5: time", "error"),
    ]


def test_duplicate_rows_warn(tmp_path: Path):
    path = _csv(tmp_path, ROW, ROW)
    probs = check_results(path)
    assert _fields(probs) == [(path.name, "line 3: row", "warning")] and "line 2" in probs[0].message


# ----------------------------------------------------------------------------- against a dataset


def _gt_estimates() -> list[PoseEstimate]:
    out = []
    for im_id, instances in GT.items():
        for obj_id, R, t_mm in instances:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t_mm / 1000
            out.append(PoseEstimate(0, im_id, obj_id, 1.0, T, 0.2 + im_id))
    return out


def test_ids_checked_against_the_dataset(tmp_path: Path):
    root = write_tiny_bop(tmp_path)
    path = tmp_path / "cosylite_tiny-test.csv"
    ests = _gt_estimates()
    write_results_csv(path, ests)
    assert check_results(path, root) == []
    ests[0].obj_id, ests[1].im_id, ests[2].scene_id = 7, 9, 5
    write_results_csv(path, ests)
    probs = check_results(path, root)
    assert _fields(probs) == [
        (path.name, "line 2: obj_id", "error"), (path.name, "line 3: im_id", "error"),
        (path.name, "line 4: scene_id", "error"),
    ]
    assert "models_info.json" in probs[0].message and "scene_camera.json" in probs[1].message


def _check_results_cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    command_check_results.add_arguments(parser)
    return command_check_results.run(parser.parse_args(argv))


def test_command_check_results(tmp_path: Path, capsys):
    root = write_tiny_bop(tmp_path)
    good = tmp_path / "cosylite_tiny-test.csv"
    write_results_csv(good, _gt_estimates())
    assert _check_results_cli([str(good), "--dataset", str(root)]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith("OK")
    bad = _csv(tmp_path, "0,0,1,0.5,1 0 0 0 1 0 0 0 1,0.1 -0.02 0.5,0.25", name="bad_tiny-test.csv")
    assert _check_results_cli([str(bad), "--dataset", str(root), "--split", "test"]) == 1
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith(f"ERROR {bad} [line 2: t]: t looks like metres")
    assert lines[-1].endswith("1 errors, 0 warnings")


def test_warnings_of_one_kind_are_one_line():
    from cosy_lite.bop.validate import Problem, summarised

    problems = [Problem("a.csv", f"line {n}: row", f"identical to line {n - 1}", "warning") for n in (3, 5, 9)]
    problems.insert(1, Problem("a.csv", "line 4: score", "not a number", "error"))
    lines = [str(p) for p in summarised(problems)]
    assert lines == ["WARNING a.csv [line 3: row]: identical to line 2 (and 2 more like it: line 5: row; line 9: row)",
                     "ERROR a.csv [line 4: score]: not a number"]
