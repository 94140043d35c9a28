"""``cosy-lite templates``: render the silhouette templates of some objects into a cache folder.

    cosy-lite templates --dataset ycbvsynth --cache runs/demo/templates [--objects 1,3,5] [--start appearance]

``--start appearance`` also describes the templates' textured renderings for the appearance start
(:mod:`cosy_lite.nets.appearance_templates`), rendered with ``--shading`` (the pose networks':
``headlight`` for every shipped refiner).

``infer.py --start templates --templates-cache DIR`` renders each object's templates on its first
detection and keeps them in ``DIR``; this command fills ``DIR`` ahead, e.g. for a deployment, or
split over several processes (``cosy-lite demo`` renders its objects in two processes, one core
each, before its two inference runs, which would otherwise both render every object). The files
are the ones the predictor writes (same keys: the mesh file's hash and the template settings), so
objects already in ``DIR`` are skipped.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cosy_lite.inference.command_predict import obj_id_list
from cosy_lite.inference.starts import TEMPLATE_STARTS


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dataset", required=True, help="dataset name (folder under --data-root) or folder (its models/)")
    p.add_argument("--data-root", type=Path, default=None, help="default: $COSY_LITE_DATA or ./data")
    p.add_argument("--cache", type=Path, required=True, metavar="DIR", help="the templates folder (--templates-cache of infer)")
    p.add_argument("--objects", type=obj_id_list, default=None, metavar="IDS",
                   help="object ids separated by commas (default: every object of models_info.json)")
    p.add_argument("--start", choices=TEMPLATE_STARTS, default="templates",
                   help="appearance: also the appearance descriptors of infer --start appearance")
    p.add_argument("--shading", choices=["headlight", "flat"], default="headlight",
                   help="the renderer shading of the appearance templates: the refiner's (default headlight)")


def render_templates(models_dir: Path, cache: Path, obj_ids: list[int] | None = None, start: str = "templates",
                     shading: str = "headlight") -> dict[int, float]:
    """Render (or find) the templates of ``obj_ids`` (default: all) of the BOP ``models_dir`` in
    ``cache`` (``start="appearance"``: their appearance descriptors too, rendered with ``shading``);
    seconds per object. Raises SetupError for an object without a model."""
    from cosy_lite.inference.object_meshes import ObjectMeshes, SetupError, objects_and_renderer, start_templates

    models = ObjectMeshes(models_dir)
    ids = sorted(obj_ids) if obj_ids else models.obj_ids
    unknown = sorted(set(ids) - set(models.obj_ids))
    if unknown:
        raise SetupError(f"{models.models_dir / 'models_info.json'}: no models of obj_ids {unknown}")
    cache.mkdir(parents=True, exist_ok=True)
    objects, renderer, _ = objects_and_renderer(models, ids, None, icp=False, shading=shading)
    templates = start_templates(start, models, objects, renderer, cache)
    assert templates is not None
    seconds = {obj_id: templates.prepare([obj_id]) for obj_id in ids}
    renderer.close()
    return seconds


def run(args: argparse.Namespace) -> int:
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.bop.folders import dataset_folder
    from cosy_lite.render.gl import use_egl

    use_egl()
    dataset = BopDataset(dataset_folder(args.dataset, args.data_root))
    seconds = render_templates(dataset.models_dir, args.cache, args.objects, args.start, args.shading)
    print(f"templates of {len(seconds)} objects in {args.cache} ({sum(seconds.values()):.0f} s: "
          + ", ".join(f"{i}: {s:.1f}" for i, s in seconds.items()) + ")")
    return 0
