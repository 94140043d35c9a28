"""Typed configuration: dataclasses hold the defaults, YAML files in the top-level ``configs/`` (shipped in
the package: :func:`packaged_config`) hold only the differences, and ``key=value`` command-line
overrides come last (merged with OmegaConf)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar, overload

import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from cosy_lite.errors import ConfigError, FieldValueError

T = TypeVar("T")


def packaged_config(*parts: str) -> Path:
    """A YAML file of the config profiles, e.g. ``packaged_config("synth", "tiny.yaml")`` or
    ``packaged_config("refiner", "demo.yaml")``: in an installed package its data ``cosy_lite/configs/``
    (found with importlib.resources), in a source checkout the top-level ``configs/`` that data is
    installed from (pyproject.toml maps it). The file may not exist: callers check."""
    from importlib.resources import files

    installed = Path(str(files("cosy_lite").joinpath("configs")))
    root = installed if installed.is_dir() else Path(__file__).resolve().parents[1] / "configs"
    return root.joinpath(*parts)


def _omegaconf_problem(e: OmegaConfBaseException) -> tuple[str, str]:
    """(dotted key, message without OmegaConf's multi-line context) of an OmegaConf error."""
    key = str(getattr(e, "full_key", "") or "")
    msg = str(getattr(e, "msg", "") or e).split("\n    full_key")[0]
    return key, " ".join(msg.split("\n"))


def _failing_key(cfg: DictConfig, data: DictConfig) -> str:
    """The top-level key of ``data`` whose merge into ``cfg`` fails ("" if none alone does)."""
    for key in data:
        try:
            OmegaConf.merge(cfg, {key: data[key]})
        except OmegaConfBaseException:
            return str(key)
    return ""


def _yaml_problem(e: yaml.YAMLError) -> str:
    """What a PyYAML error says, on one line. OmegaConf reads files and override values with PyYAML's
    safe loader: a tag that asks for a Python object (``!!python/object/apply:...``) is refused, never run."""
    mark = getattr(e, "problem_mark", None)
    where = f" at line {mark.line + 1} column {mark.column + 1}" if mark is not None else ""
    problem = getattr(e, "problem", None) or str(e).splitlines()[0]
    if isinstance(e, yaml.constructor.ConstructorError):
        return f"YAML tag refused{where}: {problem} (config values are plain YAML: numbers, strings, lists, mappings)"
    return f"malformed YAML{where}: {problem}"


def _load_yaml(path: Path) -> DictConfig:
    """One YAML file as a mapping; a missing, unreadable or malformed file raises ConfigError."""
    if not path.is_file():
        raise ConfigError(path, "", "config file not found")
    try:
        loaded = OmegaConf.load(path)
    except yaml.YAMLError as e:
        raise ConfigError(path, "", _yaml_problem(e)) from None
    except UnicodeDecodeError as e:
        raise ConfigError(path, "", f"not a UTF-8 text file ({e.reason} at byte {e.start})") from None
    except OmegaConfBaseException as e:
        key, msg = _omegaconf_problem(e)
        raise ConfigError(path, key, msg) from None
    if not isinstance(loaded, DictConfig):
        raise ConfigError(path, "", f"expected a mapping of config keys (key: value), found a {type(loaded).__name__}")
    return loaded


def _merged(cfg: DictConfig, data: Any, where: str | Path) -> DictConfig:
    """``cfg`` with the mapping ``data`` merged in; ConfigError naming ``where`` and the key."""
    try:
        return OmegaConf.merge(cfg, data)  # type: ignore[return-value]
    except OmegaConfBaseException as e:
        key, msg = _omegaconf_problem(e)
        raise ConfigError(where, key or _failing_key(cfg, OmegaConf.create(data)), msg) from None


@overload
def load_config(cls: type[T], yaml_path: str | Path | None = None, overrides: list[str] | None = None,
                layers: list[tuple[str, Any]] | None = None) -> T: ...
@overload
def load_config(cls: T, yaml_path: str | Path | None = None, overrides: list[str] | None = None,
                layers: list[tuple[str, Any]] | None = None) -> T: ...
def load_config(cls: type[T] | T, yaml_path: str | Path | None = None, overrides: list[str] | None = None,
                layers: list[tuple[str, Any]] | None = None) -> T:
    """Build a ``cls`` instance: dataclass defaults <- ``layers`` (``(source, mapping)`` pairs, e.g. the
    settings a JSON file holds under one of its keys) <- YAML file <- ``["a.b=1", ...]`` overrides.

    Raises ConfigError naming the file or the override, the key and what was expected: a missing
    or malformed YAML file or override value (a YAML tag that would build a Python object is refused,
    nothing runs), an unknown key, a value of the wrong type, an override without ``=``.
    """
    cfg = OmegaConf.structured(cls)
    for where, data in layers or []:
        if not isinstance(data, dict):
            raise ConfigError(where, "", f"expected a mapping of settings, found {type(data).__name__}")
        cfg = _merged(cfg, data, where)
    if yaml_path is not None:
        path = Path(yaml_path)
        cfg = _merged(cfg, _load_yaml(path), path)
    for item in overrides or []:
        where = f"command-line override {item!r}"
        key, sep, _ = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(where, "", "expected key=value, e.g. loop.steps=200")
        try:  # the value is parsed by the same safe YAML loader as the files
            cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist([item]))
        except yaml.YAMLError as e:
            raise ConfigError(where, key.strip(), _yaml_problem(e)) from None
        except OmegaConfBaseException as e:
            full_key, msg = _omegaconf_problem(e)
            raise ConfigError(where, full_key or key, msg) from None
    sources = " + ".join([*(str(w) for w, _ in layers or []), str(yaml_path or "defaults"),
                          *(f"override {o!r}" for o in overrides or [])])
    try:
        return OmegaConf.to_object(cfg)  # type: ignore[return-value]
    except OmegaConfBaseException as e:
        key, msg = _omegaconf_problem(e)
        raise ConfigError(sources, key, msg) from None
    except (TypeError, ValueError) as e:  # a config dataclass's own checks (__post_init__)
        if isinstance(e, ConfigError):
            raise
        if isinstance(e, FieldValueError):
            raise ConfigError(sources, e.field, e.problem) from None
        raise ConfigError(sources, "", str(e)) from None


def save_config(cfg: Any, path: str | Path) -> None:
    Path(path).write_text(OmegaConf.to_yaml(OmegaConf.structured(cfg)))
