"""Parameters of the BOP datasets: a lookup table, one row per dataset.

Values follow the BOP toolkit (``bop_toolkit_lib/dataset_params.py``) and the BOP Challenge 2020
paper. Depth ranges are in millimetres, as the toolkit states them (the BOP boundary).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class SplitParams:
    """One image split of a dataset (e.g. ``train_pbr`` or ``test_primesense``)."""

    im_size: tuple[int, int]  # (width, height) in pixels
    rgb_ext: str = ".png"  # extension of the colour images
    depth_ext: str = ".png"
    gray: bool = False  # grayscale images in gray/ instead of rgb/ (ITODD)


@dataclass(frozen=True)
class DatasetParams:
    """Static facts about one BOP dataset."""

    name: str
    obj_ids: tuple[int, ...]
    splits: dict[str, SplitParams]  # split folder name -> its parameters
    test_split: str  # folder of the BOP19 test split, e.g. "test" or "test_primesense"
    vsd_delta_mm: float = 15.0  # tolerance of the VSD visibility test
    depth_range_mm: tuple[float, float] | None = None  # of the test images
    azimuth_range: tuple[float, float] | None = None  # radians
    elev_range: tuple[float, float] | None = None  # radians
    symmetric_obj_ids: tuple[int, ...] = field(default=())  # evaluated with ADI (ADD-S)


_PBR_JPG = SplitParams((640, 480), rgb_ext=".jpg")
_VGA = SplitParams((640, 480))

DATASETS: dict[str, DatasetParams] = {
    p.name: p
    for p in [
        DatasetParams(
            "lm", tuple(range(1, 16)),
            {"train_pbr": _PBR_JPG, "test": _VGA}, "test",
            depth_range_mm=(600.90, 1102.35), azimuth_range=(0, 2 * math.pi),
            elev_range=(0, 0.5 * math.pi), symmetric_obj_ids=(3, 7, 10, 11),
        ),
        DatasetParams(
            "lmo", (1, 5, 6, 8, 9, 10, 11, 12),
            {"train_pbr": _PBR_JPG, "test": _VGA}, "test",
            depth_range_mm=(346.31, 1499.84), azimuth_range=(0, 2 * math.pi),
            elev_range=(0, 0.5 * math.pi), symmetric_obj_ids=(10, 11),
        ),
        DatasetParams(
            "tless", tuple(range(1, 31)),
            {
                "train_pbr": SplitParams((720, 540), rgb_ext=".jpg"),
                "train_primesense": SplitParams((400, 400)),
                "test_primesense": SplitParams((720, 540)),
            },
            "test_primesense",
            depth_range_mm=(649.89, 940.04), azimuth_range=(0, 2 * math.pi),
            elev_range=(-0.5 * math.pi, 0.5 * math.pi), symmetric_obj_ids=tuple(range(1, 31)),
        ),
        DatasetParams(
            "tudl", (1, 2, 3),
            {"train_pbr": _PBR_JPG, "train_real": _VGA, "test": _VGA}, "test",
            depth_range_mm=(851.29, 2016.14), azimuth_range=(0, 2 * math.pi),
            elev_range=(-0.4363, 0.5 * math.pi),
        ),
        DatasetParams(
            "icbin", (1, 2),
            {"train_pbr": _PBR_JPG, "test": _VGA}, "test",
            depth_range_mm=(454.56, 1076.29), azimuth_range=(0, 2 * math.pi),
            elev_range=(-1.0297, 0.5 * math.pi), symmetric_obj_ids=(1,),
        ),
        DatasetParams(
            "itodd", tuple(range(1, 29)),
            {
                "train_pbr": SplitParams((1280, 960), rgb_ext=".jpg"),
                "val": SplitParams((1280, 960), rgb_ext=".tif", depth_ext=".tif", gray=True),
                "test": SplitParams((1280, 960), rgb_ext=".tif", depth_ext=".tif", gray=True),
            },
            "test", vsd_delta_mm=5.0,
            symmetric_obj_ids=(2, 3, 4, 5, 7, 8, 9, 11, 12, 14, 17, 18, 19, 23, 24, 25, 27, 28),
        ),
        DatasetParams(
            "hb", tuple(range(1, 34)),
            {"train_pbr": _PBR_JPG, "val_primesense": _VGA, "test_primesense": _VGA},
            "test_primesense",
            depth_range_mm=(420.0, 1430.0), azimuth_range=(0, 2 * math.pi),
            elev_range=(0.1920, 1.5184), symmetric_obj_ids=(6, 10, 11, 12, 13, 14, 18, 24, 29),
        ),
        DatasetParams(
            "ycbv", tuple(range(1, 22)),
            {"train_pbr": _PBR_JPG, "train_real": _VGA, "train_synt": _VGA, "test": _VGA}, "test",
            depth_range_mm=(610.09, 1250.11), azimuth_range=(0, 2 * math.pi),
            elev_range=(-1.2872, 1.1294), symmetric_obj_ids=(1, 13, 14, 16, 18, 19, 20, 21),
        ),
        # The embedded synthetic datasets written by cosy_lite.synth (YCB-V ids, YCB-V camera).
        DatasetParams(
            "ycbvsynth", tuple(range(1, 22)), {"train_pbr": _PBR_JPG, "test": _VGA}, "test",
            depth_range_mm=(400.0, 1300.0), azimuth_range=(0, 2 * math.pi),
            elev_range=(0.35, 1.45),
        ),
        DatasetParams(
            "tiny", (1, 2, 5, 8), {"train_pbr": _PBR_JPG, "test": _VGA}, "test",
            depth_range_mm=(400.0, 1300.0), azimuth_range=(0, 2 * math.pi),
            elev_range=(0.35, 1.45),
        ),
    ]
}

BOP_CORE = ("lmo", "tless", "tudl", "icbin", "itodd", "hb", "ycbv")

# Old name -> new name. The BOP toolkit reads results files ``METHOD_DATASET-SPLIT[-SPLITTYPE].csv``
# by splitting on ``_`` and ``-``, so a dataset name must contain neither.
RENAMED_DATASETS: dict[str, str] = {"ycbv-synth": "ycbvsynth"}


def renamed_dataset_message(old: str, folder: object | None = None) -> str:
    """Why ``old`` is no longer a dataset name and what to use instead (``folder``: an old folder on disk)."""
    new = RENAMED_DATASETS[old]
    msg = (f"dataset {old!r} is now called {new!r} (the BOP toolkit splits results file names "
           f"METHOD_DATASET-SPLIT.csv on '_' and '-', so it cannot score results of {old!r})")
    if folder is not None:
        msg += f"; rename the folder: mv {folder} {Path(str(folder)).with_name(new)}"
    return msg


def current_dataset_name(name: str, folder: object | None = None, warn: bool = True) -> str:
    """``name``, or its new name (with a warning naming ``folder``, if ``warn``) if it is an old one of
    :data:`RENAMED_DATASETS`."""
    if name not in RENAMED_DATASETS:
        return name
    if warn:
        warnings.warn(renamed_dataset_message(name, folder) + f"; read as {RENAMED_DATASETS[name]!r}", stacklevel=3)
    return RENAMED_DATASETS[name]


def dataset_name_of(root: str | Path, name: str | None = None, warn: bool = True) -> str:
    """The dataset name of folder ``root``: ``name`` if given, else the folder name (old names mapped to new ones)."""
    return current_dataset_name(name or Path(root).name, None if name else root, warn)


def get_dataset_params(name: str) -> DatasetParams:
    """Look up a dataset by name; a clear error lists the known names."""
    try:
        return DATASETS[name]
    except KeyError:
        if name in RENAMED_DATASETS:
            raise KeyError(renamed_dataset_message(name)) from None
        raise KeyError(f"unknown BOP dataset {name!r}; known: {sorted(DATASETS)}") from None
