"""Bad configs and arguments at every entry point (``train.py``, ``infer.py``, ``cosy-lite``): one
line naming the file or override, the key and what was expected, exit status 2, no traceback;
a traceback is kept for real bugs only."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from cosy_lite.config import load_config, packaged_config
from cosy_lite.errors import BopFormatError, ConfigError, run_reporting_errors

# (torchvision, imported by the training tasks, before anything renders: see cosy_lite/inference/predictor.py)
from cosy_lite.train.pose_task import PoseTrainConfig

ROOT = Path(__file__).resolve().parents[1]
DEMO = packaged_config("coarse", "demo.yaml")


def _train(capsys, *argv: str) -> tuple[int, str]:
    import train

    rc = train.main(["--dataset", "/nonexistent/tiny", "--model", "coarse", *argv])
    err = capsys.readouterr().err
    return rc, err


def _one_error(err: str, *words: str) -> None:
    lines = [s for s in err.splitlines() if s.strip()]
    assert len(lines) == 1 and "error:" in lines[0] and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], (w, lines[0])


@pytest.mark.parametrize("override, words", [
    ("loop.stepz=3", ["override 'loop.stepz=3'", "[loop.stepz]", "not in 'LoopConfig'"]),
    ("loop.steps=abc", ["override 'loop.steps=abc'", "[loop.steps]", "Integer"]),
    ("loop.batch_size=2.5", ["[loop.batch_size]", "Integer"]),
    ("loop.amp=maybe", ["[loop.amp]", "not a valid bool"]),
    ("loop.steps", ["override 'loop.steps'", "expected key=value"]),
    ("net.crop_resolution=5", ["[net.crop_resolution]", "list"]),
    ("loop=3", ["[loop]", "LoopConfig"]),
    ("loop.steps=0", ["override 'loop.steps=0'", "[loop.steps]", "expected at least 1"]),
    ("loop.steps=-5", ["[loop.steps]", "-5"]),
    ("loop.log_every=0", ["[loop.log_every]", "at least 1"]),
    ("loop.checkpoint_every=0", ["[loop.checkpoint_every]", "at least 1"]),
    ("loop.batch_size=0", ["[loop.batch_size]", "at least 1"]),
    ("loop.device=gpu", ["[loop.device]", "expected auto, cpu, cuda"]),
    ("optim.lr=0", ["[optim.lr]", "> 0"]),
    ("optim.lr=nan", ["[optim.lr]", "finite"]),
    ("optim.decay_factor=-1", ["[optim.decay_factor]", "> 0"]),
])
def test_train_py_bad_override(capsys, override: str, words: list[str]):
    rc, err = _train(capsys, override)
    assert rc == 2
    _one_error(err, "train.py: error:", *words)


def _yaml(tmp_path: Path, text: str | bytes) -> Path:
    path = tmp_path / "cfg.yaml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    return path


@pytest.mark.parametrize("text, words", [
    ("loop:\n  steps: [1\n", ["malformed YAML at line 3 column 1"]),
    ("- a\n- b\n", ["expected a mapping of config keys"]),
    ("loop:\n  stepz: 3\n", ["[loop.stepz]", "not in 'LoopConfig'"]),
    ("loop:\n  steps: many\n", ["[loop.steps]", "Integer"]),
    ("loop: 5\n", ["[loop]", "LoopConfig"]),
    ("optim:\n  lr: -0.1\n", ["[optim.lr]", "> 0"]),
    (b"loop:\n  device: \xff\xfe\n", ["not a UTF-8 text file"]),
    ("loop:\n  steps: !!python/object/apply:os.system [echo hi]\n",
     ["YAML tag refused at line 2 column 10", "python/object/apply:os.system"]),
], ids=["broken", "a-list", "unknown-key", "wrong-type", "wrong-shape", "bad-value", "not-utf8", "python-tag"])
def test_train_py_bad_config_file(tmp_path, capsys, text, words):
    path = _yaml(tmp_path, text)
    rc, err = _train(capsys, "--config", str(path))
    assert rc == 2
    _one_error(err, f"error: {path}", *words)


def test_train_py_missing_config_and_unknown_profile(tmp_path, capsys):
    rc, err = _train(capsys, "--config", str(tmp_path / "none.yaml"))
    assert rc == 2
    _one_error(err, f"{tmp_path / 'none.yaml'}: config file not found")
    rc, err = _train(capsys, "--config", str(tmp_path))  # a folder
    assert rc == 2
    _one_error(err, f"{tmp_path}: config file not found")
    rc, err = _train(capsys, "--profile", "huge")
    assert rc == 2
    _one_error(err, "huge.yaml [--profile]", "expected one of ['demo', 'full']")


def test_an_empty_config_file_means_the_defaults(tmp_path):
    assert load_config(PoseTrainConfig, _yaml(tmp_path, "")) == PoseTrainConfig()


def test_train_py_process_prints_no_traceback(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, str(ROOT / "train.py"), "--model", "refiner", "--dataset", str(tmp_path),
                        "loop.stepz=1"], capture_output=True, text=True, env=env, timeout=120, cwd=ROOT)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    _one_error(r.stderr, "[loop.stepz]")


def test_cosy_lite_generate_bad_override(tmp_path, capsys):
    from cosy_lite.cli import main

    rc = main(["generate", "--out", str(tmp_path / "d"), "train.n_imagez=3"])
    assert rc == 2
    _one_error(capsys.readouterr().err, "cosy-lite generate: error:", "[train.n_imagez]")
    assert not (tmp_path / "d").exists()


def _python_tag(marker: Path) -> str:
    """A YAML value that would run ``touch MARKER`` if it were loaded with PyYAML's unsafe loader."""
    return f"!!python/object/apply:os.system ['touch {marker}']"


