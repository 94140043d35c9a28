"""What an export folder holds: ``manifest.json`` + one ``.onnx`` file per network, and the
metadata each ``.onnx`` carries about itself.

``manifest.json``::

    {"format": 1, "cosy_lite_version": "0.1.0",
     "models": {"coarse": {"file": "coarse.onnx", "kind": "coarse", "obj_ids": [1, 2],
                           "input_name": "images", "input_shape": ["batch", 6, 240, 320],
                           "crop_resolution": [240, 320], "quantization": "none", "opset": 17,
                           "bytes": 1234, "sha256": "...", "source": "runs/.../checkpoint.pt",
                           "check": {"batch": 2, "max_abs_diff": 1e-7}},
                "coarse.int8": {...}, "refiner": {...}, "detector": {...},
                "scorer": {"file": "scorer.onnx", "kind": "scorer", "input_name": "crops",
                           "input_shape": ["batch", 3, 64, 64], "crop_resolution": [64, 64], ...}},
     "inference": {"start": "appearance", "n_candidates": 1, "n_refiner_iterations": 4, ...}}

Entry names are the role ("detector", "coarse", "refiner", "scorer": the coarse scorer of
``start="appearance"``), with ``.int8`` for the dynamically quantised copies of the pose
networks. ``inference`` is how the networks are meant to run
(the fields of :class:`~cosy_lite.inference.settings.InferenceConfig`, which checks them; its
defaults when absent), so that an export is complete by itself. Each ``.onnx`` repeats its entry's facts in
``metadata_props`` (keys :data:`META_KEYS`), so a single file is usable without the manifest and a
file copied from another export is caught. Every problem raises :class:`OnnxModelError` naming
the file and the field.
"""

from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cosy_lite
from cosy_lite.errors import CosyLiteError

MANIFEST = "manifest.json"
MANIFEST_FORMAT = 1
POSE_KINDS = ("coarse", "refiner")
SCORER_KIND = "scorer"
KINDS = ("detector", *POSE_KINDS, SCORER_KIND)
QUANTIZATIONS = ("none", "int8")
POSE_INPUT_CHANNELS = 6  # image crop + rendered crop, RGB each
SCORER_INPUT_CHANNELS = 3  # the detection crop, RGB (the templates keep their cached descriptors)

# metadata_props key -> what it holds (values are strings; JSON where structured)
META_KEYS: dict[str, str] = {
    "cosy_lite.kind": "detector | coarse | refiner | scorer",
    "cosy_lite.obj_ids": "JSON list of BOP obj_ids (detector: label k is obj_ids[k - 1])",
    "cosy_lite.input": "JSON {name, shape, dtype, range}",
    "cosy_lite.crop_resolution": "JSON [h, w] px of the pose networks' and the scorer's crops (not the detector)",
    "cosy_lite.config": "JSON of the network config (PoseNetConfig / DetectorConfig / the scorer's trunk, "
                        "template shading and iou_weight)",
    "cosy_lite.quantization": "none | int8",
    "cosy_lite.version": "cosy_lite version that exported the file",
    "cosy_lite.source": "the checkpoint the weights came from",
}
REQUIRED_META = ("cosy_lite.kind", "cosy_lite.obj_ids", "cosy_lite.input", "cosy_lite.version")


class OnnxModelError(CosyLiteError):
    """An exported model (or its manifest) that cannot be used as asked.

    Args:
        path: the offending file (``.onnx`` or ``manifest.json``).
        field: the manifest key / metadata key / graph property that is wrong ("" if the whole file).
        problem: what is wrong and what was expected.
    """

    def __init__(self, path: str | Path, field: str, problem: str):
        self.path, self.field, self.problem = str(path), field, problem
        super().__init__(f"{self.path}" + (f" [{field}]" if field else "") + f": {problem}")


