"""The VSD loop of :mod:`cosy_lite.eval.pose_errors` (numba, ``cache=True``: compiled once per
install, then loaded): both visibility masks, their union and the costs under each tolerance in one
pass over the union of two windows, the distances computed at each pixel, where numpy made a dozen
full-size temporaries per pair.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _distance(depth_map, r, c, x0, y0, depths, X, Y):
    """float64 value of ``depth_map`` at image pixel (r, c) of a window at (x0, y0) (0 outside it);
    with ``depths`` the distance of that depth from the camera centre, as the toolkit's
    ``depth_im_to_dist_im_fast``: ``sqrt((X d)^2 + (Y d)^2 + d^2)``."""
    h, w = depth_map.shape
    if not (y0 <= r < y0 + h and x0 <= c < x0 + w):
        return 0.0
    d = np.float64(depth_map[r - y0, c - x0])
    if depths and d != 0.0:
        d = np.sqrt((X * d) ** 2 + (Y * d) ** 2 + d ** 2)
    return d


@njit(cache=True, nogil=True)
def vsd_counts(map_e, ex0, ey0, map_g, gx0, gy0, map_test, depths, fx, fy, cx, cy,
               x0, y0, x1, y1, delta, taus, diameter, matches):
    """Over the image pixels ``y0:y1, x0:x1``: ``matches[k]`` += pixels of ``V_g & V_e`` with cost
    < ``taus[k]``; returns ``#(V_g | V_e)``.

    ``map_e`` / ``map_g``: maps of windows at (ex0, ey0) / (gx0, gy0) (0 outside them); ``map_test``:
    the whole test image at (0, 0). Distance maps, or with ``depths`` depth maps (m) whose
    distances are computed with ``X = (x - cx) / fx``, ``Y = (y - cy) / fy`` at pixel indices.
    Visibility as the toolkit's: float32 differences against float32 ``delta``; cost
    ``|dist_g - dist_e|`` in float64, divided by ``diameter`` if > 0.
    """
    delta32 = np.float32(delta)
    union = 0
    for r in range(y0, y1):
        Y = (r - cy) / fy
        for c in range(x0, x1):
            X = (c - cx) / fx
            de = _distance(map_e, r, c, ex0, ey0, depths, X, Y)
            dg = _distance(map_g, r, c, gx0, gy0, depths, X, Y)
            if not (de > 0.0 or dg > 0.0):
                continue
            dt = _distance(map_test, r, c, 0, 0, depths, X, Y)
            t32 = np.float32(dt)
            vg = dg > 0.0 and (np.float32(dg) - t32 <= delta32 or dt == 0.0)
            ve = de > 0.0 and (np.float32(de) - t32 <= delta32 or dt == 0.0 or vg)
            if vg or ve:
                union += 1
            if vg and ve:
                cost = abs(dg - de)
                if diameter > 0.0:
                    cost = cost / diameter
                for k in range(len(taus)):
                    if cost < taus[k]:
                        matches[k] += 1
    return union
