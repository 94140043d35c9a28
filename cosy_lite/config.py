"""Typed configuration: dataclasses hold the defaults, YAML files in ``configs/`` hold only the
differences, and ``key=value`` command-line overrides come last (merged with OmegaConf)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, TypeVar

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

T = TypeVar("T")


def load_config(cls: type[T], yaml_path: str | Path | None = None, overrides: list[str] | None = None) -> T:
    """Build a ``cls`` instance: dataclass defaults <- YAML file <- ``["a.b=1", ...]`` overrides.

    Unknown keys and wrongly typed values raise a ValueError naming the file and the key.
    """
    cfg = OmegaConf.structured(cls)
    where = "defaults"
    try:
        if yaml_path is not None:
            where = str(yaml_path)
            if not Path(yaml_path).is_file():
                raise ValueError(f"{yaml_path}: config file not found")
            cfg = OmegaConf.merge(cfg, OmegaConf.load(yaml_path))
        if overrides:
            where = f"command-line overrides {overrides}"
            cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(list(overrides)))
    except OmegaConfBaseException as e:
        raise ValueError(f"{where}: {e}".split("\n    full_key")[0]) from None
    return OmegaConf.to_object(cfg)  # type: ignore[return-value]


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """Plain dict of a config dataclass (for checkpoints and logs)."""
    return dataclasses.asdict(cfg)


def save_config(cfg: Any, path: str | Path) -> None:
    Path(path).write_text(OmegaConf.to_yaml(OmegaConf.structured(cfg)))
