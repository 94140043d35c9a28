"""Draw masks, contours and labels over images (RGB uint8, OpenCV drawing)."""

from __future__ import annotations

import colorsys

import cv2
import numpy as np

HALO = (0, 0, 0)  # under every contour and label


def object_colour(obj_id: int) -> tuple[int, int, int]:
    """A stable, distinct RGB colour per object id (golden-ratio hues)."""
    h = (obj_id * 0.618033988749895) % 1.0
    r, g, b = colorsys.hsv_to_rgb(h, 0.85, 1.0)
    return int(r * 255), int(g * 255), int(b * 255)


def draw_mask(image: np.ndarray, mask: np.ndarray, colour: tuple[int, int, int], alpha: float = 0.35) -> np.ndarray:
    """Blend ``colour`` into ``image`` where ``mask`` is set (returns a new image)."""
    out = image.copy()
    out[mask] = (1 - alpha) * out[mask] + alpha * np.asarray(colour, np.float32)
    return out


def draw_contour(image: np.ndarray, mask: np.ndarray, colour: tuple[int, int, int], thickness: int = 2) -> np.ndarray:
    """The outline of ``mask`` in ``colour`` over a dark halo, so that it stays visible on any object
    (a white outline on a white or grey object was invisible)."""
    out = image.copy()
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, HALO, thickness + 4, lineType=cv2.LINE_AA)
    cv2.drawContours(out, contours, -1, colour, thickness, lineType=cv2.LINE_AA)
    return out


def draw_label(image: np.ndarray, text: str, xy: tuple[int, int], colour: tuple[int, int, int]) -> np.ndarray:
    out = image.copy()
    x, y = int(np.clip(xy[0], 0, image.shape[1] - 1)), int(np.clip(xy[1], 12, image.shape[0] - 1))
    cv2.putText(out, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, HALO, 3, cv2.LINE_AA)
    cv2.putText(out, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
    return out


def grid(images: list[np.ndarray], cols: int, pad: int = 4) -> np.ndarray:
    """Tile equally sized RGB images into a grid with white padding."""
    h, w = images[0].shape[:2]
    rows = (len(images) + cols - 1) // cols
    sheet = np.full((rows * (h + pad) + pad, cols * (w + pad) + pad, 3), 255, np.uint8)
    for k, im in enumerate(images):
        r, c = divmod(k, cols)
        sheet[pad + r * (h + pad): pad + r * (h + pad) + h, pad + c * (w + pad): pad + c * (w + pad) + w] = im
    return sheet
