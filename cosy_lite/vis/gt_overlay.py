"""Pictures of BOP ground truth: GT poses re-rendered over an image, and contact sheets."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from cosy_lite.bop.dataset import BopDataset, ImageRecord
from cosy_lite.bop.io import load_mask
from cosy_lite.vis.overlay import draw_contour, draw_label, draw_mask, grid, object_colour

if TYPE_CHECKING:
    from cosy_lite.render.renderer import Renderer


def render_gt_overlay(ds: BopDataset, rec: ImageRecord, renderer: Renderer | None = None) -> np.ndarray:
    """The image with, per GT instance, its stored visible mask filled and the contour of the
    model re-rendered at the GT pose (so a wrong pose or a wrong mask shows).

    ``renderer``: of the dataset's ``models/`` (default: a :class:`GlRenderer` made and closed here).
    """
    from cosy_lite.render.renderer import GlRenderer

    rgb = ds.load_rgb(rec)
    h, w = rgb.shape[:2]
    if not rec.gt:
        return rgb
    owned: GlRenderer | None = None  # made here, so closed here
    if renderer is None:
        renderer = owned = GlRenderer.from_dataset(ds)
    try:
        depth = renderer.render([g.obj_id for g in rec.gt], np.stack([g.TCO for g in rec.gt]), rec.camera.K, (h, w),
                                depth_only=True).depth
    finally:
        if owned is not None:
            owned.close()
    out = rgb
    for k, g in enumerate(rec.gt):
        colour = object_colour(g.obj_id)
        visib_path = ds.mask_path(rec.split, rec.scene_id, rec.im_id, k, visib=True)
        if visib_path.is_file():
            out = draw_mask(out, load_mask(visib_path), colour)
        out = draw_contour(out, depth[k] > 0, colour)
    for k, g in enumerate(rec.gt):
        ys, xs = np.nonzero(depth[k] > 0)
        if len(xs):
            label = f"{g.obj_id}" + (f" v{rec.gt_info[k].visib_fract:.2f}" if rec.gt_info else "")
            out = draw_label(out, label, (int(xs.mean()) - 10, int(ys.mean())), object_colour(g.obj_id))
    return out


def contact_sheet(ds: BopDataset, split: str, n: int, seed: int = 0, cols: int = 4, scale: float = 0.5) -> np.ndarray:
    """``n`` random images of ``split`` with their stored visible-mask contours, tiled."""
    import cv2

    recs = [(s, i) for s in ds.scene_ids(split) for i in ds.image_ids(split, s)]
    rng = np.random.default_rng(seed)
    picks = [recs[k] for k in rng.choice(len(recs), size=min(n, len(recs)), replace=False)]
    tiles = []
    for scene_id, im_id in picks:
        rec = ds.image(split, scene_id, im_id)
        im = ds.load_rgb(rec)
        for k, g in enumerate(rec.gt):
            p = ds.mask_path(split, scene_id, im_id, k, visib=True)
            if p.is_file():
                im = draw_contour(im, load_mask(p), object_colour(g.obj_id))
        im = draw_label(im, f"{split}/{scene_id:06d}/{im_id:06d}", (6, 16), (255, 255, 255))
        tiles.append(cv2.resize(im, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA))
    return grid(tiles, cols)
