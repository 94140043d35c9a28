"""The strong RGB augmentation of CosyPose, one implementation for the pose networks and the detector.

Batched on tensors (CPU or GPU), each sample drawing its own parameters. What CosyPose does
(``cosypose/datasets/pose_dataset.py`` and ``detection_dataset.py``, ``augmentations.py``), in order:

1. background replacement, p=0.3: pixels where the "any object" mask is 0 are replaced by a
   background image (CosyPose: a PASCAL VOC photo; here :class:`~cosy_lite.data.backgrounds.BackgroundPool`);
2. with probability 0.8 the photometric block, each op with its own probability and a factor
   drawn uniformly in its range:

   ==========  ====  ==============  ==============================================
   op          p     range           PIL semantics reproduced here
   ==========  ====  ==============  ==============================================
   blur        0.4   sigma {1,2,3}   ``ImageFilter.GaussianBlur(radius)``, radius = std
   sharpness   0.3   [0, 50]         blend with the 3x3 SMOOTH image (borders kept)
   contrast    0.3   [0.2, 50]       blend with the mean gray level
   brightness  0.5   [0.1, 6]        blend with black (= scale)
   color       0.3   [0, 20]         blend with the grayscale image (saturation)
   ==========  ====  ==============  ==============================================

   "Blend" is PIL's ``ImageEnhance``: ``out = clamp(degenerate + f * (image - degenerate))``.
   The degenerate images come from ``torchvision.transforms.v2.functional`` (``adjust_*`` with
   factor 0, which mirror PIL); the blur is ``kornia.filters.gaussian_blur2d`` with per-sample sigma.
3. grayscale (CosyPose's ``gray_augmentation``, off by default; p=0.5 when switched on).

Differences from the CosyPose code, on purpose: its ``PillowBlur`` never reads its ``p`` (the blur
runs every time the block runs); we apply it with the declared p=0.4 as MegaPose/HappyPose do.
Values stay float between ops instead of being rounded to uint8 after each PIL call.
Depth augmentations are off (RGB only), as in CosyPose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
import torchvision.transforms.v2.functional as TF
from torch import Tensor

from cosy_lite.data.backgrounds import BackgroundPool


@dataclass
class AugmentationConfig:
    """Probabilities and factor ranges; defaults are CosyPose's."""

    enabled: bool = True
    p_background: float = 0.3  # replace mask-0 pixels by a background image
    background_photo_fraction: float = 0.5  # share of photos (vs procedural textures) among backgrounds
    p_photometric: float = 0.8  # probability that the photometric block runs at all
    p_blur: float = 0.4
    blur_sigma: tuple[int, int] = (1, 3)  # integer std [px], both ends included
    p_sharpness: float = 0.3
    sharpness: tuple[float, float] = (0.0, 50.0)
    p_contrast: float = 0.3
    contrast: tuple[float, float] = (0.2, 50.0)
    p_brightness: float = 0.5
    brightness: tuple[float, float] = (0.1, 6.0)
    p_color: float = 0.3
    color: tuple[float, float] = (0.0, 20.0)
    p_gray: float = 0.0  # CosyPose: 0.5 when gray_augmentation is on


# ----------------------------------------------------------------------------- ops on float [N,3,H,W] in [0,1]


def blend(images: Tensor, degenerate: Tensor, factors: Tensor) -> Tensor:
    """PIL ``ImageEnhance``: ``clamp(degenerate + f * (images - degenerate), 0, 1)``; factors [N]."""
    f = factors.to(images.dtype).view(-1, 1, 1, 1)
    return (degenerate + f * (images - degenerate)).clamp_(0.0, 1.0)


def smooth(images: Tensor) -> Tensor:
    """PIL's ``ImageFilter.SMOOTH`` (3x3 kernel [[1,1,1],[1,5,1],[1,1,1]]/13), border pixels kept.

    Equals ``torchvision...adjust_sharpness(images, 0)``; written as a 3x3 mean (``avg_pool2d``)
    because a depthwise convolution is ~6x slower on CPU.
    """
    out = images.clone()
    inner = images[..., 1:-1, 1:-1]
    out[..., 1:-1, 1:-1] = (9.0 * F.avg_pool2d(images, 3, stride=1) + 4.0 * inner) / 13.0
    return out


def adjust_sharpness(images: Tensor, factors: Tensor) -> Tensor:
    return blend(images, smooth(images), factors)


def adjust_contrast(images: Tensor, factors: Tensor) -> Tensor:
    return blend(images, TF.adjust_contrast(images, 0.0), factors)


def adjust_brightness(images: Tensor, factors: Tensor) -> Tensor:
    return blend(images, torch.zeros_like(images), factors)


def adjust_color(images: Tensor, factors: Tensor) -> Tensor:
    return blend(images, TF.adjust_saturation(images, 0.0), factors)


def gaussian_matrices(n: int, sigmas: Tensor) -> Tensor:
    """[N,n,n] matrices ``G`` with ``G @ v`` = the 1D Gaussian blur of ``v`` [n] with std
    ``sigmas[i]`` (kernel support 3 x the largest sigma, normalised, edge values replicated)."""
    r = max(1, math.ceil(3.0 * float(sigmas.max())))
    offsets = torch.arange(-r, r + 1, dtype=sigmas.dtype, device=sigmas.device)
    k = torch.exp(-0.5 * (offsets[None] / sigmas[:, None]) ** 2)  # [N,2r+1]
    k = k / k.sum(dim=1, keepdim=True)
    steps = torch.arange(-r, r + 1, device=sigmas.device)
    src = (torch.arange(n, device=sigmas.device)[:, None] + steps[None]).clamp_(0, n - 1)  # [n,2r+1]
    G = torch.zeros((len(sigmas), n, n), dtype=sigmas.dtype, device=sigmas.device)
    return G.scatter_add_(2, src.expand(len(sigmas), -1, -1), k[:, None, :].expand(-1, n, -1))


def gaussian_blur(images: Tensor, sigmas: Tensor) -> Tensor:
    """Gaussian blur with a per-image std ``sigmas`` [N] in pixels (edge pixels replicated).

    Separable, as two batched matrix products (rows then columns): one call for all sigmas, and
    on CPU ~3x faster than a depthwise convolution with the 19-tap kernel of sigma = 3.
    """
    s = sigmas.to(device=images.device, dtype=images.dtype)
    H, W = images.shape[-2:]
    out = images @ gaussian_matrices(W, s).transpose(1, 2)[:, None]  # blur along x
    out = gaussian_matrices(H, s)[:, None] @ out  # blur along y
    return out.clamp_(0.0, 1.0)


def to_gray(images: Tensor, factors: Tensor) -> Tensor:  # noqa: ARG001 (same signature as the others)
    return TF.rgb_to_grayscale(images, num_output_channels=3)


# name -> (function, probability field, range field); applied in this order.
PHOTOMETRIC_OPS: dict[str, tuple[Callable[[Tensor, Tensor], Tensor], str, str | None]] = {
    "blur": (gaussian_blur, "p_blur", "blur_sigma"),
    "sharpness": (adjust_sharpness, "p_sharpness", "sharpness"),
    "contrast": (adjust_contrast, "p_contrast", "contrast"),
    "brightness": (adjust_brightness, "p_brightness", "brightness"),
    "color": (adjust_color, "p_color", "color"),
    "gray": (to_gray, "p_gray", None),
}
INTEGER_RANGES = {"blur_sigma"}


# ----------------------------------------------------------------------------- the augmentation


