"""Errors raised on bad input. Every message names the file, the field and what was expected."""

from __future__ import annotations

from pathlib import Path


class BopFormatError(ValueError):
    """A BOP file is missing, malformed or inconsistent.

    Args:
        path: the offending file (or folder).
        field: the JSON key / CSV column / image property that is wrong ("" if the whole file).
        problem: what is wrong and what was expected.
    """

    def __init__(self, path: str | Path, field: str, problem: str):
        self.path = str(path)
        self.field = field
        self.problem = problem
        where = f"{self.path}" + (f" [{field}]" if field else "")
        super().__init__(f"{where}: {problem}")
