"""One typed inference configuration: its defaults written once, its errors naming file and field, and
an export that runs as its reference set by itself."""

from __future__ import annotations

import ast
import dataclasses
import json
from pathlib import Path

import pytest

from cosy_lite.errors import ConfigError
from cosy_lite.inference.settings import InferenceConfig, inference_config

REPO = Path(__file__).resolve().parents[1]
SETTINGS = REPO / "cosy_lite" / "inference" / "settings.py"
CROPS = REPO / "cosy_lite" / "geometry" / "crops.py"
# names under which the package takes a refiner iteration count or a candidate count
SETTING_NAMES = {"n_refiner_iterations", "n_refiner_iters", "n_iterations", "val_iterations", "n_candidates",
                 "candidates", "iterations"}


def _literal_defaults(path: Path) -> list[tuple[str, int, object]]:
    """(name, line, value) of every literal number given as the default of a setting-like name in
    ``path``: function parameters, annotated class fields, ``add_argument("--NAME", default=...)``."""
    tree = ast.parse(path.read_text())
    found = []

    def literal(node):
        return node.value if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) \
            and not isinstance(node.value, bool) else None

    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            args = node.args
            positional = args.posonlyargs + args.args
            for a, d in zip(positional[len(positional) - len(args.defaults):], args.defaults):
                found.append((a.arg, d.lineno, literal(d)))
            for a, d in zip(args.kwonlyargs, args.kw_defaults):
                if d is not None:
                    found.append((a.arg, d.lineno, literal(d)))
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and node.value is not None:
            found.append((node.target.id, node.lineno, literal(node.value)))
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_argument" and node.args:
            flag = node.args[0].value if isinstance(node.args[0], ast.Constant) else ""
            for kw in node.keywords:
                if kw.arg == "default" and isinstance(flag, str):
                    found.append((flag.lstrip("-").replace("-", "_"), kw.value.lineno, literal(kw.value)))
    return [(n, line, v) for n, line, v in found if v is not None and n in SETTING_NAMES]


def _crop_literals(path: Path) -> list[int]:
    """Lines of ``path`` holding the crop size (240, 320) as a tuple or list literal in code."""
    lines = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, (ast.Tuple, ast.List)) and len(node.elts) == 2 and all(
                isinstance(e, ast.Constant) for e in node.elts) and [e.value for e in node.elts] == [240, 320]:
            lines.append(node.lineno)
    return lines


def test_every_inference_default_is_written_once():
    files = sorted((REPO / "cosy_lite").rglob("*.py")) + sorted((REPO / "bench").glob("*.py")) + [
        REPO / "infer.py", REPO / "train.py"]
    duplicated = [f"{p.relative_to(REPO)}:{line} {name} = {value}" for p in files if p != SETTINGS
                  for name, line, value in _literal_defaults(p)]
    assert not duplicated, "inference defaults live in InferenceConfig only:\n" + "\n".join(duplicated)
    crops = [f"{p.relative_to(REPO)}:{line}" for p in files if p != CROPS for line in _crop_literals(p)]
    assert not crops, "the crop size is CROP_RESOLUTION (geometry/crops.py) only:\n" + "\n".join(crops)
    # and the check finds them where they are
    assert {n for n, _, _ in _literal_defaults(SETTINGS)} >= {"n_refiner_iterations", "n_candidates"}
    assert _crop_literals(CROPS)


