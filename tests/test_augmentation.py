"""The shared strong augmentation and the background pool: determinism, identity when off,
background replacement only outside the mask, and each op against Pillow's ImageEnhance/ImageFilter."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image, ImageEnhance, ImageFilter

from cosy_lite.data.augmentation import (
    PHOTOMETRIC_OPS,
    AugmentationConfig,
    StrongAugmentation,
    gaussian_blur,
    smooth,
)
from cosy_lite.data.backgrounds import PROCEDURAL, SKIMAGE_PHOTOS, BackgroundPool, load_skimage_photos

H, W = 48, 64
OFF = dict(p_background=0.0, p_photometric=1.0, p_blur=0.0, p_sharpness=0.0, p_contrast=0.0,
           p_brightness=0.0, p_color=0.0, p_gray=0.0)


def images(b: int = 4, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Smooth random colour images uint8 [b,3,H,W] and a rectangle "object" mask [b,H,W]."""
    g = torch.Generator().manual_seed(seed)
    low = torch.rand((b, 3, H // 8, W // 8), generator=g)
    x = torch.nn.functional.interpolate(low, size=(H, W), mode="bilinear", align_corners=False)
    x = (x * 200 + 20 * torch.rand((b, 3, H, W), generator=g)).round().clamp(0, 255).to(torch.uint8)
    m = torch.zeros((b, H, W), dtype=torch.bool)
    m[:, 10:30, 20:50] = True
    return x, m


def only(op: str, lo: float, hi: float | None = None, **kw) -> AugmentationConfig:
    """A config applying exactly ``op`` (factor range [lo, hi]) to every image."""
    cfg = AugmentationConfig(**OFF, **kw)
    setattr(cfg, f"p_{op}", 1.0)
    range_field = PHOTOMETRIC_OPS[op][2]
    if range_field is not None:
        setattr(cfg, range_field, (lo, lo if hi is None else hi))
    return cfg


def pil(x: torch.Tensor) -> Image.Image:
    return Image.fromarray(x.permute(1, 2, 0).numpy())


def from_pil(im: Image.Image) -> torch.Tensor:
    return torch.from_numpy(np.asarray(im).copy()).permute(2, 0, 1)


def test_deterministic_with_seed_and_varies_across_seeds():
    x, m = images(8)
    aug = StrongAugmentation(AugmentationConfig(p_background=0.5), BackgroundPool(seed=0))
    a = aug(x, m, torch.Generator().manual_seed(7))
    b = aug(x, m, torch.Generator().manual_seed(7))
    c = aug(x, m, torch.Generator().manual_seed(8))
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


@pytest.mark.parametrize("dtype", [torch.uint8, torch.float32])
def test_identity_when_all_probabilities_zero_or_disabled(dtype):
    x, m = images()
    x = x if dtype == torch.uint8 else x.float() / 255
    zero = AugmentationConfig(**OFF)
    zero.p_photometric = 0.0
    for cfg in (zero, AugmentationConfig(**OFF), AugmentationConfig(enabled=False)):
        y = StrongAugmentation(cfg)(x, m, torch.Generator().manual_seed(0))
        assert y.dtype == dtype and torch.equal(y, x)
        assert y.data_ptr() != x.data_ptr()  # a new tensor: the input is never modified


def test_background_replacement_changes_only_mask0_pixels():
    x, m = images(6)
    aug = StrongAugmentation(AugmentationConfig(**{**OFF, "p_background": 1.0}), BackgroundPool(seed=3))
    y = aug(x, m, torch.Generator().manual_seed(1))
    keep = m[:, None].expand_as(x)
    assert torch.equal(y[keep], x[keep])
    changed = (y != x).any(dim=1)[~m]  # background pixels with any channel changed
    assert changed.float().mean() > 0.9
    # Without a mask there is no replacement.
    assert torch.equal(aug(x, None, torch.Generator().manual_seed(1)), x)


def test_background_probability_is_per_image():
    x, m = images(200)
    aug = StrongAugmentation(AugmentationConfig(**{**OFF, "p_background": 0.3}), BackgroundPool(seed=0, photo_fraction=0.0))
    y = aug(x, m, torch.Generator().manual_seed(0))
    replaced = (y != x).flatten(1).any(dim=1).float().mean().item()
    assert 0.2 < replaced < 0.4


@pytest.mark.parametrize("op", ["blur", "sharpness", "contrast", "brightness", "color", "gray"])
@pytest.mark.parametrize("dtype", [torch.uint8, torch.float32])
def test_each_op_changes_image_and_keeps_dtype_and_range(op, dtype):
    x, m = images()
    x = x if dtype == torch.uint8 else x.float() / 255
    lo, hi = {"blur": (1, 3), "sharpness": (10, 50), "contrast": (2, 50), "brightness": (2, 6),
              "color": (3, 20), "gray": (0, 0)}[op]
    y = StrongAugmentation(only(op, lo, hi))(x, m, torch.Generator().manual_seed(0))
    assert y.dtype == dtype and y.shape == x.shape
    assert float(y.min()) >= 0 and float(y.max()) <= (255 if dtype == torch.uint8 else 1.0)
    diff = (y.float() - x.float()).abs().flatten(1).mean(dim=1)
    assert bool((diff > (0.5 if dtype == torch.uint8 else 0.5 / 255)).all()), diff


# factor, max abs difference to Pillow in grey levels (uint8), mean abs difference
PIL_CASES = {
    "brightness": (ImageEnhance.Brightness, 1.7, 1, 0.6),  # Pillow truncates, we round
    "contrast": (ImageEnhance.Contrast, 3.0, 3, 1.0),  # Pillow rounds the mean grey to an integer
    "color": (ImageEnhance.Color, 4.0, 4, 1.0),  # Pillow's fixed-point luma
    "sharpness": (ImageEnhance.Sharpness, 6.0, 3, 1.5),  # Pillow rounds the smoothed image first
}


@pytest.mark.parametrize("op", list(PIL_CASES))
def test_enhance_ops_match_pillow(op):
    fn, f, max_diff, mean_diff = PIL_CASES[op]
    x, m = images(2)
    y = StrongAugmentation(only(op, f))(x, m, torch.Generator().manual_seed(0)).int()
    ref = torch.stack([from_pil(fn(pil(xi)).enhance(f)) for xi in x]).int()
    d = (y - ref).abs()
    assert int(d.max()) <= max_diff and float(d.float().mean()) <= mean_diff


@pytest.mark.parametrize("sigma", [1, 2, 3])
def test_blur_matches_pillow_gaussian_blur(sigma):
    """Pillow's GaussianBlur(radius) is an extended-box approximation of a Gaussian of std radius."""
    x, m = images(2)
    y = StrongAugmentation(only("blur", sigma))(x, m, torch.Generator().manual_seed(0)).float()
    ref = torch.stack([from_pil(pil(xi).filter(ImageFilter.GaussianBlur(sigma))) for xi in x]).float()
    inner = (y - ref)[..., 8:-8, 8:-8].abs()  # borders: Pillow and we extend edges differently
    assert float(inner.mean()) < 1.0 and float(inner.max()) <= 6


def test_kernels_equal_library_references():
    import torchvision.transforms.v2.functional as TF
    from kornia.filters import gaussian_blur2d

    x = torch.rand(3, 3, 20, 30, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(smooth(x), TF.adjust_sharpness(x, 0.0), atol=1e-6)
    sig = torch.tensor([1.0, 2.0, 3.0])
    ref = torch.cat([gaussian_blur2d(x[i:i + 1], (19, 19), (s, s), border_type="replicate")
                     for i, s in enumerate(sig.tolist())])
    assert torch.allclose(gaussian_blur(x, sig), ref, atol=1e-5)


def test_factor_ranges_and_photometric_block_probability():
    """Brightness with factor range [0.5, 2] on a flat grey image: the output/input ratios are the
    factors; the block probability 0.8 leaves ~20% of images untouched."""
    x = torch.full((400, 3, 8, 8), 0.25)
    cfg = only("brightness", 0.5, 2.0)
    cfg.p_photometric = 0.8
    y = StrongAugmentation(cfg)(x, None, torch.Generator().manual_seed(0))
    ratio = y[:, 0, 0, 0] / 0.25
    untouched = (ratio == 1.0).float().mean().item()
    assert 0.14 < untouched < 0.26
    assert float(ratio.min()) >= 0.5 and float(ratio.max()) <= 2.0


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="p_contrast"):
        StrongAugmentation(AugmentationConfig(p_contrast=1.5))
    with pytest.raises(ValueError, match="brightness"):
        StrongAugmentation(AugmentationConfig(brightness=(2.0, 1.0)))
    with pytest.raises(ValueError, match="p_background"):
        StrongAugmentation(AugmentationConfig(p_background=-0.1))
    with pytest.raises(ValueError, match="blur_sigma"):
        StrongAugmentation(AugmentationConfig(blur_sigma=(0, 3)))
    x, m = images(2)
    with pytest.raises(ValueError, match="masks_any"):
        StrongAugmentation()(x, m[:1])
    with pytest.raises(ValueError, match=r"\[B,3,H,W\]"):
        StrongAugmentation()(x[:, :1])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_gpu_matches_cpu():
    x, m = images(8)
    aug = StrongAugmentation(AugmentationConfig(p_background=0.5), BackgroundPool(seed=0))
    a = aug(x, m, torch.Generator().manual_seed(5))
    b = aug(x.cuda(), m.cuda(), torch.Generator().manual_seed(5))
    assert b.device.type == "cuda"
    assert (a.int() - b.cpu().int()).abs().max() <= 1


# ----------------------------------------------------------------------------- backgrounds


def test_bundled_photos_load_offline():
    photos = load_skimage_photos()
    assert len(photos) == len(SKIMAGE_PHOTOS) == 12
    assert all(p.ndim == 3 and p.shape[2] == 3 and p.dtype == np.uint8 for p in photos)
    assert min(min(p.shape[:2]) for p in photos) >= 300


@pytest.mark.parametrize("name", list(PROCEDURAL))
def test_procedural_textures(name):
    im = PROCEDURAL[name](np.random.default_rng(0), 30, 40)
    assert im.shape == (30, 40, 3) and im.dtype == np.uint8
    assert im.std() > 1.0  # not a flat colour


def test_background_pool_samples():
    a = BackgroundPool(seed=4).sample(6, 37, 53)
    b = BackgroundPool(seed=4).sample(6, 37, 53)
    assert a.shape == (6, 3, 37, 53) and a.dtype == torch.uint8
    assert torch.equal(a, b)
    assert not torch.equal(a, BackgroundPool(seed=5).sample(6, 37, 53))
    assert len({bytes(x.numpy()) for x in a}) == 6  # six different images
    photos_only = BackgroundPool(seed=0, photo_fraction=1.0)
    assert photos_only.sample(2, 20, 20).shape == (2, 3, 20, 20)
    with pytest.raises(ValueError, match="photo_fraction"):
        BackgroundPool(photo_fraction=1.5)
