"""BOP19 results CSV: ``METHOD_DATASET-SPLIT.csv`` with one pose estimate per line.

File names are read as the BOP toolkit reads them (split on ``_`` and ``-``), so no part may
contain the separators of another.

This is the BOP boundary: poses are in metres inside the library and in millimetres in the
file. Format as written and read by the BOP toolkit (``inout.save_bop_results`` /
``load_bop_results``)::

    scene_id,im_id,obj_id,score,R,t,time
    48,1,2,0.9,r11 r12 r13 r21 r22 r23 r31 r32 r33,tx ty tz,0.25

R is row-major, t in mm, time in seconds (-1 = unknown) and the same for every estimate of one
image. Lines are joined with ``\\n`` and there is no newline after the last one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator, NamedTuple

import numpy as np

from cosy_lite.bop.io import MIN_PLAUSIBLE_T_MM, atomic_write_text
from cosy_lite.bop.params import DATASETS
from cosy_lite.errors import BopFormatError

COLUMNS = ("scene_id", "im_id", "obj_id", "score", "R", "t", "time")
HEADER = ",".join(COLUMNS)
ROTATION_TOL = 1e-3  # max |R R^T - I| accepted as a rotation (as io._check_rotation)
TIME_TOL = 1e-3  # seconds; the BOP toolkit's tolerance for "same time per image"
UNKNOWN_TIME = -1.0  # BOP: run time not measured


@dataclass
class PoseEstimate:
    """One line of a results file, in metres and seconds."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    TCO: np.ndarray  # [4,4] object-to-camera [m]
    time: float = UNKNOWN_TIME  # seconds for the whole image; -1 = unknown


class ResultRow(NamedTuple):
    """What :func:`parse_results_csv` yields: a parsed estimate (or None) and the problems found."""

    line: int  # 1-based line number in the file (the header is line 1)
    estimate: PoseEstimate | None
    problems: list[BopFormatError]


# ----------------------------------------------------------------------------- file names


def results_filename(method: str, dataset: str, split: str) -> str:
    """``METHOD_DATASET-SPLIT.csv``. ValueError if a part is empty or contains ``_`` (BOP rule), or the
    dataset contains ``-`` (the toolkit would read its first part as the dataset)."""
    for what, value in (("method", method), ("dataset", dataset), ("split", split)):
        if not value or "_" in value or "/" in value or "." in value or (what == "dataset" and "-" in value):
            raise ValueError(
                f"{what} {value!r}: must be non-empty without '_', '/' or '.'"
                + (" or '-'" if what == "dataset" else "")
                + " (BOP results are named METHOD_DATASET-SPLIT.csv; write e.g. train_pbr as train-pbr)"
            )
    return f"{method}_{dataset}-{split}.csv"


class ToolkitFileName(NamedTuple):
    """A results file name as bop_toolkit ``inout.parse_result_filename`` reads it."""

    result_name: str
    method: str
    dataset: str
    split: str
    split_type: str | None
    ext: str


def toolkit_parse_results_filename(path: str | Path) -> ToolkitFileName:
    """Read a results file name with the BOP toolkit's rule, nothing more.

    The base name is split on ``.``: the first part is the result name, the rest the extension.
    The result name is split on ``_``: part 0 is the method, part 1 is split on ``-`` into dataset,
    split and (if present) split type; further ``_`` parts (an optional id) and ``-`` parts are
    ignored. Raises BopFormatError (field ``file name``) where the toolkit fails (a part missing).
    """
    path = Path(path)
    result_name, _, ext = path.name.partition(".")
    info = result_name.split("_")
    dataset_info = info[1].split("-") if len(info) > 1 else []
    if len(dataset_info) < 2:
        raise BopFormatError(path, "file name", (
            f"{path.name!r}: the BOP toolkit cannot read it (it needs METHOD_DATASET-SPLIT[-SPLITTYPE].csv)"))
    split_type = dataset_info[2] if len(dataset_info) > 2 else None
    return ToolkitFileName(result_name, info[0], dataset_info[0], dataset_info[1], split_type, ext)