@dataclass
class ModelEntry:
    """One exported network (a manifest entry; see the module docstring for the fields)."""

    file: str
    kind: str
    obj_ids: list[int]
    input_name: str
    input_shape: list[int | str]
    crop_resolution: list[int] | None = None
    quantization: str = "none"
    opset: int = 17
    bytes: int = 0
    sha256: str = ""
    source: str = ""
    check: dict[str, Any] = field(default_factory=dict)


def file_digest(path: Path) -> tuple[int, str]:
    """(size in bytes, sha256 hex) of ``path`` (the one file hash of the package, shared with the
    reference-model cards)."""
    from cosy_lite.weights.reference_models import file_sha256

    return path.stat().st_size, file_sha256(path)


def metadata_of(entry: ModelEntry, config: dict[str, Any]) -> dict[str, str]:
    """The ``metadata_props`` written into the ``.onnx`` of ``entry``."""
    meta = {
        "cosy_lite.kind": entry.kind,
        "cosy_lite.obj_ids": json.dumps([int(i) for i in entry.obj_ids]),
        "cosy_lite.input": json.dumps({"name": entry.input_name, "shape": entry.input_shape, "dtype": "float32",
                                       "range": [0.0, 1.0]}),
        "cosy_lite.config": json.dumps(config, sort_keys=True),
        "cosy_lite.quantization": entry.quantization,
        "cosy_lite.version": cosy_lite.__version__,
        "cosy_lite.source": entry.source,
    }
    if entry.crop_resolution is not None:
        meta["cosy_lite.crop_resolution"] = json.dumps([int(v) for v in entry.crop_resolution])
    return meta


def write_metadata(path: Path, meta: dict[str, str]) -> None:
    """Replace the ``metadata_props`` of the ``.onnx`` file ``path`` with ``meta`` (e.g.
    :func:`metadata_of`) and validate the file with ``onnx.checker``."""
    import onnx

    model = onnx.load(str(path))
    del model.metadata_props[:]
    for k, v in sorted(meta.items()):
        model.metadata_props.add(key=k, value=v)
    model.producer_name = "cosy_lite"
    onnx.save(model, str(path))
    onnx.checker.check_model(str(path))


def parse_json_meta(meta: dict[str, str], key: str, path: Path) -> Any:
    """The JSON value of ``metadata_props[key]`` (OnnxModelError naming the file and key)."""
    if key not in meta:
        raise OnnxModelError(path, f"metadata_props[{key}]", "missing (not a cosy_lite export, or an older one)")
    try:
        return json.loads(meta[key])
    except json.JSONDecodeError as e:
        raise OnnxModelError(path, f"metadata_props[{key}]", f"not JSON ({e}): {meta[key][:80]!r}") from None


