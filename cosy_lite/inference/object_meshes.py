"""The objects a predictor estimates: their BOP ``models/`` folder, point table, renderer and templates.

Built once by the predictor's factories (:meth:`~cosy_lite.inference.predictor.Predictor.from_checkpoints`,
``from_onnx``): :class:`ObjectMeshes` reads a ``models/`` folder without a dataset;
:func:`objects_and_renderer` gives the object table, the renderer with the networks' shading and the
ICP symmetry sets; :func:`start_templates` the silhouette templates of ``start="templates"``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from cosy_lite.bop import io
from cosy_lite.errors import BopFormatError, CosyLiteError
from cosy_lite.inference.starts import TEMPLATE_STARTS
from cosy_lite.nets.silhouette_templates import SilhouetteTemplates
from cosy_lite.weights.loaders import PoseModel

if TYPE_CHECKING:
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.nets.appearance_templates import Scorer
    from cosy_lite.nets.object_table import ObjectTable
    from cosy_lite.render.renderer import MeshRenderer


class SetupError(CosyLiteError):
    """A predictor that cannot be built or run as asked (missing model, objects not covered); the
    message names the file."""


@dataclass
class ObjectMeshes:
    """The BOP ``models/`` folder of the objects (PLY in mm, ``models_info.json``), read lazily.

    Has what :meth:`cosy_lite.nets.object_table.ObjectTable.from_dataset` reads of a dataset
    (``models_dir``, ``models_info``, ``load_model``), so no dataset folder is needed.
    """

    models_dir: Path

    def __post_init__(self) -> None:
        self.models_dir = Path(self.models_dir)
        if not (self.models_dir / "models_info.json").is_file():
            raise BopFormatError(self.models_dir / "models_info.json", "", "not found (a BOP models/ folder is needed)")

    @cached_property
    def models_info(self) -> dict[int, io.ModelInfo]:
        return io.load_models_info(self.models_dir / "models_info.json")

    @property
    def obj_ids(self) -> list[int]:
        return sorted(self.models_info)

    def load_model(self, obj_id: int):
        """trimesh.Trimesh in metres."""
        return io.load_model(self.models_dir / f"obj_{int(obj_id):06d}.ply")


def estimated_obj_ids(requested: Sequence[int] | None, network_ids: Sequence[int], mesh_ids: Sequence[int],
                      meshes_file: Path) -> list[int]:
    """The objects a predictor estimates: ``requested`` (each must have a mesh), else those of the
    networks that have a mesh (a folder of one object estimates that one). SetupError naming
    ``meshes_file`` when none is left or a requested one has no mesh."""
    if requested:
        ids = sorted(int(i) for i in requested)
        unknown = sorted(set(ids) - set(mesh_ids))
        if unknown:
            raise SetupError(f"{meshes_file}: no models of obj_ids {unknown} (it has {sorted(mesh_ids)})")
        return ids
    ids = sorted(set(int(i) for i in network_ids) & set(int(i) for i in mesh_ids))
    if not ids:
        raise SetupError(f"{meshes_file}: no models of the networks' obj_ids {sorted(network_ids)} "
                         f"(it has {sorted(mesh_ids)})")
    return ids


def object_meshes(models_dir: str | Path | None, dataset: BopDataset | str | Path | None) -> ObjectMeshes:
    """The objects' BOP ``models/`` folder: ``models_dir`` or ``dataset``'s (exactly one given)."""
    from cosy_lite.bop.dataset import BopDataset

    if (models_dir is None) == (dataset is None):
        raise SetupError("give exactly one of models_dir (a BOP models/ folder) and dataset")
    if dataset is not None:
        ds = dataset if isinstance(dataset, BopDataset) else BopDataset(Path(dataset))
        return ObjectMeshes(ds.models_dir)
    assert models_dir is not None  # (exactly one of the two is given)
    return ObjectMeshes(Path(models_dir))


def render_shading(coarse: PoseModel | None, refiner: PoseModel | None) -> str:
    """The renderer shading the pose networks were trained with (SetupError if they differ)."""
    if coarse is None or refiner is None:
        model = coarse or refiner
        if model is None:
            raise SetupError("no pose model given (a coarse and/or a refiner checkpoint is needed)")
        return model.render_shading
    if refiner.render_shading != coarse.render_shading:
        raise SetupError(f"the coarse model ({coarse.describe()}) was trained on {coarse.render_shading!r} renderings, "
                         f"the refiner ({refiner.describe()}) on {refiner.render_shading!r}: they need one renderer")
    return coarse.render_shading


def objects_and_renderer(models: ObjectMeshes, ids: list[int], n_points: int | None, icp: bool,
                         shading: str = "flat") -> tuple[Any, Any, Any]:
    """(ObjectTable of ``ids``, a renderer of ``models`` with ``shading``, ICP symmetry sets or None)."""
    from cosy_lite.geometry.symmetries import symmetry_transforms
    from cosy_lite.nets.object_table import ObjectTable
    from cosy_lite.render.renderer import GlRenderer

    kwargs = {} if n_points is None else {"n_points": n_points}
    objects = ObjectTable.from_dataset(models, ids, **kwargs)  # type: ignore[arg-type]
    syms = {i: symmetry_transforms(models.models_info[i]) for i in ids} if icp else None
    return objects, GlRenderer(models_dir=models.models_dir, shading=shading), syms


def start_templates(start: str, models: ObjectMeshes, objects: ObjectTable, renderer: MeshRenderer,
                    cache_dir: str | Path | None, scorer: Scorer | None = None) -> SilhouetteTemplates | None:
    """The templates of a template start (``"templates"``, ``"appearance"``: with appearance
    descriptors, and the trained ``scorer`` (torch or onnxruntime) describing the detections when
    given; None otherwise),
    cached in ``cache_dir`` by the hash of each object's mesh file
    (:func:`~cosy_lite.nets.appearance_templates.object_templates`)."""
    if start not in TEMPLATE_STARTS:
        return None
    from cosy_lite.nets.appearance_templates import object_templates

    return object_templates(renderer, objects.obj_ids, objects.diameters.detach().cpu().double().tolist(),
                            models.models_dir, cache_dir, appearance=start == "appearance", scorer=scorer)
