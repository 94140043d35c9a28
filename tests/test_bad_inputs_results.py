"""Results CSVs as users hand them in: a UTF-8 byte-order mark (the BOP toolkit reads it) is accepted
with a warning by check-results and scored by eval; broken files are one error naming the line and
column, exit 1, never a traceback."""

from __future__ import annotations

import codecs
import json
from pathlib import Path

import numpy as np
import pytest
from bop_fixtures import GT, write_tiny_bop

from cosy_lite.bop.results import HEADER, PoseEstimate, read_results_csv, write_results_csv
from cosy_lite.cli import main

ROW = "0,0,1,0.5,1.0 0.0 0.0 0.0 1.0 0.0 0.0 0.0 1.0,100.0 -20.0 500.0,0.25"


@pytest.fixture
def root(tmp_path: Path) -> Path:
    return write_tiny_bop(tmp_path)


def _gt_text(root: Path) -> str:
    ests = []
    for im_id, insts in GT.items():
        for obj_id, R, t in insts:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t / 1000.0
            ests.append(PoseEstimate(0, im_id, obj_id, 0.9, T, 0.1))
    tmp = root.parent / "gt_tiny-test.csv"
    write_results_csv(tmp, ests)
    return tmp.read_text()


def _cli(capsys, *argv: str) -> tuple[int, str]:
    rc = main(list(argv))
    captured = capsys.readouterr()
    return rc, captured.out + captured.err


@pytest.mark.parametrize("newline", ["\n", "\r\n"], ids=["lf", "crlf"])
def test_bom_is_accepted_with_a_warning_and_scored(root: Path, capsys, newline: str):
    csv = root.parent / "bom_tiny-test.csv"
    csv.write_bytes(codecs.BOM_UTF8 + _gt_text(root).replace("\n", newline).encode())
    assert [e.obj_id for e in read_results_csv(csv)] == [1, 2, 1, 1, 2]
    rc, text = _cli(capsys, "check-results", str(csv), "--dataset", str(root))
    assert rc == 0 and f"WARNING {csv} [line 1: header]: starts with a UTF-8 byte-order mark" in text, text
    rc, text = _cli(capsys, "eval", "--dataset", str(root), "--results", str(csv), "--out", str(root.parent / "ev"),
                    "--no-progress")
    assert rc == 0, text
    assert json.loads((root.parent / "ev" / "scores.json").read_text())["ar"] == 1.0


def test_header_with_trailing_whitespace_is_read_as_the_toolkit_does(root: Path, capsys):
    text = _gt_text(root)
    csv = root.parent / "ws_tiny-test.csv"
    csv.write_text(text.replace(HEADER, HEADER + " \t", 1))  # the toolkit: line 1 is the header if it contains it
    assert [e.obj_id for e in read_results_csv(csv)] == [1, 2, 1, 1, 2]
    rc, out = _cli(capsys, "check-results", str(csv), "--dataset", str(root))
    assert rc == 0, out
    inner = root.parent / "sp_tiny-test.csv"
    inner.write_text(text.replace(HEADER, HEADER.replace(",", ", "), 1))  # not contained: the toolkit fails too
    rc, out = _cli(capsys, "check-results", str(inner), "--dataset", str(root))
    assert rc == 1 and "line 1: header" in out


# (file bytes, field of the first error, words)
BROKEN = {
    "bom-then-bad-header": (codecs.BOM_UTF8 + b"scene,im,obj\n" + ROW.encode(), "line 1: header", "expected exactly"),
    "utf-16": (("\n".join([HEADER, ROW])).encode("utf-16"), "", "not a UTF-8 text file"),
    "binary": (bytes(range(256)), "", "not a UTF-8 text file"),
    "empty": (b"", "line 1: header", "empty file"),
    "two-numbers-for-t": (f"{HEADER}\n0,0,1,0.5,1 0 0 0 1 0 0 0 1,100 -20,0.25".encode(), "line 2: t",
                          "expected 3 numbers"),
    "commas-inside-R": (f"{HEADER}\n0,0,1,0.5,1,0,0,0,1,0,0,0,1,100 -20 500,0.25".encode(), "line 2: row",
                        "expected 7 comma-separated columns"),
    "negative-im-id": (f"{HEADER}\n0,-1,1,0.5,1 0 0 0 1 0 0 0 1,100 -20 500,0.25".encode(), "line 2: im_id",
                       "non-negative integer"),
    "float-obj-id": (f"{HEADER}\n0,0,1.0,0.5,1 0 0 0 1 0 0 0 1,100 -20 500,0.25".encode(), "line 2: obj_id",
                     "non-negative integer"),
    "inf-score": (f"{HEADER}\n0,0,1,inf,1 0 0 0 1 0 0 0 1,100 -20 500,0.25".encode(), "line 2: score", "NaN or inf"),
    "scaled-rotation": (f"{HEADER}\n0,0,1,0.5,2 0 0 0 2 0 0 0 2,100 -20 500,0.25".encode(), "line 2: R",
                        "not a rotation matrix"),
    "negative-time": (f"{HEADER}\n0,0,1,0.5,1 0 0 0 1 0 0 0 1,100 -20 500,-3".encode(), "line 2: time",
                      "seconds >= 0 or -1"),
}


@pytest.mark.parametrize("name", list(BROKEN))
def test_broken_results_file_names_line_and_column(root: Path, capsys, name: str):
    data, fld, words = BROKEN[name]
    csv = root.parent / "bad_tiny-test.csv"
    csv.write_bytes(data)
    where = f"{csv}" + (f" [{fld}]" if fld else "")
    for argv in (["check-results", str(csv), "--dataset", str(root)],
                 ["eval", "--dataset", str(root), "--results", str(csv), "--no-progress"]):
        rc, text = _cli(capsys, *argv)
        assert rc == 1 and "Traceback" not in text, text
        line = next((s for s in text.splitlines() if s.startswith(f"ERROR {where}: ")), None)
        assert line is not None and words in line, text
    assert not (root.parent / "bad_tiny-test_eval").exists() and not Path("outputs/eval/bad_tiny-test").exists()


def test_results_for_another_dataset_are_refused_by_eval(root: Path, capsys):
    csv = root.parent / "gt_ycbv-test.csv"
    csv.write_text(_gt_text(root))
    rc, text = _cli(capsys, "eval", "--dataset", str(root), "--results", str(csv), "--name", "tiny", "--no-progress")
    assert rc == 1 and f"ERROR {csv} [file name]: results for dataset 'ycbv', expected 'tiny'" in text, text


def test_results_file_that_is_a_folder(root: Path, capsys):
    folder = root.parent / "dir_tiny-test.csv"
    folder.mkdir()
    rc, text = _cli(capsys, "check-results", str(folder))
    assert rc == 1 and f"ERROR {folder}: results file not found" in text