@pytest.mark.parametrize("prog, key", [("train.py", "loop.steps"), ("cosy-lite generate", "train.n_images"),
                                       ("infer.py", "icp_settings.max_translation")],
                         ids=["train", "generate", "infer-set"])
def test_a_python_tag_in_an_override_is_one_message_and_never_runs(tmp_path, capsys, prog, key):
    import infer
    import train
    from cosy_lite.cli import main

    marker = tmp_path / "PWNED"
    override = f"{key}={_python_tag(marker)}"
    if prog == "train.py":
        rc = train.main(["--dataset", str(tmp_path / "none"), "--model", "refiner", override])
    elif prog == "cosy-lite generate":
        rc = main(["generate", "--out", str(tmp_path / "d"), override])
    else:
        rc = infer.main(["--dataset", str(tmp_path), "--coarse", "c.pt", "--detections", "oracle", "--icp",
                         "--set", override])
    assert rc == 2
    _one_error(capsys.readouterr().err, f"{prog}: error: ", f"command-line override {override!r} [{key}]: YAML tag "
               "refused at line 1 column 1: could not determine a constructor for the tag "
               "'tag:yaml.org,2002:python/object/apply:os.system'")
    assert not marker.exists(), "the override ran a command"
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("args, words", [
    (["--threads", "0"], "--threads 0: expected an integer >= 1"),
    (["--limit-images", "0"], "--limit-images 0: expected an integer >= 1"),
    (["--n-refiner-iters", "-1"], "--n-refiner-iters -1: expected an integer >= 0"),
    (["--vis", "-2"], "--vis -2: expected an integer >= 0"),
    (["--candidates", "0"], "--candidates 0: expected an integer >= 1"),
    (["--icp", "--icp-set", "max_translation=far"],
     "command-line override 'icp_settings.max_translation=far' [icp_settings.max_translation]"),
    (["--icp", "--icp-set", "verify_candidatez=false"], "[icp_settings.verify_candidatez]: Key 'verify_candidatez' not in"),
    (["--set", "n_candidates=many"], "command-line override 'n_candidates=many' [n_candidates]"),
    (["--settings", "missing.yaml"], "missing.yaml: config file not found"),
    (["--icp", "--icp-set", "iterations=[5]"], "max_correspondence_distances"),
])
def test_infer_py_bad_number(tmp_path, capsys, args, words):
    import infer

    rc = infer.main(["--dataset", str(tmp_path), "--coarse", "c.pt", "--detections", "oracle", *args])
    assert rc == 2
    _one_error(capsys.readouterr().err, words)


