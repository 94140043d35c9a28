"""Detection masks from mask probabilities (``nets/detection_masks.py``): 0.5 as torchvision unless
another threshold is named, and a mask empty at its threshold taken at half its own peak instead of nothing."""

import numpy as np
import pytest

from cosy_lite.nets.detection_masks import binary_masks


def test_threshold_and_the_fallback_for_masks_empty_at_one_half():
    p = np.zeros((3, 4, 5), dtype=np.float32)
    p[0, 1:3, 1:4] = 0.9  # a confident mask: thresholded at 0.5 as it is
    p[0, 0, 0] = 0.3
    p[1, 1:3, 2:4] = 0.46  # peak 0.46 < 0.5 (the demo detector's typical empty mask): >= 0.23 kept
    p[1, 0, 0] = 0.2
    p[2, 2, 2] = 0.04  # peak under MIN_PEAK: stays empty
    m = binary_masks(p)
    assert m.dtype == bool and m.shape == p.shape
    assert m[0].sum() == 6 and not m[0, 0, 0]
    assert m[1].sum() == 4 and m[1, 1:3, 2:4].all() and not m[1, 0, 0]
    assert not m[2].any()
    assert binary_masks(np.zeros((0, 4, 5))).shape == (0, 4, 5)
    with pytest.raises(ValueError, match=r"\[N,H,W\]"):
        binary_masks(np.zeros((4, 5)))


def test_a_named_threshold_and_its_fallback():
    p = np.zeros((2, 4, 5), dtype=np.float32)
    p[0, 1:3, 1:4] = 0.9
    p[0, 0, :] = 0.3  # in at 0.275, out at 0.5
    p[1, 1, 1:3] = 0.26  # peak 0.26 under 0.275: half its peak, 0.13, and up
    p[1, 2, 1] = 0.14
    p[1, 3, 3] = 0.12
    m = binary_masks(p, 0.275)
    assert m[0].sum() == 6 + 5 and m[0, 0].all()
    assert m[1].sum() == 3 and m[1, 2, 1] and not m[1, 3, 3]
    assert binary_masks(p)[0].sum() == 6 and not binary_masks(p)[0, 0].any()  # the default stays 0.5
    for bad in (0.0, 1.0, float("nan")):
        with pytest.raises(ValueError, match="mask threshold"):
            binary_masks(p, bad)