def parse_results_filename(path: str | Path) -> tuple[str, str, str]:
    """``.../METHOD_DATASET-SPLIT[-SPLITTYPE].csv`` -> (method, dataset, split), as the BOP toolkit reads it.

    ``split`` is ``SPLIT-SPLITTYPE`` when there is a split type (e.g. ``test-primesense``). Stricter
    than the toolkit: exactly one ``_``, no ``.`` before ``.csv``, at most three ``-`` parts and none
    empty (what the toolkit would ignore or misread). Raises BopFormatError (field ``file name``).
    """
    path = Path(path)
    expected = "expected METHOD_DATASET-SPLIT.csv with no '_' in METHOD and no '-' in DATASET (e.g. cosylite_ycbv-test.csv)"
    if path.suffix != ".csv":
        raise BopFormatError(path, "file name", f"{path.name!r} does not end with .csv; {expected}")
    if "." in path.stem:
        raise BopFormatError(path, "file name", f"{path.name!r}: the BOP toolkit ends the name at the first '.'; {expected}")
    parts = path.stem.split("_")
    if len(parts) != 2 or not all(parts):
        try:
            t = toolkit_parse_results_filename(path)
            reading = (f"the BOP toolkit would read method {t.method!r}, dataset {t.dataset!r}, split {t.split!r}"
                       + (f", split type {t.split_type!r}" if t.split_type else ""))
        except BopFormatError:
            reading = "the BOP toolkit cannot read it"
        raise BopFormatError(path, "file name", f"{path.name!r} needs exactly one '_' ({reading}); {expected}")
    dataset_info = parts[1].split("-")
    if len(dataset_info) < 2 or not all(dataset_info):
        raise BopFormatError(path, "file name", f"{path.name!r} has no DATASET-SPLIT part; {expected}")
    if len(dataset_info) > 3:
        raise BopFormatError(path, "file name", (
            f"{path.name!r}: the BOP toolkit reads only DATASET-SPLIT-SPLITTYPE and would ignore "
            f"{'-'.join(dataset_info[3:])!r}; {expected}"))
    name = toolkit_parse_results_filename(path)
    return name.method, name.dataset, "-".join(dataset_info[1:])


def misread_dataset(path: str | Path, names: Iterable[str] = ()) -> str | None:
    """Why the toolkit would misread the dataset of a results file name (None: it reads it right).

    That is the case when ``DATASET-SPLIT`` starts with a dataset name containing ``-``: an old
    name of :data:`~cosy_lite.bop.params.RENAMED_DATASETS`, a row of the table, or one of ``names``
    (e.g. the dataset folder's name).
    """
    from cosy_lite.bop.params import RENAMED_DATASETS

    path = Path(path)
    rest = path.stem.partition("_")[2]
    for name in sorted({*RENAMED_DATASETS, *DATASETS, *names}, key=len, reverse=True):
        if "-" in name and rest.startswith(name + "-"):
            t = toolkit_parse_results_filename(path)
            fix = RENAMED_DATASETS.get(name, name.replace("-", ""))
            return (f"{path.name!r} is for dataset {name!r}, but the BOP toolkit splits the name on '_' and '-' and "
                    f"reads dataset {t.dataset!r}, split {t.split!r}, split type {t.split_type!r}; "
                    f"name it {t.method}_{fix}-{rest[len(name) + 1:]}.csv (dataset {fix!r})")
    return None


# ----------------------------------------------------------------------------- writing


def _fmt(v: float) -> str:
    return repr(float(v))  # shortest string that reads back to the same double


def rotation_problem(R: np.ndarray, tol: float = ROTATION_TOL) -> str | None:
    """Why the [3,3] matrix R is not a rotation, or None if it is one (orthonormal, det +1)."""
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if err > tol or abs(det - 1.0) > tol:
        return f"not a rotation matrix (|R R^T - I| = {err:.2g}, det = {det:.4f}; expected orthonormal, det +1)"
    return None


def _estimate_problem(e: PoseEstimate) -> str | None:
    TCO = np.asarray(e.TCO, dtype=np.float64)
    if TCO.shape != (4, 4):
        return f"TCO must be [4,4], got {list(TCO.shape)}"
    if not np.all(np.isfinite(TCO)):
        return "TCO contains NaN or inf"
    if not math.isfinite(e.score):
        return f"score must be finite, got {e.score}"
    if not math.isfinite(e.time) or (e.time < 0 and e.time != UNKNOWN_TIME):
        return f"time must be >= 0 s or -1 (unknown), got {e.time}"
    if (msg := rotation_problem(TCO[:3, :3])) is not None:
        return f"TCO[:3,:3] {msg}"
    if np.linalg.norm(TCO[:3, 3]) * 1000.0 < MIN_PLAUSIBLE_T_MM:
        return f"t = {TCO[:3, 3].tolist()} m is closer than {MIN_PLAUSIBLE_T_MM} mm to the camera (TCO must be in metres)"
    for name in ("scene_id", "im_id", "obj_id"):
        v = getattr(e, name)
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 0:
            return f"{name} must be a non-negative integer, got {v!r}"
    return None


