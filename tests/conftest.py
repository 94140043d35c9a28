"""Shared fixtures: a small rendered synthetic BOP dataset (made once per test session)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent
sys.path.insert(0, str(TESTS))  # bop_fixtures, toy_task

TINY_SYNTH = ["train.n_images=6", "train.views_per_layout=6", "test.n_images=2", "test.views_per_layout=2"]


@pytest.fixture(scope="session")
def tiny_synth_root(tmp_path_factory) -> Path:
    """``tiny`` synthetic dataset (objects 1, 2, 5, 8): 6 train_pbr images, 2 test images."""
    from cosy_lite.config import load_config, packaged_config
    from cosy_lite.synth.generator import SynthConfig, generate

    root = tmp_path_factory.mktemp("synth") / "tiny"
    generate(load_config(SynthConfig, packaged_config("synth", "tiny.yaml"), TINY_SYNTH), root, progress=False)
    return root
