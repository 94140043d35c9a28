"""How the predictor runs its networks: timing per stage, precision, BatchNorm folding, denormals.

* :class:`Clock` adds up seconds per stage (waiting for the device first); :class:`TimedRenderer`
  and :func:`timed_net` put the renderer's and the networks' calls under their stage.
* :func:`inference_net`: a copy of a network for inference (BatchNorm folded, channels-last).
* :func:`flush_denormals`: denormal floats flushed to zero around a call (CPU).
"""

from __future__ import annotations

import copy
import time
from collections import defaultdict
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, Callable, Iterator

import torch
from torch import Tensor, nn

from cosy_lite.nets.batchnorm_folding import batchnorm_folded

if TYPE_CHECKING:
    from cosy_lite.render.renderer import Renderer


class Clock:
    """Accumulates seconds per key; waits for the device before reading the clock (CUDA is asynchronous)."""

    def __init__(self, device: torch.device):
        self.device = device
        self.seconds: dict[str, float] = defaultdict(float)

    def sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    @contextmanager
    def __call__(self, key: str) -> Iterator[None]:
        self.sync()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.sync()
            self.seconds[key] += time.perf_counter() - t0


class TimedRenderer:
    """A renderer whose ``render`` / ``render_tensors`` calls are timed under "render"."""

    def __init__(self, renderer: Renderer, clock: Clock):
        self.renderer, self.clock = renderer, clock

    def render(self, *args: Any, **kwargs: Any):
        with self.clock("render"):
            return self.renderer.render(*args, **kwargs)

    def render_tensors(self, *args: Any, **kwargs: Any):
        with self.clock("render"):
            return self.renderer.render_tensors(*args, **kwargs)


# name -> autocast dtype of the pose networks' forward pass (None: full fp32)
AUTOCAST_DTYPES: dict[str, torch.dtype | None] = {"fp32": None, "bf16": torch.bfloat16}


def timed_net(net: nn.Module | Callable[[Tensor], Tensor], clock: Clock, channels_last: bool, precision: str):
    """``net`` as a function of ``[B,6,h,w]`` float32 -> ``[B,9]`` float32, timed under "networks".
    A ``net`` that is not a torch module (an onnxruntime session) is only timed."""
    if not isinstance(net, nn.Module):
        def run_plain(x: Tensor) -> Tensor:
            with clock("networks"):
                return net(x).float()

        return run_plain
    dtype = AUTOCAST_DTYPES[precision]
    memory_format = torch.channels_last if channels_last else torch.contiguous_format

    def run(x: Tensor) -> Tensor:
        with clock("networks"), torch.autocast(x.device.type, dtype=dtype or torch.float32, enabled=dtype is not None):
            return net(x.contiguous(memory_format=memory_format)).float()

    return run


def inference_net(net: nn.Module, device: torch.device, channels_last: bool = True, fuse_bn: bool = True,
                  example_shape: tuple[int, ...] | None = None) -> nn.Module:
    """A copy of a network for inference on ``device``, in eval mode: BatchNorm folded into the
    convolutions (:func:`~cosy_lite.nets.batchnorm_folding.batchnorm_folded`), optionally channels-last.
    The given module is left as it is. ``example_shape`` (e.g. a pose network's ``[2,6,h,w]``): the
    folded copy is kept only if it gives the unfolded copy's outputs on a random input of that shape
    (to 1e-3 of their largest magnitude), else the unfolded copy runs, with a warning."""
    out = copy.deepcopy(net).eval().to(device)
    if fuse_bn:
        out = batchnorm_folded(out, example_shape)
    return out.to(memory_format=torch.channels_last if channels_last else torch.contiguous_format)


@contextmanager
def flush_denormals() -> Iterator[None]:
    """Denormal floats flushed to zero on CPU (x86 arithmetic on them is ~100x slower; untrained
    nets produce many), back to PyTorch's default (off) afterwards."""
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)


