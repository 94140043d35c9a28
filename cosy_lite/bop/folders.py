"""Where a dataset lives: the one resolver of ``--dataset`` values, for every command.

A folder is taken as given (also a path that does not exist yet, so errors name it); a bare name is
``DATA_ROOT/NAME``, ``DATA_ROOT`` being ``$COSY_LITE_DATA`` (read when asked, default ``data``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from cosy_lite.bop.params import RENAMED_DATASETS, renamed_dataset_message
from cosy_lite.errors import BopFormatError


def default_data_root() -> Path:
    return Path(os.environ.get("COSY_LITE_DATA", "data"))


def default_cache_dir() -> Path:
    """Where rendered templates, scorer observations and generated meshes are kept between runs:
    ``$COSY_LITE_CACHE``, default ``~/.cache/cosy_lite``."""
    return Path(os.environ.get("COSY_LITE_CACHE") or Path.home() / ".cache" / "cosy_lite")


def where_datasets_are() -> str:
    """How a dataset name becomes a folder, for "not found" errors."""
    return (f"a dataset NAME is the folder $COSY_LITE_DATA/NAME (COSY_LITE_DATA now: {default_data_root()}); "
            "set COSY_LITE_DATA or --data-root DIR, or give the dataset folder's path")


def dataset_folder(dataset: str | Path, data_root: Path | None = None) -> Path:
    """The folder of a ``--dataset`` value: a folder (or a path) as given, else ``DATA_ROOT/NAME``.

    An old name of :data:`~cosy_lite.bop.params.RENAMED_DATASETS` (e.g. ``ycbv-synth``) gives its new
    name's folder when that exists; else its old folder when that exists (read under the new name,
    with a warning to rename it); else a BopFormatError naming the new name.
    """
    given = Path(dataset)
    if given.is_dir() or len(given.parts) > 1:
        return given
    name = str(dataset)
    root = (data_root or default_data_root()) / name
    if name not in RENAMED_DATASETS:
        return root
    new_root = root.with_name(RENAMED_DATASETS[name])
    if new_root.is_dir():
        print(f"note: {renamed_dataset_message(name)}: using {new_root}", file=sys.stderr)
        return new_root
    if root.is_dir():
        return root  # BopDataset warns and reads it under the new name
    raise BopFormatError(root, "--dataset", renamed_dataset_message(name) + f": use --dataset {RENAMED_DATASETS[name]}")
