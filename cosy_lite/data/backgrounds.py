"""Background images for background replacement, from sources that install with the registries.

CosyPose pastes PASCAL VOC photos behind the objects; VOC is a download, so this pool mixes:

* **Photos bundled inside the scikit-image wheel** (``skimage/data/``, read directly from the
  package folder with OpenCV, never through ``skimage.data``'s fetchers, so nothing is downloaded).
  Only images whose licence is stated in their ``skimage.data`` docstring are used
  (see :data:`SKIMAGE_PHOTOS`): public domain (NASA, SpaceX), CC0, or "no known copyright
  restrictions". Grayscale photos are tinted with a random colour half of the time.
* **Procedural textures** made on the fly (:data:`PROCEDURAL`): multi-octave value noise,
  linear gradients, random shapes (rectangles, ellipses, lines, polygons), stripes/checkers.
  They give unlimited variety; photos give natural-image statistics.

Every sample is a random crop (random scale, the requested aspect ratio), random flip and resize
to ``H x W``. Nothing is read or generated at import; photos are loaded on the first sample.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import torch
from torch import Tensor

# file in skimage/data -> licence, as given by the docstring of the matching skimage.data function.
SKIMAGE_PHOTOS: dict[str, str] = {
    "astronaut.png": "NASA, public domain",
    "brick.png": "CC0 (CC0Textures)",
    "camera.png": "CC0 (Lav Varshney)",
    "chelsea.png": "CC0 (Stefan van der Walt)",
    "coffee.png": "CC0 (Rachel Michetti)",
    "coins.png": "Brooklyn Museum, no known copyright restrictions",
    "grass.png": "CC0 (DeviantArt linolafett)",
    "gravel.png": "CC0 (CC0Textures)",
    "hubble_deep_field.jpg": "NASA, public domain",
    "ihc.png": "CMMI, no known copyright restrictions",
    "retina.jpg": "CC0 (Mikael Haggstrom, Wikimedia)",
    "rocket.jpg": "SpaceX, public domain",
}


def skimage_data_dir() -> Path:
    """The folder of images shipped inside the installed scikit-image package."""
    import skimage

    return Path(skimage.__file__).parent / "data"


def load_skimage_photos(names: list[str] | None = None) -> list[np.ndarray]:
    """The bundled photos as RGB uint8 ``[H,W,3]`` arrays (grayscale ones repeated to 3 channels).

    Raises FileNotFoundError naming the file if one is missing from the installed package.
    """
    folder = skimage_data_dir()
    out = []
    for name in names if names is not None else list(SKIMAGE_PHOTOS):
        path = folder / name
        im = cv2.imread(str(path), cv2.IMREAD_COLOR) if path.is_file() else None
        if im is None:
            raise FileNotFoundError(f"{path}: background photo not found or unreadable in the scikit-image package")
        out.append(cv2.cvtColor(im, cv2.COLOR_BGR2RGB))
    return out


# ----------------------------------------------------------------------------- procedural textures


def _colours(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.integers(0, 256, size=(n, 3)).astype(np.float32)


def value_noise(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Multi-octave value noise between two random colours (and a little per-channel noise)."""
    acc = np.zeros((h, w), np.float32)
    amp, total = 1.0, 0.0
    cells = int(rng.integers(2, 8))
    for _ in range(int(rng.integers(2, 6))):
        grid = rng.random((cells, max(1, cells * w // h))).astype(np.float32)
        acc += amp * cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= float(rng.uniform(0.4, 0.7))
        cells *= 2
    t = np.clip(acc / total, 0, 1)[..., None]
    c0, c1 = _colours(rng, 2)
    im = c0 * (1 - t) + c1 * t + float(rng.uniform(0, 12)) * rng.standard_normal((h, w, 3), dtype=np.float32)
    return np.clip(im, 0, 255).astype(np.uint8)


def gradient(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A linear gradient at a random angle between two random colours, with mild noise."""
    a = rng.uniform(0, 2 * np.pi)
    s = np.arange(w, dtype=np.float32)[None] * np.cos(a) + np.arange(h, dtype=np.float32)[:, None] * np.sin(a)
    t = ((s - s.min()) / max(float(s.max() - s.min()), 1.0))[..., None]
    c0, c1 = _colours(rng, 2)
    im = c0 * (1 - t) + c1 * t + 4.0 * rng.standard_normal((h, w, 3), dtype=np.float32)
    return np.clip(im, 0, 255).astype(np.uint8)


def shapes(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Random filled/outlined rectangles, ellipses, lines and polygons on a random colour."""
    im: np.ndarray = np.empty((h, w, 3), np.uint8)
    im[:] = _colours(rng, 1)[0].astype(np.uint8)
    s = max(h, w)
    for _ in range(int(rng.integers(8, 40))):
        c = tuple(int(v) for v in _colours(rng, 1)[0])
        thick = -1 if rng.random() < 0.6 else int(rng.integers(1, 8))
        p = rng.integers(0, [w, h], size=(2, 2))
        kind = int(rng.integers(0, 4))
        if kind == 0:
            cv2.rectangle(im, tuple(map(int, p[0])), tuple(map(int, p[1])), c, thick)
        elif kind == 1:
            axes = tuple(int(v) for v in rng.integers(2, max(3, s // 4), size=2))
            cv2.ellipse(im, tuple(map(int, p[0])), axes, float(rng.uniform(0, 180)), 0, 360, c, thick)
        elif kind == 2:
            cv2.line(im, tuple(map(int, p[0])), tuple(map(int, p[1])), c, int(rng.integers(1, 10)))
        else:
            pts = rng.integers(0, [w, h], size=(int(rng.integers(3, 7)), 2)).astype(np.int32)
            cv2.fillPoly(im, [pts], c)
    if rng.random() < 0.5:
        im = cv2.GaussianBlur(im, (0, 0), float(rng.uniform(0.5, 3.0)))
    return im


def stripes(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Stripes or a checkerboard of two random colours at a random angle and period."""
    a = rng.uniform(0, np.pi)
    period = rng.uniform(4.0, max(8.0, max(h, w) / 4))
    x = np.arange(w, dtype=np.float32)[None] / period
    y = np.arange(h, dtype=np.float32)[:, None] / period
    u = x * np.cos(a) + y * np.sin(a)
    v = -x * np.sin(a) + y * np.cos(a)
    t = np.floor(u) % 2 if rng.random() < 0.5 else (np.floor(u) + np.floor(v)) % 2
    c0, c1 = _colours(rng, 2)
    return np.where(t[..., None] > 0, c1.astype(np.uint8), c0.astype(np.uint8))


PROCEDURAL: dict[str, Callable[[np.random.Generator, int, int], np.ndarray]] = {
    "noise": value_noise,
    "gradient": gradient,
    "shapes": shapes,
    "stripes": stripes,
}


# ----------------------------------------------------------------------------- pool


def random_crop_resize(rng: np.random.Generator, im: np.ndarray, h: int, w: int, min_scale: float = 0.3) -> np.ndarray:
    """A random crop of ``im`` with aspect ratio ``w/h`` covering [min_scale, 1] of the largest
    such crop, randomly flipped, resized to ``[h,w,3]``."""
    H, W = im.shape[:2]
    cw_max = min(W, H * w / h)
    scale = rng.uniform(min_scale, 1.0)
    cw = max(1, int(round(cw_max * scale)))
    ch = max(1, int(round(cw * h / w)))
    ch, cw = min(ch, H), min(cw, W)
    y0 = int(rng.integers(0, H - ch + 1))
    x0 = int(rng.integers(0, W - cw + 1))
    crop = im[y0:y0 + ch, x0:x0 + cw]
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
    if rng.random() < 0.5:
        crop = crop[::-1]
    interp = cv2.INTER_AREA if cw > w else cv2.INTER_LINEAR
    return cv2.resize(np.ascontiguousarray(crop), (w, h), interpolation=interp)


class BackgroundPool:
    """Random background images: bundled scikit-image photos and procedural textures.

    Args:
        seed: seed of the pool's own generator (used when ``sample`` gets no ``rng``).
        photo_fraction: probability that a sample is a photo (else a procedural texture).
        photos: file names in ``skimage/data`` (default: all of :data:`SKIMAGE_PHOTOS`).
    """

    def __init__(self, seed: int = 0, photo_fraction: float = 0.5, photos: list[str] | None = None):
        if not 0.0 <= photo_fraction <= 1.0:
            raise ValueError(f"BackgroundPool: photo_fraction must be in [0, 1], got {photo_fraction}")
        self.photo_fraction = photo_fraction
        self.photo_names = list(SKIMAGE_PHOTOS) if photos is None else list(photos)
        self._rng = np.random.default_rng(seed)
        self._photos: list[np.ndarray] | None = None
        self._gray: list[bool] = []

    @property
    def photos(self) -> list[np.ndarray]:
        """The photos, loaded on first use."""
        if self._photos is None:
            self._photos = load_skimage_photos(self.photo_names)
            self._gray = [
                bool(np.array_equal(p[..., 0], p[..., 1]) and np.array_equal(p[..., 1], p[..., 2])) for p in self._photos
            ]
        return self._photos

    def sample_numpy(self, height: int, width: int, rng: np.random.Generator | None = None) -> np.ndarray:
        """One background, RGB uint8 ``[height,width,3]``."""
        rng = self._rng if rng is None else rng
        if self.photo_names and rng.random() < self.photo_fraction:
            k = int(rng.integers(len(self.photos)))
            out = random_crop_resize(rng, self.photos[k], height, width)
            if self._gray[k] and rng.random() < 0.5:  # grayscale photo: tint it
                tint = rng.uniform(0.3, 1.0, size=3).astype(np.float32)
                out = (out.astype(np.float32) * tint).astype(np.uint8)
            return out
        names = list(PROCEDURAL)
        fn = PROCEDURAL[names[int(rng.integers(len(names)))]]
        # Generate at a random, mostly lower, resolution then crop/resize: varies the texture's
        # frequency content and keeps a 640x480 sample at a few ms.
        s = rng.uniform(0.3, 1.0)
        gh, gw = max(8, int(height * s)), max(8, int(width * s))
        return random_crop_resize(rng, fn(rng, gh, gw), height, width, min_scale=0.6)

    def sample(self, n: int, height: int, width: int, rng: np.random.Generator | None = None) -> Tensor:
        """``n`` backgrounds as a uint8 tensor ``[n,3,height,width]`` (CPU)."""
        if n == 0:
            return torch.zeros((0, 3, height, width), dtype=torch.uint8)
        ims = np.stack([self.sample_numpy(height, width, rng) for _ in range(n)])
        return torch.from_numpy(ims).permute(0, 3, 1, 2).contiguous()
