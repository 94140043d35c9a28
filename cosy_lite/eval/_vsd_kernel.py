"""The VSD loop of :mod:`cosy_lite.eval.pose_errors` (numba, ``cache=True``: compiled once per
install, then loaded): the two windows' distances placed in the union of the windows, then both
visibility masks, their union and the costs under each tolerance in one pass, where numpy made a
dozen full-size temporaries per pair.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _place(src, x0, y0, depths, fx, fy, cx, cy, out, ox, oy):
    """``out[oy + r, ox + c]`` = ``src[r, c]`` as float64 (``src`` the window at image pixel x0, y0);
    with ``depths`` the distance of that depth from the camera centre, as the toolkit's
    ``depth_im_to_dist_im_fast``: ``sqrt((X d)^2 + (Y d)^2 + d^2)``, ``X = (x - cx) / fx``,
    ``Y = (y - cy) / fy`` at pixel indices."""
    h, w = src.shape
    for r in range(h):
        Y = (r + y0 - cy) / fy
        for c in range(w):
            d = np.float64(src[r, c])
            if depths:
                X = (c + x0 - cx) / fx
                d = np.sqrt((X * d) ** 2 + (Y * d) ** 2 + d ** 2)
            out[oy + r, ox + c] = d


@njit(cache=True, nogil=True)
def vsd_counts(map_e, ex0, ey0, map_g, gx0, gy0, test, depths, fx, fy, cx, cy,
               x0, y0, x1, y1, delta, taus, diameter, matches):
    """Over the image pixels ``y0:y1, x0:x1`` (containing both windows): ``matches[k]`` += pixels
    of ``V_g & V_e`` with cost < ``taus[k]``; returns ``#(V_g | V_e)``.

    ``map_e`` / ``map_g``: maps of the windows at (ex0, ey0) / (gx0, gy0), 0 outside them;
    ``test``: the whole test image. Distance maps, or with ``depths`` depth maps (see
    :func:`_place`). Visibility as the toolkit's: float32 differences against float32 ``delta``,
    no test measurement (0) visible; cost ``|dist_g - dist_e|`` in float64, divided by
    ``diameter`` if > 0.
    """
    h, w = y1 - y0, x1 - x0
    dist_e = np.zeros((h, w))
    dist_g = np.zeros((h, w))
    _place(map_e, ex0, ey0, depths, fx, fy, cx, cy, dist_e, ex0 - x0, ey0 - y0)
    _place(map_g, gx0, gy0, depths, fx, fy, cx, cy, dist_g, gx0 - x0, gy0 - y0)
    delta32 = np.float32(delta)
    union = 0
    for r in range(h):
        Y = (r + y0 - cy) / fy
        for c in range(w):
            de = dist_e[r, c]
            dg = dist_g[r, c]
            if de == 0.0 and dg == 0.0:
                continue
            dt = np.float64(test[r + y0, c + x0])
            if depths:
                X = (c + x0 - cx) / fx
                dt = np.sqrt((X * dt) ** 2 + (Y * dt) ** 2 + dt ** 2)
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
