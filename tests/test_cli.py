"""The ``cosy-lite`` command table: ``train`` and ``infer`` are sub-commands (the ``train.py`` /
``infer.py`` wrappers parse the same arguments), errors name the program they ran as, and parsing
loads no torch (``OMP_WAIT_POLICY`` is set before it loads)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from cosy_lite import cli

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("argv", [
    ["train", "--dataset", "tiny", "--model", "refiner", "--profile", "full", "--resume", "loop.steps=3", "seed=2"],
    ["infer", "--dataset", "ycbvsynth", "--pretrained", "ycbvsynth", "--icp", "--icp-set", "max_translation=0.1",
     "--detections", "oracle", "--limit-images", "2", "--out", "res"],
])
def test_the_wrappers_parse_exactly_the_sub_command_arguments(argv):
    full = vars(cli.build_parser().parse_args(argv))
    alone = vars(cli.command_parser(argv[0], f"{argv[0]}.py").parse_args(argv[1:]))
    only = vars(cli.build_parser(only=argv[0]).parse_args(argv))
    assert full == alone == only and full["command"] == argv[0]


@pytest.mark.parametrize("prog, expected", [(None, "cosy-lite train: error:"), ("train.py", "train.py: error:")])
def test_expected_errors_are_one_line_under_the_program_name(capsys, prog, expected):
    rc = cli.main(["train", "--dataset", "/nonexistent/tiny", "--model", "coarse", "loop.stepz=1"], prog=prog)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith(expected) and "[loop.stepz]" in err[0], err


def test_parsing_every_command_loads_no_torch():
    code = ("import sys, cosy_lite.cli as c; c.build_parser(); [c.command_parser(n, n) for n in c.COMMANDS]; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'torchvision', 'cv2', 'open3d')))")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env, cwd=ROOT)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr
