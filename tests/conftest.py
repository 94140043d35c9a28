"""Shared fixtures: a small rendered synthetic BOP dataset (made once per test session)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent
sys.path.insert(0, str(TESTS))  # bop_fixtures, scorer_files, toy_task

# Every test computes with this many torch threads, whatever the machine has: float reductions split
# over threads round differently, so a tolerance measured here holds on a 2- or a 64-core machine.
# One: `make test` runs two pytest workers (pytest-xdist), one per core.
TEST_THREADS = 1


@pytest.fixture(scope="session", autouse=True)
def _own_cache(tmp_path_factory):
    """Templates, observations and meshes that commands keep between runs go to a folder of this test
    run ($COSY_LITE_CACHE), not to the user's ~/.cache."""
    import os

    before = os.environ.get("COSY_LITE_CACHE")
    os.environ["COSY_LITE_CACHE"] = str(tmp_path_factory.mktemp("cosy_lite_cache"))
    yield
    if before is None:
        os.environ.pop("COSY_LITE_CACHE", None)
    else:
        os.environ["COSY_LITE_CACHE"] = before


@pytest.fixture(autouse=True)
def _same_arithmetic_everywhere():
    """Each test starts from the same random state (Python, numpy, torch) and the same torch thread
    count, and leaves them as it found them: no test depends on the ones that ran before it."""
    import random

    import numpy as np

    torch = sys.modules.get("torch")  # not imported here: some tests check that commands load no torch
    threads = torch.get_num_threads() if torch is not None else None
    if torch is not None:
        torch.set_num_threads(TEST_THREADS)
        torch.manual_seed(0)
    random.seed(0)
    np.random.seed(0)
    yield
    if torch is not None and threads is not None:
        torch.set_num_threads(threads)


TINY_SYNTH = ["train.n_images=6", "train.views_per_layout=6", "test.n_images=2", "test.views_per_layout=2"]


@pytest.fixture(scope="session")
def tiny_synth_root(tmp_path_factory) -> Path:
    """``tiny`` synthetic dataset (objects 1, 2, 5, 8): 6 train_pbr images, 2 test images."""
    from cosy_lite.config import load_config, packaged_config
    from cosy_lite.synth.generator import SynthConfig, generate

    root = tmp_path_factory.mktemp("synth") / "tiny"
    generate(load_config(SynthConfig, packaged_config("synth", "tiny.yaml"), TINY_SYNTH), root, progress=False)
    return root
