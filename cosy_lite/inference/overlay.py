"""Pictures of pose estimates: the models rendered at the estimated poses, drawn as contours over
the image (object colours, labelled ``obj_id score``), and the ground truth as thin white contours."""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

from cosy_lite.vis.overlay import draw_contour, draw_label, object_colour

if TYPE_CHECKING:
    from cosy_lite.render.renderer import Renderer

GT_COLOUR = (255, 255, 255)


def _silhouettes(renderer: Renderer, obj_ids: Sequence[int], TCO: np.ndarray, K: np.ndarray,
                 size: tuple[int, int]) -> np.ndarray:
    if len(obj_ids) == 0:
        return np.zeros((0, *size), dtype=bool)
    return renderer.render([int(i) for i in obj_ids], TCO, K, size, depth_only=True).mask


def draw_estimates(rgb: np.ndarray, K: np.ndarray, obj_ids: Sequence[int], TCO: np.ndarray, scores: Sequence[float],
                   renderer: Renderer, gt_obj_ids: Sequence[int] = (), gt_TCO: np.ndarray | None = None) -> np.ndarray:
    """``rgb [H,W,3]`` uint8 with the estimated poses ``TCO [N,4,4]`` (m) of ``obj_ids [N]`` as
    contours in object colours and, when given, the GT poses ``gt_TCO [G,4,4]`` as white contours.

    ``renderer``: renders full-size silhouettes (``render(ids, TCO, K, (H, W), depth_only=True)``).
    """
    H, W = rgb.shape[:2]
    K = np.asarray(K, dtype=np.float64)
    out = rgb
    if gt_TCO is not None and len(gt_obj_ids):
        for mask in _silhouettes(renderer, gt_obj_ids, np.asarray(gt_TCO), K, (H, W)):
            out = draw_contour(out, mask, GT_COLOUR, thickness=1)
    est = _silhouettes(renderer, obj_ids, np.asarray(TCO), K, (H, W))
    for obj_id, mask in zip(obj_ids, est):
        out = draw_contour(out, mask, object_colour(int(obj_id)), thickness=2)
    for obj_id, mask, score in zip(obj_ids, est, scores):
        ys, xs = np.nonzero(mask)
        if len(xs):
            out = draw_label(out, f"{int(obj_id)} {float(score):.2f}", (int(xs.mean()) - 12, int(ys.mean())),
                             object_colour(int(obj_id)))
    legend = "estimates: object colours" + (", GT: white" if gt_TCO is not None and len(gt_obj_ids) else "")
    return draw_label(out, legend, (6, 16), GT_COLOUR)