def test_exact_masks_are_refused_for_the_detectors_masks(tmp_path, capsys):
    """--exact-masks without --detections: the detector's masks are not exact (the settings lower their AR)."""
    import infer

    rc = infer.main(["--dataset", str(tmp_path), "--coarse", "c.pt", "--exact-masks"])
    assert rc == 2
    _one_error(capsys.readouterr().err, "--exact-masks: the detector's masks are not exact")
    from cosy_lite.cli import main

    assert main(["predict", "--rgb", "x.png", "--camera", "c.json", "--pretrained", "ycbvsynth", "--exact-masks",
                 "--out", str(tmp_path / "o")]) == 2
    _one_error(capsys.readouterr().err, "--exact-masks: the detector's masks are not exact")


def test_infer_py_missing_dataset(tmp_path, capsys):
    import infer

    rc = infer.main(["--dataset", str(tmp_path / "nothere"), "--coarse", "c.pt", "--detections", "oracle"])
    assert rc == 2
    _one_error(capsys.readouterr().err, f"{tmp_path / 'nothere'}: dataset folder not found")


# ----------------------------------------------------------------------------- the reporter


def test_reporter_turns_expected_errors_into_one_line(tmp_path, capsys):
    def config_error():
        raise ConfigError("a.yaml", "loop.steps", "0: expected\nat least 1")

    assert run_reporting_errors(config_error, "prog") == 2
    assert capsys.readouterr().err == "prog: error: a.yaml [loop.steps]: 0: expected at least 1\n"

    def os_error():
        open(tmp_path / "missing" / "file.txt")

    assert run_reporting_errors(os_error, "prog") == 2
    assert capsys.readouterr().err == f"prog: error: {tmp_path / 'missing' / 'file.txt'}: No such file or directory\n"

    def interrupted():
        raise KeyboardInterrupt

    assert run_reporting_errors(interrupted, "prog") == 130


def test_reporter_keeps_the_traceback_of_a_bug():
    with pytest.raises(ZeroDivisionError):
        run_reporting_errors(lambda: 1 // 0, "prog")
    with pytest.raises(KeyError):  # not an input error: a bug to see whole
        run_reporting_errors(lambda: {}["x"], "prog")

    def runtime_bug():
        raise RuntimeError("Caught ValueError in DataLoader worker process 0.\nValueError: a bug in a worker")

    with pytest.raises(RuntimeError):
        run_reporting_errors(runtime_bug, "prog")


class _BrokenImages(torch.utils.data.Dataset):
    def __len__(self):
        return 4

    def __getitem__(self, i):
        raise BopFormatError(f"/data/train_pbr/000000/rgb/{i:06d}.png", "", "cannot decode image")


def test_reporter_names_a_bad_file_read_in_a_data_loading_worker(capsys):
    """train.py's DataLoader workers re-raise a BopFormatError as a RuntimeError with a traceback text."""
    def read_all():
        for _ in torch.utils.data.DataLoader(_BrokenImages(), batch_size=2, num_workers=1):
            pass

    assert run_reporting_errors(read_all, "train.py") == 2
    _one_error(capsys.readouterr().err, "train.py: error: /data/train_pbr/000000/rgb/000000.png: cannot decode image",
               "(in a data loading worker)")


@pytest.mark.parametrize("model", ["refiner", "detector"])
def test_train_py_on_a_dataset_smaller_than_the_held_out_set(tmp_path, capsys, model):
    """A user's own small dataset (6 images) with the default data.val_images=20: one line naming the
    setting and the split folder, not a traceback from the splitter."""
    import train
    from cosy_lite.synth.generator import SynthConfig, generate

    root = tmp_path / "tiny"
    generate(load_config(SynthConfig, packaged_config("synth", "tiny.yaml"),
                         ["train.n_images=6", "train.views_per_layout=6", "test.n_images=1", "test.views_per_layout=1"]),
             root, progress=False)
    rc = train.main(["--dataset", str(root), "--model", model, "--out", str(tmp_path / "run"), "loop.steps=1"])
    err = capsys.readouterr().err
    assert rc == 2
    _one_error(err, "[data.val_images]", "20 images held out", f"{root / 'train_pbr'} has only 6", "N < 6")