def format_estimate(e: PoseEstimate) -> str:
    """One CSV line (no newline): R row-major, t in mm, full float precision."""
    TCO = np.asarray(e.TCO, dtype=np.float64)
    R = " ".join(_fmt(v) for v in TCO[:3, :3].reshape(-1))
    t = " ".join(_fmt(v * 1000.0) for v in TCO[:3, 3])
    return f"{int(e.scene_id)},{int(e.im_id)},{int(e.obj_id)},{_fmt(e.score)},{R},{t},{_fmt(e.time)}"


def estimate_to_json(e: PoseEstimate) -> dict:
    """One estimate as JSON-ready numbers at the BOP boundary: ``obj_id``, ``score``, ``R`` [3][3]
    (row-major rows), ``t`` [3] in mm, ``time`` (s), and ``bop19_csv_row`` (its line of a results file)."""
    TCO = np.asarray(e.TCO, dtype=np.float64)
    return {"obj_id": int(e.obj_id), "score": float(e.score), "R": TCO[:3, :3].tolist(),
            "t": [float(v * 1000.0) for v in TCO[:3, 3]], "time": float(e.time), "bop19_csv_row": format_estimate(e)}


def write_results_csv(path: str | Path, estimates: Iterable[PoseEstimate]) -> None:
    """Write a BOP19 results file atomically (TCO in metres -> t in mm).

    Raises ValueError naming scene/im/obj for a NaN/inf pose or score, a non-rotation R, a
    translation closer than 20 mm (TCO not in metres), or estimates of one image with different
    ``time`` values (more than 1 ms apart).
    """
    lines = [HEADER]
    times: dict[tuple[int, int], float] = {}
    for e in estimates:
        where = f"{path}: scene_id {e.scene_id}, im_id {e.im_id}, obj_id {e.obj_id}"
        if (msg := _estimate_problem(e)) is not None:
            raise ValueError(f"{where}: {msg}")
        key = (int(e.scene_id), int(e.im_id))
        t0 = times.setdefault(key, float(e.time))
        if abs(t0 - e.time) > TIME_TOL:
            raise ValueError(f"{where}: time {e.time} differs from {t0} of another estimate of the same image "
                             "(BOP: one time per image, the same on all its lines)")
        lines.append(format_estimate(e))
    atomic_write_text(path, "\n".join(lines))


# ----------------------------------------------------------------------------- reading


def _parse_int(path: Path, fld: str, cell: str, problems: list[BopFormatError]) -> int | None:
    try:
        v = int(cell.strip())
    except ValueError:
        problems.append(BopFormatError(path, fld, f"expected a non-negative integer, got {cell!r}"))
        return None
    if v < 0:
        problems.append(BopFormatError(path, fld, f"expected a non-negative integer, got {v}"))
        return None
    return v


def _parse_floats(path: Path, fld: str, cell: str, n: int, problems: list[BopFormatError]) -> np.ndarray | None:
    try:
        arr = np.array([float(s) for s in cell.split()], dtype=np.float64)
    except ValueError:
        problems.append(BopFormatError(path, fld, f"expected {n} numbers separated by spaces, got {cell!r}"))
        return None
    if arr.size != n:
        problems.append(BopFormatError(path, fld, f"expected {n} numbers separated by spaces, got {arr.size}"))
        return None
    if not np.all(np.isfinite(arr)):
        problems.append(BopFormatError(path, fld, f"contains NaN or inf: {cell.strip()!r}"))
        return None
    return arr


def _parse_row(path: Path, n: int, cells: list[str], order: tuple[str, ...]) -> ResultRow:
    c = dict(zip(order, cells))
    problems: list[BopFormatError] = []
    ids = {k: _parse_int(path, f"line {n}: {k}", c[k], problems) for k in ("scene_id", "im_id", "obj_id")}
    score = _parse_floats(path, f"line {n}: score", c["score"], 1, problems)
    R = _parse_floats(path, f"line {n}: R", c["R"], 9, problems)
    if R is not None and (msg := rotation_problem(R.reshape(3, 3))) is not None:
        problems.append(BopFormatError(path, f"line {n}: R", msg))
        R = None
    t = _parse_floats(path, f"line {n}: t", c["t"], 3, problems)
    if t is not None and np.linalg.norm(t) < MIN_PLAUSIBLE_T_MM:
        problems.append(BopFormatError(
            path, f"line {n}: t",
            f"t looks like metres, BOP expects mm: {c['t'].strip()!r} is closer than {MIN_PLAUSIBLE_T_MM} mm",
        ))
        t = None
    time = _parse_floats(path, f"line {n}: time", c["time"], 1, problems)
    if time is not None and time[0] < 0 and time[0] != UNKNOWN_TIME:
        problems.append(BopFormatError(path, f"line {n}: time", f"expected seconds >= 0 or -1 (unknown), got {time[0]}"))
    if problems:
        return ResultRow(n, None, problems)
    # every parser that returned None (and every value set to None above) added a problem
    scene_id, im_id, obj_id = ids["scene_id"], ids["im_id"], ids["obj_id"]
    assert scene_id is not None and im_id is not None and obj_id is not None
    assert score is not None and R is not None and t is not None and time is not None
    TCO = np.eye(4)
    TCO[:3, :3] = R.reshape(3, 3)
    TCO[:3, 3] = t / 1000.0
    return ResultRow(n, PoseEstimate(scene_id, im_id, obj_id, float(score[0]), TCO, float(time[0])), [])