def test_the_check_finds_a_duplicated_default(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("def f(x, n_refiner_iterations=4):\n    pass\n\nclass C:\n    n_candidates: int = 5\n\n"
                   "def g(ap):\n    ap.add_argument('--candidates', type=int, default=3)\n    crop = (240, 320)\n")
    assert sorted(n for n, _, _ in _literal_defaults(bad)) == ["candidates", "n_candidates", "n_refiner_iterations"]
    assert _crop_literals(bad) == [9]


def test_settings_read_from_a_file_with_overrides_and_errors_naming_file_and_field(tmp_path):
    path = tmp_path / "settings.yaml"
    path.write_text("start: appearance\nn_candidates: 3\nicp_settings: {max_translation: 0.05}\n")
    cfg = inference_config({"icp": True}, "pipeline.json", path, ["n_refiner_iterations=2"])
    assert (cfg.start, cfg.n_candidates, cfg.n_refiner_iterations, cfg.icp) == ("appearance", 3, 2, True)
    assert cfg.icp_settings.max_translation == 0.05 and cfg.icp_settings.min_points == 50
    assert inference_config(cfg.to_dict()) == cfg  # written and read back: the same
    for base, overrides, where, field in [({"start": "sideways"}, [], "pipeline.json", "start"),
                                          ({"n_candidates": 2}, [], "pipeline.json", "n_candidates"),
                                          ({}, ["batch_size=0"], "batch_size=0", "batch_size"),
                                          ({"min_score": "high"}, [], "pipeline.json", "min_score"),
                                          ({"bogus": 1}, [], "pipeline.json", "bogus")]:
        with pytest.raises(ConfigError) as e:
            inference_config(base, "pipeline.json", None, overrides)
        assert where in e.value.where and e.value.field == field, (base, overrides, str(e.value))
    path.write_text("start: !!python/object/apply:os.system ['echo hacked']\n")
    with pytest.raises(ConfigError, match="YAML tag refused"):
        inference_config(None, "", path)


def test_an_export_carries_its_settings_and_a_bad_one_is_named(tmp_path):
    from cosy_lite.export.manifest import Manifest, ModelEntry

    entry = ModelEntry(file="refiner.onnx", kind="refiner", obj_ids=[1], input_name="images",
                       input_shape=["batch", 6, 240, 320], crop_resolution=[240, 320])
    settings = dataclasses.replace(InferenceConfig(), start="appearance", n_refiner_iterations=3).to_dict()
    Manifest(tmp_path, {"refiner": entry}, inference=settings).write()
    manifest = Manifest.read(tmp_path)
    assert inference_config(manifest.inference, manifest.path) == InferenceConfig(**{
        **settings, "icp_settings": InferenceConfig().icp_settings})
    payload = json.loads(manifest.path.read_text())
    payload["inference"]["n_refiner_iterations"] = -1
    manifest.path.write_text(json.dumps(payload))
    with pytest.raises(ConfigError) as e:
        inference_config(Manifest.read(tmp_path).inference, manifest.path)
    assert e.value.where.startswith(str(manifest.path)) and e.value.field == "n_refiner_iterations"


def test_the_estimated_objects_are_those_with_a_mesh(tmp_path):
    """Without --objects, a folder of meshes of some of the networks' objects estimates those (a
    one-object folder failed with 'no models of obj_ids [1, 3, ...]' unless --objects was given)."""
    from cosy_lite.inference.object_meshes import SetupError, estimated_obj_ids

    info = tmp_path / "models_info.json"
    assert estimated_obj_ids(None, range(1, 22), [2], info) == [2]
    assert estimated_obj_ids([5, 2], range(1, 22), [2, 5, 30], info) == [2, 5]
    with pytest.raises(SetupError, match=r"models_info.json: no models of obj_ids \[7\]"):
        estimated_obj_ids([7], range(1, 22), [2], info)
    with pytest.raises(SetupError, match=r"no models of the networks' obj_ids \[1, 2\] \(it has \[30\]\)"):
        estimated_obj_ids(None, [1, 2], [30], info)


def test_no_refiner_iterations_alone_works_over_a_set_with_candidates():
    """``--n-refiner-iters 0`` over settings with 5 candidates: the best template is the start (it
    stopped with "n_candidates: 5 needs n_refiner_iterations >= 1" unless --candidates 1 was added)."""
    import argparse

    from cosy_lite.inference.settings import add_arguments, config_from_arguments

    ap = argparse.ArgumentParser()
    add_arguments(ap, "")
    base = {"start": "templates", "n_candidates": 5, "n_refiner_iterations": 4}
    cfg = config_from_arguments(ap.parse_args(["--n-refiner-iters", "0"]), base, "pipeline.json")
    assert (cfg.n_refiner_iterations, cfg.n_candidates) == (0, 1)
    cfg = config_from_arguments(ap.parse_args(["--n-refiner-iters", "2"]), base, "pipeline.json")
    assert (cfg.n_refiner_iterations, cfg.n_candidates) == (2, 5)
    with pytest.raises(Exception, match="needs n_refiner_iterations >= 1"):  # asked for both: say why not
        config_from_arguments(ap.parse_args(["--n-refiner-iters", "0", "--candidates", "5"]), base, "pipeline.json")


def test_predict_filters_by_default_and_infer_does_not():
    """predict keeps detections scoring >= 0.5, the best one per object (bench/bench_score_threshold.py's best
    F1; it posed every detection: 36 estimates on an image of 10 objects); flags win; infer keeps all."""
    import argparse

    from cosy_lite.inference import command_infer, command_predict
    from cosy_lite.inference.settings import PREDICT_DEFAULTS, pretrained_config

    def predict_config(*flags: str):
        ap = argparse.ArgumentParser()
        command_predict.add_arguments(ap)
        return command_predict._settings(ap.parse_args(["--rgb", "x", "--camera", "c", "--out", "o", *flags]))

    assert PREDICT_DEFAULTS == {"min_score": 0.5, "max_per_object": 1}
    cfg = predict_config("--pretrained", "ycbvsynth")
    assert (cfg.min_score, cfg.max_per_object, cfg.start) == (0.5, 1, "appearance")  # over the set's settings
    cfg = predict_config("--pretrained", "ycbvsynth", "--min-score", "0", "--max-per-object", "0")
    assert (cfg.min_score, cfg.max_per_object) == (0.0, 0)
    ap = argparse.ArgumentParser()
    command_infer.add_arguments(ap)
    cfg = pretrained_config(ap.parse_args(["--dataset", "d", "--pretrained", "ycbvsynth"]))
    assert (cfg.min_score, cfg.max_per_object) == (0.0, 0)


def test_templates_are_kept_between_runs_by_default(tmp_path, monkeypatch):
    """infer and predict keep rendered templates in $COSY_LITE_CACHE/templates unless told where (a
    second predict rendered them all again: 187 s warm against 202 s cold)."""
    import argparse

    from cosy_lite.inference.settings import templates_cache

    monkeypatch.setenv("COSY_LITE_CACHE", str(tmp_path))
    assert templates_cache(argparse.Namespace(templates_cache=None)) == tmp_path / "templates"
    assert templates_cache(argparse.Namespace(templates_cache=Path("mine"))) == Path("mine")


def test_refiner_depth_drift_is_read_checked_and_indexed_by_iterations():
    cfg = inference_config(None, "", None, ["refiner_depth_drift=[1.005, 1.01]"])
    assert cfg.refiner_depth_drift == [1.005, 1.01]
    assert (cfg.depth_drift(0), cfg.depth_drift(1), cfg.depth_drift(2), cfg.depth_drift(4)) == (1.0, 1.005, 1.01, 1.01)
    assert InferenceConfig().depth_drift(4) == 1.0  # none by default
    for bad in ("[0.1]", "[1.0, nan]"):
        with pytest.raises(ConfigError) as e:
            inference_config(None, "", None, [f"refiner_depth_drift={bad}"])
        assert e.value.field == "refiner_depth_drift"


def test_refiner_fine_iterations_are_read_and_checked():
    cfg = inference_config(None, "", None, ["refiner_fine_iterations=[2, 4]", "refiner_fine_resolution=[240, 320]"])
    assert (cfg.refiner_fine_iterations, cfg.refiner_fine_resolution) == ([2, 4], [240, 320])
    assert cfg.depth_iterations() == 2  # iterations 1 and 3 set the depth: its drift is that of 2
    cfg5 = inference_config(cfg.to_dict(), "pipeline.json", None, ["n_refiner_iterations=5", "refiner_fine_iterations=[5, 7]"])
    assert cfg5.depth_iterations() == 4  # (iteration 7 is not run)
    assert [cfg.depth_iterations(through=i) for i in range(5)] == [0, 1, 1, 2, 2]  # after iterations 0-4 (4 run)
    off = inference_config(cfg.to_dict(), "pipeline.json", None, ["refiner_fine_iterations=[]"])
    assert off.refiner_fine_iterations == []  # off with the resolution left as it was
    for bad, field in (("refiner_fine_resolution=[250, 320]", "refiner_fine_resolution"),
                       ("refiner_fine_resolution=[240]", "refiner_fine_resolution"),
                       ("refiner_fine_iterations=[0]", "refiner_fine_iterations"),
                       ("refiner_fine_iterations=[2]", "refiner_fine_resolution")):  # no crop size
        with pytest.raises(ConfigError) as e:
            inference_config(None, "", None, [bad])
        assert e.value.field == field, bad


def test_the_exact_mask_settings_are_read_and_checked():
    cfg = inference_config(None, "", None, ["silhouette_guard=0.05", "depth_from_mask=true"])
    assert (cfg.silhouette_guard, cfg.depth_from_mask) == (0.05, True)
    assert (InferenceConfig().silhouette_guard, InferenceConfig().depth_from_mask) == (0.0, False)  # off by default
    for bad, field in (("silhouette_guard=1.5", "silhouette_guard"), ("silhouette_guard=-0.1", "silhouette_guard"),
                       ("depth_from_mask=maybe", "depth_from_mask")):
        with pytest.raises(ConfigError) as e:
            inference_config(None, "pipeline.json", None, [bad])
        assert e.value.field == field, bad


def test_exact_masks_flag_gives_the_exact_mask_settings_and_set_wins():
    import argparse

    from cosy_lite.inference import command_infer
    from cosy_lite.inference.settings import EXACT_MASK_SETTINGS, config_from_arguments

    ap = argparse.ArgumentParser()
    command_infer.add_arguments(ap)
    cfg = config_from_arguments(ap.parse_args(["--detections", "oracle", "--exact-masks"]))
    assert (cfg.silhouette_guard, cfg.depth_from_mask) == (0.05, True)
    assert EXACT_MASK_SETTINGS == ("silhouette_guard=0.05", "depth_from_mask=true")
    cfg = config_from_arguments(ap.parse_args(["--exact-masks", "--set", "silhouette_guard=0.1", "depth_from_mask=false"]))
    assert (cfg.silhouette_guard, cfg.depth_from_mask) == (0.1, False)
    plain = config_from_arguments(ap.parse_args(["--detections", "oracle"]))
    assert (plain.silhouette_guard, plain.depth_from_mask) == (0.0, False)
