"""Binary detection masks from Mask R-CNN's mask probabilities, one rule for the torch detector
(:mod:`cosy_lite.nets.detector`) and the onnxruntime one (:mod:`cosy_lite.inference.onnx_runtime`).

Pixels with probability above a threshold: :data:`MASK_THRESHOLD`, torchvision's 0.5, unless the caller
names another (the inference setting ``mask_threshold``: a reference set's ``pipeline.json`` chooses its
detector's). A weakly trained mask head
often stays below 0.5 everywhere for a detection whose box and class are right (measured on the demo
detector: bench/RESULTS.md, issue 13); such a mask is taken as the pixels of at least
:data:`PEAK_FRACTION` of its own peak, when that peak reaches :data:`MIN_PEAK`, instead of nothing.
numpy only.
"""

from __future__ import annotations

import numpy as np

MASK_THRESHOLD = 0.5  # mask probability -> bool (torchvision's)
PEAK_FRACTION = 0.5  # a mask empty at its threshold: the pixels at least this fraction of its peak ...
MIN_PEAK = 0.05  # ... if the peak is at least this (else it stays empty)


def binary_masks(probabilities: np.ndarray, threshold: float = MASK_THRESHOLD) -> np.ndarray:
    """``[N,H,W]`` bool masks of ``probabilities [N,H,W]`` (float in [0, 1]): above ``threshold``."""
    probabilities = np.asarray(probabilities)
    if probabilities.ndim != 3:
        raise ValueError(f"mask probabilities must be [N,H,W], got shape {probabilities.shape}")
    if not 0.0 < threshold < 1.0:
        raise ValueError(f"mask threshold must be in (0, 1), got {threshold!r}")
    masks = probabilities > threshold
    for i in np.flatnonzero(~masks.any(axis=(1, 2))):
        peak = float(probabilities[i].max()) if probabilities[i].size else 0.0
        if peak >= MIN_PEAK:
            masks[i] = probabilities[i] >= PEAK_FRACTION * peak
    return masks
