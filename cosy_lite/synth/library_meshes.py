"""A synthetic dataset's object meshes without its images: what ``predict --pretrained NAME`` poses
when no dataset of that name has been generated (the reference set's objects, from the installed
package's object library)."""

from __future__ import annotations

from pathlib import Path

from cosy_lite.synth.objects import write_bop_models


def library_models(name: str, progress: bool = True) -> Path:
    """The BOP ``models/`` folder of the synthetic dataset ``name``'s objects (e.g. those of a shipped
    reference set), without its images: ``$COSY_LITE_DATA/NAME/models`` when generated, else written
    once from the installed package (the YCB-V library, ~4 s) into the cache, ``$COSY_LITE_CACHE/meshes/NAME``."""
    from cosy_lite.bop.folders import dataset_folder, default_cache_dir
    from cosy_lite.config import load_config, packaged_config
    from cosy_lite.errors import BopFormatError
    from cosy_lite.synth.generator import SynthConfig
    from cosy_lite.synth.ownership import check_can_write

    generated = dataset_folder(name) / "models"
    if (generated / "models_info.json").is_file():
        return generated
    profile = packaged_config("synth", f"{name}.yaml")
    cfg = load_config(SynthConfig, profile if profile.is_file() else None)
    if cfg.name != name:
        raise BopFormatError(generated.parent, "--meshes", f"not found, and {name!r} is not a dataset the package "
                             "generates: give the objects' meshes (--meshes DIR, a BOP models/ folder)")
    root = default_cache_dir() / "meshes" / name
    check_can_write(root, None, list(cfg.obj_ids))
    write_bop_models(list(cfg.obj_ids), root, progress=progress)
    return root / "models"
