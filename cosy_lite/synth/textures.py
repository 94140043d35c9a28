"""Random textures for the walls and floor of the synthetic scenes.

Sources: the images that ship inside scikit-image (``skimage.data``, no download: brick, grass,
gravel, ... and a few colour photos) and procedural fractal noise, tiles and stripes. One kind is
drawn per surface from a lookup table; every texture is randomly tinted.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Callable

import cv2
import numpy as np

GRAY_TEXTURES = ("brick", "grass", "gravel", "camera", "moon", "text", "page", "coins", "checkerboard")
PHOTOS = ("astronaut", "coffee", "chelsea", "rocket", "hubble_deep_field", "immunohistochemistry", "colorwheel", "cat")


@lru_cache(maxsize=None)
def _skimage_image(name: str) -> np.ndarray:
    import skimage.data

    im = getattr(skimage.data, name)()
    if im.dtype != np.uint8:
        im = (255 * (im - im.min()) / max(float(np.ptp(im)), 1e-6)).astype(np.uint8)
    if im.ndim == 3:
        im = im[:, :, :3]
    return im


def _random_colour(rng: np.random.Generator) -> np.ndarray:
    hsv = np.array([[[rng.integers(0, 180), rng.integers(0, 200), rng.integers(60, 256)]]], np.uint8)
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0].astype(np.float32) / 255.0


def _fractal_noise(rng: np.random.Generator, size: int, octaves: int = 5) -> np.ndarray:
    """Value noise summed over octaves, in [0, 1], [size, size]."""
    out = np.zeros((size, size), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        cells = 2 ** (o + 2)
        grid = rng.random((cells, cells)).astype(np.float32)
        out += amp * cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= 0.5
    out /= total
    return np.clip((out - out.min()) / max(float(np.ptp(out)), 1e-6), 0, 1)


def _two_colour(rng: np.random.Generator, pattern: np.ndarray) -> np.ndarray:
    c0, c1 = _random_colour(rng), _random_colour(rng)
    return pattern[:, :, None] * c0 + (1 - pattern[:, :, None]) * c1


def _noise(rng: np.random.Generator, size: int) -> np.ndarray:
    return _two_colour(rng, _fractal_noise(rng, size))


def _tiles(rng: np.random.Generator, size: int) -> np.ndarray:
    n = int(rng.integers(2, 12))
    ij = np.indices((size, size)) * n // size
    checker = ((ij[0] + ij[1]) % 2).astype(np.float32)
    grout = (np.indices((size, size)) % (size // n) < max(1, size // (n * 20))).any(0)
    pattern = np.where(grout, 0.5, checker) * 0.8 + 0.2 * _fractal_noise(rng, size, 3)
    return _two_colour(rng, pattern)


def _stripes(rng: np.random.Generator, size: int) -> np.ndarray:
    freq = rng.uniform(2, 20)
    angle = rng.uniform(0, np.pi)
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    wave = 0.5 + 0.5 * np.sin(2 * np.pi * freq * (x * np.cos(angle) + y * np.sin(angle)) + 4 * _fractal_noise(rng, size, 3))
    return _two_colour(rng, wave)


def _gray_image(rng: np.random.Generator, size: int) -> np.ndarray:
    im: np.ndarray = _skimage_image(GRAY_TEXTURES[rng.integers(len(GRAY_TEXTURES))]).astype(np.float32) / 255.0
    im = cv2.resize(im if im.ndim == 2 else im.mean(2), (size, size), interpolation=cv2.INTER_AREA)
    return im[:, :, None] * _random_colour(rng)[None, None, :] * rng.uniform(1.0, 1.6)


def _photo(rng: np.random.Generator, size: int) -> np.ndarray:
    im: np.ndarray = _skimage_image(PHOTOS[rng.integers(len(PHOTOS))]).astype(np.float32) / 255.0
    im = cv2.resize(im, (size, size), interpolation=cv2.INTER_AREA)
    return im * (0.6 + 0.4 * _random_colour(rng))


TEXTURE_KINDS: dict[str, Callable[[np.random.Generator, int], np.ndarray]] = {
    "noise": _noise,
    "tiles": _tiles,
    "stripes": _stripes,
    "gray_image": _gray_image,
    "photo": _photo,
}


def random_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """A random RGB uint8 texture [size, size, 3]."""
    kinds = list(TEXTURE_KINDS)
    tex = TEXTURE_KINDS[kinds[rng.integers(len(kinds))]](rng, size)
    return (np.clip(tex, 0, 1) * 255).astype(np.uint8)