@dataclass
class Manifest:
    """``manifest.json`` of an export folder: entry name -> :class:`ModelEntry`."""

    root: Path
    models: dict[str, ModelEntry]
    version: str = cosy_lite.__version__
    inference: dict[str, Any] = field(default_factory=dict)  # InferenceConfig's fields, {}: its defaults

    @property
    def path(self) -> Path:
        return self.root / MANIFEST

    def write(self) -> Path:
        payload = {"format": MANIFEST_FORMAT, "cosy_lite_version": self.version,
                   "models": {name: asdict(e) for name, e in sorted(self.models.items())},
                   "inference": self.inference}
        text = json.dumps(payload, indent=2)
        # lists of numbers/strings on one line (obj_ids, shapes), the rest indented
        text = re.sub(r"\[\s+([^\[\]{}]*?)\s+\]",
                      lambda m: "[" + ", ".join(v.strip() for v in m.group(1).split(",")) + "]", text)
        self.path.write_text(text + "\n")
        return self.path

    def entry(self, name: str) -> ModelEntry | None:
        return self.models.get(name)

    def file(self, name: str) -> Path:
        """The ``.onnx`` of entry ``name``: it must exist with the recorded size and sha256."""
        e = self.models[name]
        path = self.root / e.file
        if not path.is_file():
            raise OnnxModelError(path, "", f"not found (listed in {self.path} as models.{name}.file)")
        size, digest = file_digest(path)
        if e.bytes and size != e.bytes:
            raise OnnxModelError(path, "bytes", f"{size} bytes, but {self.path} records {e.bytes} for models.{name} "
                                 "(truncated or replaced file)")
        if e.sha256 and digest != e.sha256:
            raise OnnxModelError(path, "sha256", f"content differs from the export recorded in {self.path} "
                                 f"(models.{name}.sha256): the file was replaced; export again")
        return path

    @classmethod
    def read(cls, root: str | Path) -> "Manifest":
        """The manifest of the export folder ``root`` (OnnxModelError naming the file and field)."""
        root = Path(root)
        path = root / MANIFEST
        if not root.is_dir():
            raise OnnxModelError(root, "", "export folder not found (cosy-lite export --out DIR writes one)")
        if not path.is_file():
            raise OnnxModelError(path, "", "not found: not an export folder (cosy-lite export --out DIR writes one)")
        try:
            payload = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise OnnxModelError(path, "", f"not valid JSON ({e})") from None
        if not isinstance(payload, dict):
            raise OnnxModelError(path, "", f"expected a JSON object, found {type(payload).__name__}")
        if payload.get("format") != MANIFEST_FORMAT:
            raise OnnxModelError(path, "format", f"is {payload.get('format')!r}, this version reads {MANIFEST_FORMAT}")
        models = payload.get("models")
        if not isinstance(models, dict) or not models:
            raise OnnxModelError(path, "models", "missing or empty (expected {name: entry})")
        entries = {}
        for name, raw in models.items():
            entries[name] = _entry(path, name, raw)
        inference = payload.get("inference", {})
        if not isinstance(inference, dict):
            raise OnnxModelError(path, "inference", f"expected an object of settings, found {type(inference).__name__}")
        return cls(root, entries, str(payload.get("cosy_lite_version", "?")), inference)


def _entry(path: Path, name: str, raw: Any) -> ModelEntry:
    where = f"models.{name}"
    if not isinstance(raw, dict):
        raise OnnxModelError(path, where, f"expected an object, found {type(raw).__name__}")
    try:
        e = ModelEntry(**raw)
    except TypeError as err:
        raise OnnxModelError(path, where, f"fields do not fit a model entry ({err})") from None
    if e.kind not in KINDS:
        raise OnnxModelError(path, f"{where}.kind", f"{e.kind!r}, expected one of {list(KINDS)}")
    if e.quantization not in QUANTIZATIONS:
        raise OnnxModelError(path, f"{where}.quantization",
                             f"{e.quantization!r}, expected one of {list(QUANTIZATIONS)}")
    ids = e.obj_ids
    if not isinstance(ids, list) or not ids or not all(isinstance(i, int) and i > 0 for i in ids):
        raise OnnxModelError(path, f"{where}.obj_ids", f"expected a non-empty list of positive ints, got {ids!r}")
    if e.kind != "detector":
        crop = e.crop_resolution
        if not (isinstance(crop, list) and len(crop) == 2 and all(isinstance(v, int) and v > 0 for v in crop)):
            raise OnnxModelError(path, f"{where}.crop_resolution", f"expected [h, w] positive ints, got {crop!r}")
        channels = POSE_INPUT_CHANNELS if e.kind in POSE_KINDS else SCORER_INPUT_CHANNELS
        if (not isinstance(e.input_shape, list) or len(e.input_shape) != 4
                or e.input_shape[1] != channels or list(e.input_shape[2:]) != crop):
            raise OnnxModelError(path, f"{where}.input_shape", f"{e.input_shape!r}, expected "
                                 f"['batch', {channels}, {crop[0]}, {crop[1]}] (crop_resolution {crop})")
    return e