class StrongAugmentation:
    """CosyPose's strong augmentation on batches.

    Args:
        cfg: probabilities and ranges.
        backgrounds: the background source; a ``BackgroundPool(seed=0)`` is made on first use.

    Call with ``images`` [B,3,H,W] (uint8, or float in [0,1]) and ``masks_any`` [B,H,W] bool (pixels
    of any object, kept by background replacement; None skips background replacement). Returns a
    new tensor of the same dtype, shape and device. Randomness comes from ``generator`` (a CPU
    ``torch.Generator``; None: torch's global RNG, which DataLoader workers seed differently).
    The number of random draws does not depend on the image content, so a seed fixes the result.
    """

    def __init__(self, cfg: AugmentationConfig | None = None, backgrounds: BackgroundPool | None = None):
        self.cfg = cfg if cfg is not None else AugmentationConfig()
        self._backgrounds = backgrounds
        p_fields = ["p_background", "p_photometric"] + [p for _, p, _ in PHOTOMETRIC_OPS.values()]
        for field in p_fields:
            p = getattr(self.cfg, field)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"AugmentationConfig.{field}: probability must be in [0, 1], got {p}")
        for _, _, range_field in PHOTOMETRIC_OPS.values():
            if range_field is not None:
                lo, hi = getattr(self.cfg, range_field)
                if not 0.0 <= lo <= hi:
                    raise ValueError(f"AugmentationConfig.{range_field}: need 0 <= low <= high, got ({lo}, {hi})")
        if self.cfg.blur_sigma[0] < 1:
            raise ValueError(f"AugmentationConfig.blur_sigma: the smallest sigma must be >= 1 px, got {self.cfg.blur_sigma}")

    @property
    def backgrounds(self) -> BackgroundPool:
        if self._backgrounds is None:
            self._backgrounds = BackgroundPool(seed=0, photo_fraction=self.cfg.background_photo_fraction)
        return self._backgrounds

    def __call__(self, images: Tensor, masks_any: Tensor | None = None,
                 generator: torch.Generator | None = None) -> Tensor:
        self._check(images, masks_any)
        if not self.cfg.enabled or images.shape[0] == 0:
            return images.clone()
        is_uint8 = images.dtype == torch.uint8
        x = images.float() / 255.0 if is_uint8 else images.clone()
        # in float32 whatever the caller's autocast (training steps run under bf16 autocast on GPUs:
        # kornia's ops then return bf16, which cannot be written back into the float32 batch)
        with torch.autocast(x.device.type, enabled=False):
            if masks_any is not None:
                self._replace_backgrounds(x, masks_any, generator)
            self._photometric(x, generator)
        if is_uint8:
            return (x * 255.0).round_().clamp_(0, 255).to(torch.uint8)
        return x.to(images.dtype)

    @staticmethod
    def _check(images: Tensor, masks_any: Tensor | None) -> None:
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"StrongAugmentation: images must be [B,3,H,W], got {tuple(images.shape)}")
        if images.dtype != torch.uint8 and not images.is_floating_point():
            raise ValueError(f"StrongAugmentation: images must be uint8 or float, got {images.dtype}")
        want = (images.shape[0], *images.shape[2:])
        if masks_any is not None and tuple(masks_any.shape) != want:
            raise ValueError(f"StrongAugmentation: masks_any must be [B,H,W] = {want}, got {tuple(masks_any.shape)}")

    def _replace_backgrounds(self, x: Tensor, masks_any: Tensor, generator: torch.Generator | None) -> None:
        """In place on float ``x`` [B,3,H,W]: mask-0 pixels of a random subset replaced (p_background)."""
        B, _, H, W = x.shape
        replace = torch.rand(B, generator=generator) < self.cfg.p_background
        seed = int(torch.randint(0, 2**62, (1,), generator=generator))
        if not replace.any():
            return
        idx = replace.nonzero().flatten()
        bg = self.backgrounds.sample(len(idx), H, W, np.random.default_rng(seed)).to(x.device, x.dtype) / 255.0
        keep = masks_any[idx.to(masks_any.device)].to(x.device).unsqueeze(1)
        idx = idx.to(x.device)
        x[idx] = torch.where(keep, x[idx], bg)

    def _photometric(self, x: Tensor, generator: torch.Generator | None) -> None:
        """In place on float ``x``: with p_photometric, each op of PHOTOMETRIC_OPS with its own p."""
        B = x.shape[0]
        cfg = self.cfg
        block = torch.rand(B, generator=generator) < cfg.p_photometric
        for fn, p_field, range_field in PHOTOMETRIC_OPS.values():
            apply = block & (torch.rand(B, generator=generator) < getattr(cfg, p_field))
            if range_field is None:
                factors = torch.zeros(B)
            elif range_field in INTEGER_RANGES:
                lo, hi = getattr(cfg, range_field)
                factors = torch.randint(int(lo), int(hi) + 1, (B,), generator=generator).float()
            else:
                lo, hi = getattr(cfg, range_field)
                factors = lo + (hi - lo) * torch.rand(B, generator=generator)
            if apply.any():
                idx = apply.nonzero().flatten()
                on = idx.to(x.device)
                x[on] = fn(x[on], factors[idx].to(x.device))
