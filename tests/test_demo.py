"""``cosy-lite demo`` orchestration: which commands it runs, what it skips, the summary it prints.

The steps themselves (generate, train, infer, eval) have their own tests; here ``_run`` is
replaced by a recorder so the order, the arguments and the resume rules are checked in milliseconds.
Every step is ``python -m cosy_lite.cli COMMAND`` (torchrun ``-m cosy_lite.cli train``): the demo needs
the installed package, not the source tree (``tests/test_installed_package.py`` runs it installed).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cosy_lite import demo


@pytest.fixture
def recorded(monkeypatch):
    calls: list[list[str]] = []
    monkeypatch.setattr(demo, "_run", lambda cmd, what, env=None: calls.append(cmd))
    monkeypatch.setattr(demo, "_run_parallel", lambda cmds, whats, logs: calls.extend(cmds))
    return calls


def _is(cmd: list[str], command: str) -> bool:
    """Whether ``cmd`` runs ``cosy-lite COMMAND`` (``python -m cosy_lite.cli COMMAND ...``, also under torchrun)."""
    i = max(i for i, a in enumerate(cmd) if a == "-m")
    return cmd[i + 1:i + 3] == ["cosy_lite.cli", command]


def _cfg(tmp_path: Path, start: str = "templates", train: bool = True) -> demo.DemoConfig:
    return demo.DemoConfig(data_root=tmp_path / "data", runs=tmp_path / "runs", out=tmp_path / "out", start=start,
                           train=train)


def test_with_templates_the_detector_and_the_refiner_train_on_both_cores(tmp_path, recorded, monkeypatch):
    cfg = _cfg(tmp_path)
    demo.train_models(cfg, tmp_path / "data" / "ycbvsynth")
    assert [c[c.index("--model") + 1] for c in recorded] == ["detector", "refiner"]  # no coarse network
    for cmd in recorded:
        assert cmd[1:6] == ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
        assert "loop.num_workers=0" in cmd
    assert f"loop.max_minutes={cfg.train_minutes['refiner']}" in recorded[1]
    recorded.clear()
    monkeypatch.setattr(demo.json, "loads", lambda text: _scores(0.0))
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: "{}")
    demo.infer_and_eval(cfg, tmp_path / "missing")  # no scores: every step runs
    infer = [c for c in recorded if _is(c, "infer")][0]
    assert "--coarse" not in infer and infer[infer.index("--start") + 1] == "templates"
    assert infer[infer.index("--candidates") + 1] == str(demo.TRAIN_CANDIDATES)


def test_training_runs_each_model_once_with_its_budget_and_resumes_unfinished_runs(tmp_path, recorded):
    cfg = _cfg(tmp_path, start="coarse")
    (cfg.runs / "coarse").mkdir(parents=True)
    (cfg.runs / "coarse" / "checkpoint.pt").write_bytes(b"")  # interrupted run: resumed
    (cfg.runs / "refiner").mkdir(parents=True)
    (cfg.runs / "refiner" / "DONE").write_text("")  # finished run: skipped
    demo.train_models(cfg, tmp_path / "data" / "ycbvsynth")
    assert [c[c.index("--model") + 1] for c in recorded] == ["detector", "coarse"]
    det, coarse = recorded
    budgets = cfg.train_minutes
    assert "--resume" not in det and f"loop.max_minutes={budgets['detector']}" in det
    assert det[1:6] == ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]  # two DDP processes
    assert "loop.num_workers=0" in det
    assert "--resume" in coarse and f"loop.max_minutes={budgets['coarse']}" in coarse
    assert (cfg.runs / "detector" / "DONE").is_file() and (cfg.runs / "coarse" / "DONE").is_file()


def _fake_dataset(root: Path, n_train: int) -> None:
    (root / "train_pbr" / "000000").mkdir(parents=True)
    (root / "train_pbr" / "000000" / "scene_gt_info.json").write_text(json.dumps({str(i): [] for i in range(n_train)}))
    (root / "test_targets_bop19.json").write_text("[]")


def test_generation_is_skipped_when_the_dataset_is_complete(tmp_path, recorded):
    cfg = _cfg(tmp_path)
    root = cfg.data_root / cfg.dataset
    demo.prepare_dataset(cfg)
    assert recorded[0][recorded[0].index("generate") + 2] == str(root)  # generate --out ROOT
    assert "--splits" not in recorded[0]  # training from scratch: the whole dataset
    recorded.clear()
    _fake_dataset(root, 1000)
    demo.prepare_dataset(cfg)
    assert not any("generate" in c for c in recorded) and "check-dataset" in recorded[0]
    assert [c[3] for c in recorded[1:]] == ["show", "contact-sheet"]  # GT contours over a test and training images


def test_with_reference_models_only_the_test_split_and_a_few_training_images_are_generated(tmp_path, recorded):
    cfg = _cfg(tmp_path, train=False)
    assert cfg.reference == "ycbvsynth"
    root = cfg.data_root / cfg.dataset
    demo.prepare_dataset(cfg)
    gen = recorded[0]
    assert gen[gen.index("--splits") + 1:gen.index("--splits") + 3] == ["test", "train_pbr"]
    assert f"train.n_images={cfg.short_train_images}" in gen
    recorded.clear()
    _fake_dataset(root, cfg.short_train_images)
    demo.prepare_dataset(cfg)  # enough for the short runs
    assert not any("generate" in c for c in recorded) and "check-dataset" in recorded[0]
    recorded.clear()
    demo.prepare_dataset(_cfg(tmp_path, train=True))  # 100 images are not enough to train from scratch
    assert "generate" in recorded[0] and "--splits" not in recorded[0]


def _scores(ar: float) -> dict:
    thresholds = [0.05 * k for k in range(1, 11)]
    return {"ar": ar, "ar_vsd": ar + 0.1, "ar_mssd": ar + 0.2, "ar_mspd": ar + 0.3,
            "thresholds": {"mssd_x_diameter": thresholds}, "recall_mssd": [ar + 0.01 * k for k in range(10)]}


def test_infer_and_eval_reads_every_scores_file_and_the_summary_lists_them(tmp_path, recorded):
    cfg = _cfg(tmp_path)
    runs = demo.scored_runs(cfg)
    for i, run in enumerate(runs):  # as if infer.py and eval had run before
        csv = cfg.out / "results" / f"{run.method}_{cfg.dataset}-test.csv"
        (csv.parent / f"{csv.stem}_eval").mkdir(parents=True)
        csv.write_text("")
        (csv.parent / f"{csv.stem}_eval" / "scores.json").write_text(json.dumps(_scores(0.1 * i)))
    results = demo.infer_and_eval(cfg, tmp_path)
    assert recorded == []  # nothing re-run
    assert [r.method for r, _ in results] == ["cosylite", "cosyliteicp", "cosyliteoracle", "cosyliteoracleicp"]
    assert any("--icp" in r.args for r, _ in results[1:2]) and "oracle" in results[2][0].args
    assert results[0][0].label.endswith("(RGB)") and results[1][0].label.endswith("depth ICP")
    table = demo.summary_table(results).splitlines()
    assert table[0] == "| pipeline | AR | AR_VSD | AR_MSSD | AR_MSPD | MSSD recall 0.1 d |"
    assert table[3].endswith("| 0.100 | 0.200 | 0.300 | 0.400 | 0.110 |")  # 2nd run: AR 0.1, VSD 0.2, ...
    demo.plot_summary(results, tmp_path / "ar.png")
    assert (tmp_path / "ar.png").stat().st_size > 5000


def test_infer_and_eval_runs_the_missing_steps_with_the_demo_checkpoints(tmp_path, recorded, monkeypatch):
    cfg = _cfg(tmp_path, start="coarse")
    monkeypatch.setattr(demo.json, "loads", lambda text: _scores(0.0))
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: "{}")
    demo.infer_and_eval(cfg, tmp_path / "root")
    infers = [c for c in recorded if _is(c, "infer")]
    evals = [c for c in recorded if "eval" in c]
    assert len(infers) == 2 and len(evals) == 4  # each ICP run also writes its poses before ICP
    for cmd, before in zip(infers, ("cosylite", "cosyliteoracle")):
        assert "--icp" in cmd and cmd[cmd.index("--also-before-icp") + 1] == before
    first = infers[0]
    assert first[first.index("--coarse") + 1] == str(cfg.runs / "coarse" / "checkpoint.pt")
    assert first[first.index("--detector") + 1] == str(cfg.runs / "detector" / "checkpoint.pt")
    assert "--n-refiner-iters" not in first  # the inference default (InferenceConfig), written once


def test_the_two_inference_runs_go_side_by_side_on_one_core_each(tmp_path, monkeypatch):
    cfg = _cfg(tmp_path)
    runs: list = []
    monkeypatch.setattr(demo, "_run", lambda cmd, what, env=None: runs.append(("alone", cmd)))
    monkeypatch.setattr(demo, "_run_parallel", lambda cmds, whats, logs: runs.append(("parallel", cmds, logs)))
    monkeypatch.setattr(demo.json, "loads", lambda text: _scores(0.0))
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: "{}")
    demo.infer_and_eval(cfg, tmp_path / "data")
    kind, cmds, logs = runs[0]
    assert kind == "parallel" and len(cmds) == 2 and len(logs) == 2 and logs[0] != logs[1]
    for cmd in cmds:
        assert cmd[cmd.index("--threads") + 1] == "1" and "--no-progress" in cmd
    assert all(r[0] == "alone" and "eval" in r[1] for r in runs[1:])  # then the evaluations
    (cfg.out / "results").mkdir(parents=True)
    for name in ("cosyliteicp", "cosylite"):  # the detector run is done: the oracle run alone, on both cores
        (cfg.out / "results" / f"{name}_{cfg.dataset}-test.csv").write_text("")
    runs.clear()
    demo.infer_and_eval(cfg, tmp_path / "data")
    kind, cmd = runs[0]
    assert kind == "alone" and "oracle" in cmd and cmd[cmd.index("--threads") + 1] == "2"


def test_the_templates_are_rendered_ahead_half_of_the_objects_on_each_core(tmp_path, recorded):
    """Before the two inference runs (each would render every object's templates itself):
    ``cosy-lite templates`` of the test targets' objects, split in two, into infer's --templates-cache."""
    cfg = _cfg(tmp_path, train=False)
    root = tmp_path / "root"
    root.mkdir()
    targets = [{"scene_id": 0, "im_id": i, "obj_id": o, "inst_count": 1} for i, o in enumerate([5, 1, 9, 1, 3])]
    (root / "test_targets_bop19.json").write_text(json.dumps(targets))
    demo.prepare_templates(cfg, root)
    assert len(recorded) == 2 and all(_is(c, "templates") for c in recorded)
    assert [c[c.index("--objects") + 1] for c in recorded] == ["1,5", "3,9"]
    cache = demo.model_args(cfg)[demo.model_args(cfg).index("--templates-cache") + 1]
    assert all(c[c.index("--cache") + 1] == cache for c in recorded)
    recorded.clear()
    demo.prepare_templates(_cfg(tmp_path, start="coarse"), root)  # trained coarse start: no templates
    assert recorded == []


def test_with_reference_models_inference_uses_them_and_each_network_gets_a_short_run(tmp_path, recorded, monkeypatch):
    cfg = _cfg(tmp_path, train=False)
    monkeypatch.setattr(demo.json, "loads", lambda text: _scores(0.0))
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: "{}")
    demo.infer_and_eval(cfg, tmp_path / "root")
    infers = [c for c in recorded if _is(c, "infer")]
    assert len(infers) == 2
    for cmd in infers:
        assert cmd[cmd.index("--pretrained") + 1] == "ycbvsynth"
        assert not {"--coarse", "--refiner", "--detector", "--start"} & set(cmd)  # the set's own settings
        assert ("--exact-masks" in cmd) == ("oracle" in cmd)  # GT masks are exact; the detector's are not
    recorded.clear()
    monkeypatch.undo()
    monkeypatch.setattr(demo, "_run", lambda cmd, what, env=None: recorded.append(cmd))
    monkeypatch.setattr(demo, "_run_parallel", lambda cmds, whats, logs: recorded.extend(cmds))
    demo.short_training(cfg, tmp_path / "root")
    assert [c[c.index("--model") + 1] for c in recorded] == ["detector", "coarse", "refiner"]
    det, coarse, refiner = recorded
    assert det[1:6] == ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    assert coarse[1:4] == refiner[1:4] == ["-m", "cosy_lite.cli", "train"]  # side by side, one core each
    assert det[6:9] == ["-m", "cosy_lite.cli", "train"]  # torchrun runs the package's module, not a script
    for cmd, m in zip(recorded, demo.MODELS):
        assert "loop.val_at_start=true" in cmd and f"loop.max_minutes={cfg.short_minutes[m]}" in cmd
        assert cmd[cmd.index("--out") + 1] == str(cfg.runs / "short" / m)  # not the from-scratch runs' folders
    recorded.clear()
    demo.short_training(cfg, tmp_path / "root")
    assert recorded == []  # done: skipped


def test_training_table_and_plot_show_the_loss_and_the_held_out_metric(tmp_path):
    logs = {}
    for m, (key, _) in demo.SHORT_VAL.items():
        logs[m] = {"train": [{"step": 5 * i, "loss/total": 2.0 / i} for i in range(1, 5)],
                   "val": [{"step": 0, key: 0.5}, {"step": 20, key: 0.25}]}
    table = demo.training_table(logs).splitlines()
    assert len(table) == 5 and table[2].startswith("| detector | 20 | 2.000 -> 0.500 | validation AP50 |")
    assert table[2].endswith("| 0.500 (step 0) -> 0.250 (step 20) |")
    demo.plot_training(logs, tmp_path / "training.png")
    assert (tmp_path / "training.png").stat().st_size > 10000


def test_every_step_runs_the_package_from_the_current_folder(tmp_path, recorded, monkeypatch):
    """No step names a file of the source tree: the commands are ``python -m cosy_lite.cli ...`` and the
    default folders are relative to the current folder."""
    cfg = demo.DemoConfig()
    assert not any(p.is_absolute() for p in (cfg.data_root, cfg.runs, cfg.out))
    monkeypatch.chdir(tmp_path)
    demo.prepare_dataset(cfg)
    monkeypatch.setattr(demo.json, "loads", lambda text: _scores(0.0))
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: "{}")
    demo.infer_and_eval(cfg, cfg.data_root / cfg.dataset)
    for cmd in recorded:
        assert cmd[0] == demo.sys.executable and cmd[1:3] == ["-m", "cosy_lite.cli"], cmd
        assert not any(a.endswith(".py") for a in cmd), cmd
    gen = recorded[0]
    assert _is(gen, "generate") and "--config" not in gen  # ycbvsynth: the generator's defaults


def test_quick_mode_runs_every_step_at_toy_size_in_its_own_folders(tmp_path, recorded, monkeypatch):
    import argparse

    monkeypatch.chdir(tmp_path)
    parser = argparse.ArgumentParser()
    demo.add_arguments(parser)
    seen = {}

    def stop(cfg):  # the configured demo, without running anything
        seen["cfg"] = cfg
        raise SystemExit(0)

    monkeypatch.setattr(demo, "prepare_dataset", stop)
    with pytest.raises(SystemExit):
        demo.run(parser.parse_args(["--quick"]))
    cfg = seen["cfg"]
    assert (cfg.data_root, cfg.runs, cfg.out) == (demo.QUICK["data_root"], demo.QUICK["runs"], demo.QUICK["out"])
    assert cfg.quick and cfg.vis == 1 and cfg.reference == "ycbvsynth"
    with pytest.raises(SystemExit):
        demo.run(parser.parse_args([]))
    assert (seen["cfg"].data_root, seen["cfg"].out, seen["cfg"].quick) == (Path("data"), Path("outputs"), False)
    with pytest.raises(SystemExit):
        demo.run(parser.parse_args(["--train"]))
    assert seen["cfg"].out == Path("outputs") / "train"

    monkeypatch.undo()
    monkeypatch.setattr(demo, "_run", lambda cmd, what, env=None: recorded.append(cmd))
    monkeypatch.setattr(demo, "_run_parallel", lambda cmds, whats, logs: recorded.extend(cmds))
    cfg.data_root, cfg.runs, cfg.out = tmp_path / "data", tmp_path / "runs", tmp_path / "out"
    demo.prepare_dataset(cfg)
    gen = recorded[0]
    assert all(o in gen for o in demo.QUICK_GENERATE) and gen.index("--splits") > gen.index(demo.QUICK_GENERATE[-1])
    assert f"train.n_images={demo.QUICK['short_train_images']}" in gen
    recorded.clear()
    demo.short_training(cfg, tmp_path / "root")
    assert [c[c.index("--model") + 1] for c in recorded] == list(demo.MODELS)
    for cmd, model in zip(recorded, demo.MODELS):
        quick = demo.QUICK_OVERRIDES[model]
        at = cmd.index(quick[0])
        assert cmd[at:at + len(quick)] == quick and at > cmd.index("data.val_images=10")  # after the short run's: they win
        assert "loop.steps=2" in cmd
