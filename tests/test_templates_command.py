"""``cosy-lite templates``: the cache it fills is the one the predictor reads (same files, nothing
rendered again), objects are checked, and a second run skips what is cached."""

from __future__ import annotations

import numpy as np
import pytest

from cosy_lite.cli import main as cli


def test_the_predictor_reads_the_templates_the_command_rendered(tiny_synth_root, tmp_path, capsys, monkeypatch):
    from cosy_lite.inference.command_templates import render_templates
    from cosy_lite.inference.object_meshes import ObjectMeshes, SetupError, objects_and_renderer, start_templates
    from cosy_lite.nets.silhouette_templates import SilhouetteTemplates

    cache = tmp_path / "templates"
    assert cli(["templates", "--dataset", str(tiny_synth_root), "--cache", str(cache), "--objects", "2,5"]) == 0
    assert "templates of 2 objects" in capsys.readouterr().out
    files = sorted(p.name for p in cache.glob("*.npz"))
    assert len(files) == 2 and files[0].startswith("templates_obj000002_") and files[1].startswith("templates_obj000005_")

    # as the predictor builds them (infer --templates-cache): every object found, none rendered
    models = ObjectMeshes(tiny_synth_root / "models")
    objects, renderer, _ = objects_and_renderer(models, [2, 5], None, icp=False)
    templates = start_templates("templates", models, objects, renderer, cache)

    def no_render(self, obj_id):
        raise AssertionError(f"object {obj_id} rendered again: the command's cache file was not found")

    monkeypatch.setattr(SilhouetteTemplates, "_render", no_render)
    for obj_id in (2, 5):
        t = templates.templates(obj_id)
        assert t.grids.shape[0] == templates.n_rotations and np.isfinite(t.depth)
    # a second run finds everything cached (no rendering: _render is still the failing one)
    assert set(render_templates(tiny_synth_root / "models", cache, [2, 5])) == {2, 5}
    renderer.close()

    with pytest.raises(SetupError, match=r"no models of obj_ids \[99\]"):
        render_templates(tiny_synth_root / "models", cache, [99])
    for bad in ("x", "0"):  # argparse: usage error, exit 2
        with pytest.raises(SystemExit) as e:
            cli(["templates", "--dataset", str(tiny_synth_root), "--cache", str(cache), "--objects", bad])
        assert e.value.code == 2
