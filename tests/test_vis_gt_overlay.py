"""GT overlay: the GT models re-rendered (by the one renderer) as contours where the GT boxes project."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from bop_fixtures import NAME, write_tiny_bop

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.render.renderer import GlRenderer
from cosy_lite.vis.gt_overlay import render_gt_overlay
from cosy_lite.vis.overlay import object_colour


def test_contours_lie_on_the_projected_gt_boxes(tmp_path: Path):
    ds = BopDataset(write_tiny_bop(tmp_path), NAME)
    rec = ds.image("test", 0, 0)
    rgb = ds.load_rgb(rec)
    out = render_gt_overlay(ds, rec)
    assert out.shape == rgb.shape and out.dtype == np.uint8
    for g, info in zip(rec.gt, rec.gt_info):
        ys, xs = np.nonzero(np.all(out == object_colour(g.obj_id), axis=-1))  # the contour's own pixels
        assert len(xs) > 100
        x, y, w, h = info.bbox_obj  # the projected model's box, written by the fixture
        assert xs.min() >= x - 3 and xs.max() <= x + w + 3 and ys.min() >= y - 3 and ys.max() <= y + h + 3
        assert xs.max() - xs.min() >= w - 6 and ys.max() - ys.min() >= h - 6  # the contour spans the box

    with GlRenderer.from_dataset(ds) as renderer:  # a caller's renderer: used, left open
        np.testing.assert_array_equal(render_gt_overlay(ds, rec, renderer), out)
        assert renderer.render([1], rec.gt[0].TCO[None], rec.camera.K, (48, 64), depth_only=True).depth.shape == (1, 48, 64)
