"""``cosy-lite eval``'s input checks and figure beside the evaluation: in a forked process where that
is safe, in this one otherwise, with the same results and errors either way."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import pytest

from cosy_lite.bop.validate import Problem
from cosy_lite.eval import evaluator
from cosy_lite.eval.checks_and_figure import ChecksAndFigure


def _checks() -> list[Problem]:
    return [Problem("results.csv", "line 2", f"checked in process {os.getpid()}", severity="warning")]


def _plot(result, png: Path) -> None:
    png.write_text(f"{result.dataset} {len(result.targets)} targets, drawn in process {os.getpid()}")


def _failing_checks() -> list[Problem]:
    raise OSError("results.csv: permission denied")


@dataclasses.dataclass
class Result:  # what draw() is given: a dataclass whose per-target errors it leaves behind
    dataset: str
    targets: list


@pytest.mark.parametrize("forked", [True, False])
def test_checks_and_figure_where_forking_is_safe_or_not(tmp_path: Path, monkeypatch, forked: bool):
    monkeypatch.setattr(evaluator, "fork_is_safe", lambda: forked)
    side = ChecksAndFigure(_checks, lambda: None, _plot)
    (p,) = side.problems()
    assert p.severity == "warning" and p.field == "line 2"
    assert (p.message != f"checked in process {os.getpid()}") == forked
    png = tmp_path / "curves.png"
    side.draw(Result("ycbvsynth", [1, 2, 3]), png)  # returns once the file is written
    drawn = png.read_text()
    # forked: drawn in the other process, without the per-target errors (not drawn: not sent)
    assert drawn.startswith("ycbvsynth 0 targets" if forked else "ycbvsynth 3 targets")
    assert drawn.endswith(f"process {os.getpid()}") != forked
    side.close()


def test_checks_that_raise_are_reported_where_they_ran(monkeypatch):
    monkeypatch.setattr(evaluator, "fork_is_safe", lambda: True)
    side = ChecksAndFigure(_failing_checks, lambda: None, _plot)
    with pytest.raises(RuntimeError, match="OSError: results.csv: permission denied"):
        side.problems()
    side.close()
    monkeypatch.setattr(evaluator, "fork_is_safe", lambda: False)
    with pytest.raises(OSError, match="permission denied"):
        ChecksAndFigure(_failing_checks, lambda: None, _plot)


def test_the_forked_process_ends_when_no_figure_is_wanted(monkeypatch):
    monkeypatch.setattr(evaluator, "fork_is_safe", lambda: True)
    side = ChecksAndFigure(_checks, lambda: None, _plot)
    side.problems()
    proc = side._proc
    side.close()  # (bad input: nothing to draw)
    assert proc is not None and proc.exitcode == 0
