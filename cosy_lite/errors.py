"""Errors raised on bad input, and how the entry points report them.

Every expected error (bad file, bad config, bad argument) is a :class:`CosyLiteError` whose message
names the file, the field and what was expected. The entry points (``cosy-lite``, ``train.py``,
``infer.py``) run through :func:`run_reporting_errors`: such an error becomes one line on stderr
and exit status :data:`EXIT_BAD_INPUT`; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Callable

EXIT_BAD_INPUT = 2  # as argparse for a bad command line
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports Ctrl-C


class CosyLiteError(ValueError):
    """An expected error: the user's input cannot be used; the message says which file/field and why."""


class BopFormatError(CosyLiteError):
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

    def __reduce__(self):  # picklable with its three arguments (errors cross process pools)
        return type(self), (self.path, self.field, self.problem)


class ConfigError(CosyLiteError):
    """A config that cannot be used: unknown key, wrong type, bad value, unreadable YAML.

    Args:
        where: the YAML file or ``command-line override 'a.b=c'`` the bad value came from.
        field: the dotted key (``loop.steps``), "" for the whole file.
        problem: what is wrong and what was expected.
    """

    def __init__(self, where: str | Path, field: str, problem: str):
        self.where, self.field, self.problem = str(where), field, problem
        super().__init__(f"{self.where}" + (f" [{field}]" if field else "") + f": {problem}")

    def __reduce__(self):
        return type(self), (self.where, self.field, self.problem)


class FieldValueError(ValueError):
    """A config dataclass's own check (``__post_init__``) failing on one field; :func:`cosy_lite.config.load_config`
    reports it as a ConfigError naming the sources and this field."""

    def __init__(self, field: str, problem: str):
        self.field, self.problem = field, problem
        super().__init__(f"{field}: {problem}")


def describe_os_error(e: OSError) -> str:
    """``PATH: reason`` for an OSError about a file (permission denied, disk full, not a folder ...)."""
    names = [str(n) for n in (e.filename, e.filename2) if n is not None]
    reason = e.strerror or str(e)
    return f"{' -> '.join(names)}: {reason}" if names else reason


def _subclass_names(cls: type) -> set[str]:
    subclasses: list[type] = cls.__subclasses__()
    return {cls.__name__}.union(*(_subclass_names(c) for c in subclasses))


def worker_error_message(e: BaseException) -> str | None:
    """The message of an expected error raised in a torch DataLoader worker, or None.

    torch re-raises a worker's exception in the main process as a RuntimeError ``Caught NAME in
    DataLoader worker process K. Original Traceback ...`` whose last line is ``module.NAME: msg``.
    """
    text = str(e)
    found = re.match(r"Caught (\w+) in DataLoader worker process \d+", text)
    if not isinstance(e, RuntimeError) or found is None:
        return None
    if found.group(1) not in _subclass_names(CosyLiteError) | _subclass_names(OSError):
        return None
    last = text.rstrip().splitlines()[-1]
    return last.split(": ", 1)[1] if ": " in last else last


def run_reporting_errors(main: Callable[[], int], prog: str) -> int:
    """Run an entry point: expected errors -> ``PROG: error: MESSAGE`` on stderr, exit status 2.

    Expected: :class:`CosyLiteError` (files, configs, arguments) and OSError (the file system
    refused: missing file, permission, disk full), also when raised in a DataLoader worker.
    Ctrl-C exits with 130 and one line. Anything else propagates with its traceback (a bug).
    """
    try:
        return int(main() or 0)
    except CosyLiteError as e:
        print(f"{prog}: error: {' '.join(str(e).splitlines())}", file=sys.stderr)
    except OSError as e:
        print(f"{prog}: error: {describe_os_error(e)}", file=sys.stderr)
    except RuntimeError as e:
        if (msg := worker_error_message(e)) is None:
            raise
        print(f"{prog}: error: {msg} (in a data loading worker)", file=sys.stderr)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_BAD_INPUT