def _header_order(path: Path, line: str) -> tuple[tuple[str, ...] | None, list[BopFormatError]]:
    """Column order to parse the data rows with (None: line 1 is data) and the header problems."""
    cells = tuple(s.strip() for s in line.split(","))
    if line.strip() == HEADER:  # the toolkit takes line 1 as the header when it contains HEADER
        return COLUMNS, []
    if cells == COLUMNS:
        return COLUMNS, [BopFormatError(path, "line 1: header", f"got {line!r}, expected exactly {HEADER!r} (no spaces)")]
    if sorted(cells) == sorted(COLUMNS):
        return cells, [BopFormatError(path, "line 1: header", f"columns in the wrong order: {line!r}, expected {HEADER!r}")]
    if cells and cells[0].lstrip("-").isdigit():
        return None, [BopFormatError(path, "line 1: header", f"missing header line, expected {HEADER!r}")]
    return COLUMNS, [BopFormatError(path, "line 1: header", f"got {line!r}, expected exactly {HEADER!r}")]


def parse_results_csv(path: str | Path) -> Iterator[ResultRow]:
    """Check a results file line by line, collecting every problem instead of stopping.

    Yields one :class:`ResultRow` per line (estimate None where the line has problems), then one
    row per image whose lines disagree on ``time``. A single newline after the last line and a
    UTF-8 byte-order mark are tolerated here (the toolkit reads both); empty lines anywhere are
    errors. Missing file or undecodable text raise BopFormatError.
    """
    path = Path(path)
    if not path.is_file():
        raise BopFormatError(path, "", "results file not found")
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark is skipped, as the toolkit does
    except UnicodeDecodeError as e:
        raise BopFormatError(path, "", f"not a UTF-8 text file: {e}") from None
    lines = [s.removesuffix("\r") for s in text.split("\n")]
    if text.endswith("\n"):
        lines.pop()  # the terminator of the last line, not an empty line
    if not text.strip():
        yield ResultRow(1, None, [BopFormatError(path, "line 1: header", f"empty file, expected {HEADER!r}")])
        return
    order, header_problems = _header_order(path, lines[0])
    if header_problems:
        yield ResultRow(1, None, header_problems)
    first = 1 if order is not None else 0
    order = order or COLUMNS
    times: dict[tuple[int, int], tuple[float, int]] = {}
    late: list[ResultRow] = []
    for i in range(first, len(lines)):
        n, line = i + 1, lines[i]
        if not line.strip():
            where = "after the last line" if all(not s.strip() for s in lines[i:]) else "between lines"
            yield ResultRow(n, None, [BopFormatError(path, f"line {n}: row", f"empty line {where}; BOP files have none")])
            continue
        cells = line.split(",")
        if len(cells) != len(COLUMNS):
            yield ResultRow(n, None, [BopFormatError(
                path, f"line {n}: row", f"expected {len(COLUMNS)} comma-separated columns ({HEADER}), got {len(cells)}")])
            continue
        row = _parse_row(path, n, cells, order)
        if (est := row.estimate) is not None:
            t0, n0 = times.setdefault((est.scene_id, est.im_id), (est.time, n))
            if abs(est.time - t0) > TIME_TOL:
                late.append(ResultRow(n, None, [BopFormatError(
                    path, f"line {n}: time",
                    f"scene {est.scene_id} image {est.im_id}: time {est.time} differs from {t0} on line {n0}; "
                    "BOP expects the same time on every line of an image")]))
        yield row
    yield from late


def read_results_csv(path: str | Path) -> list[PoseEstimate]:
    """Read a results file (t mm -> m); the first problem raises BopFormatError naming the line and column."""
    out = []
    for row in parse_results_csv(path):
        if row.problems:
            raise row.problems[0]
        assert row.estimate is not None  # parse_results_csv yields no estimate only with problems
        out.append(row.estimate)
    return out
