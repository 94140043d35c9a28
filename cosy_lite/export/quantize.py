"""Dynamic 8-bit quantisation of the exported pose networks (onnxruntime.quantization).

Weights are stored as 8-bit integers, activations are quantised per call from their observed range
(no calibration data). The cost in accuracy is measured right away: the quantised and the fp32
graph run on the same random batch and the largest output difference is recorded in the
manifest entry (``check.max_abs_diff_vs_fp32``, ``check.relative_rms_error``). Unsigned weights (``QUInt8``) are the default:
on the project's x86 CPU onnxruntime's ``ConvInteger`` ran them ~2x faster than signed ones, at
the same error; both were slower than fp32 there (see ``bench/RESULTS.md``).
"""

from __future__ import annotations

import copy
import tempfile
from pathlib import Path
from typing import Any, Callable, cast

import numpy as np

from cosy_lite.export.manifest import ModelEntry, file_digest, metadata_of, write_metadata

CHECK_BATCH = 8


def quantize_pose_net_int8(src: Path, dst: Path, entry: ModelEntry, config: dict[str, Any],
                           signed_weights: bool = False, seed: int = 0) -> ModelEntry:
    """Write the dynamically quantised copy of the exported pose network ``src`` (manifest entry
    ``entry``) to ``dst``; returns its entry (``quantization = "int8"``)."""
    import onnxruntime as ort
    from onnxruntime.quantization import QuantType, quantize_dynamic
    from onnxruntime.quantization.shape_inference import quant_pre_process

    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)  # shapes + folding, as recommended
        quantize_dynamic(str(pre), str(dst), weight_type=QuantType.QInt8 if signed_weights else QuantType.QUInt8)
    out = copy.deepcopy(entry)
    out.file, out.quantization, out.source = dst.name, "int8", f"{entry.source} (quantised from {src.name})"
    write_metadata(dst, metadata_of(out, config))
    out.bytes, out.sha256 = file_digest(dst)
    shape = cast(list[int], entry.input_shape[1:])  # [6, h, w]: only the batch axis of a pose network is named
    x = np.random.default_rng(seed).random((CHECK_BATCH, *shape), dtype=np.float32)
    runs = [ort.InferenceSession(str(p), providers=["CPUExecutionProvider"]).run(None, {entry.input_name: x})[0]
            for p in (src, dst)]
    out.check = {"batch": CHECK_BATCH, "max_abs_diff_vs_fp32": float(np.abs(runs[1] - runs[0]).max()),
                 "max_abs_output": float(np.abs(runs[0]).max()),
                 "relative_rms_error": relative_rms_error(runs[1], runs[0])}
    return out


def relative_rms_error(out: np.ndarray, ref: np.ndarray) -> float:
    """RMS of ``out - ref`` over the RMS of ``ref``: the size of the quantisation noise relative to the
    signal (0: equal; about 1.4: an unrelated output of the same size)."""
    ref64 = ref.astype(np.float64)
    return float(np.sqrt(np.mean((out.astype(np.float64) - ref64) ** 2) / max(float(np.mean(ref64 ** 2)), 1e-30)))


# name -> quantiser(src, dst, fp32 entry, config) -> entry
QUANTIZERS: dict[str, Callable[[Path, Path, ModelEntry, dict[str, Any]], ModelEntry]] = {
    "int8": quantize_pose_net_int8,
}
