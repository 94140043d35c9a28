"""The compiled loops of :mod:`cosy_lite.render.depth_raster` (numba, ``cache=True``: compiled once
per install, ~3 s, then loaded). Imported only by that module's functions, on first use.

Coverage as a GL rasteriser decides it (what the BOP toolkit's renderer runs on): vertex positions
snapped to 1/256 px (:data:`SUBPIXELS`), so that the edge functions are exact (products of
multiples of 1/256 under 2^20 are exact in float64), and a sample exactly on an edge belongs to
the triangle whose top or left edge it is (one of the two triangles sharing it).

The z-buffer holds ``1 / z`` (0 = empty; the largest wins): ``1 / max(1 / z)`` is ``min(z)`` bit
for bit (rounding is monotonic), without a division per sample.
"""

from __future__ import annotations

import numpy as np
from numba import njit

SUBPIXELS = 256.0  # GL's sub-pixel precision (8 bits: llvmpipe, and the GPUs of the toolkit's users)
# A back face is skipped only above this doubled area (px^2): a closed mesh's back faces cover no
# sample that its front faces do not, but an edge-on sliver's depth plane is ill-conditioned, and the
# nearer of two such planes decides the depth on a few silhouette pixels as the two-sided draw does.
CULL_MIN_AREA2 = 0.5
EDGE_BIAS = 2.0 ** -17  # half the step of the edge functions' values (see draw_triangle)


@njit(cache=True, nogil=True, inline="always")
def snap(x):
    """Image coordinate -> the nearest multiple of 1 / SUBPIXELS."""
    return np.floor(x * SUBPIXELS + 0.5) / SUBPIXELS


@njit(cache=True, nogil=True, inline="always")
def edge_coefficients(ax, ay, bx, by):
    """(A, B, C) of the edge function ``A x + B y + C`` of the edge a -> b (> 0 on its left in
    image coordinates), computed from the endpoints in one order whichever way the edge runs: the
    two triangles of a shared edge get exactly opposite values, so no sample on it falls between them."""
    if ax > bx or (ax == bx and ay > by):
        A, B = by - ay, ax - bx
        return -A, -B, A * bx + B * by
    A, B = ay - by, bx - ax
    return A, B, -(A * ax + B * ay)


@njit(cache=True, nogil=True, inline="always")
def draw_triangle(out, x0, y0, ua, va, iza, ub, vb, izb, uc, vc, izc, sua, sva, sub, svb, suc, svc, cull):
    """1/z-buffer ``out`` (window at ``x0, y0``) with the image triangle (u, v) a, b, c whose corners
    have camera depth 1 / iz (> 0). Coverage from the corners snapped (su, sv: as GL), depth from
    the exact ones: ``1 / z`` is a plane over the image. ``cull`` (+1 / -1): skip the triangle if
    its snapped signed area has that sign (and is above :data:`CULL_MIN_AREA2`); 0: two-sided."""
    h, w = out.shape
    if cull != 0.0 and cull * ((sub - sua) * (svc - sva) - (suc - sua) * (svb - sva)) > CULL_MIN_AREA2:
        return  # a back face (the snapped area, exact: as below), rejected before any other work
    # pixel columns / rows whose sample (c + 0.5, r + 0.5) may be inside, clipped to the window
    c0 = max(int(np.ceil(min(sua, sub, suc) - 0.5)), x0)
    c1 = min(int(np.floor(max(sua, sub, suc) - 0.5)), x0 + w - 1)
    if c0 > c1:
        return
    r0 = max(int(np.ceil(min(sva, svb, svc) - 0.5)), y0)
    r1 = min(int(np.floor(max(sva, svb, svc) - 0.5)), y0 + h - 1)
    if r0 > r1:
        return
    Aa, Ba, Ca = edge_coefficients(sub, svb, suc, svc)
    area = Aa * sua + Ba * sva + Ca
    if area == 0.0 or not np.isfinite(area) or cull * area > CULL_MIN_AREA2:
        return
    Ab, Bb, Cb = edge_coefficients(suc, svc, sua, sva)
    Ac, Bc, Cc = edge_coefficients(sua, sva, sub, svb)
    sg = 1.0 if area > 0 else -1.0  # two-sided: either winding (a product, not a branch: the sign is exact)
    Aa, Ba, Ca, Ab, Bb, Cb, Ac, Bc, Cc = sg * Aa, sg * Ba, sg * Ca, sg * Ab, sg * Bb, sg * Cb, sg * Ac, sg * Bc, sg * Cc
    # A sample on an edge (E = 0) is inside if the triangle is right of it (a left edge: A > 0) or
    # below a horizontal one (a top edge, image rows down: B > 0). Elsewhere the edge is open: E > 0
    # is needed, i.e. E >= 2^-16, as E is a multiple of 2^-16 (corners on the 1/256 grid, samples
    # at half pixels, all exact): E - EDGE_BIAS >= 0, one test for all three edges. (Subtracting
    # EDGE_BIAS * 0 changes nothing: branch-free, as the samples below.)
    Ca -= EDGE_BIAS * ((Aa < 0) | ((Aa == 0) & (Ba <= 0)))
    Cb -= EDGE_BIAS * ((Ab < 0) | ((Ab == 0) & (Bb <= 0)))
    Cc -= EDGE_BIAS * ((Ac < 0) | ((Ac == 0) & (Bc <= 0)))
    P = Q = 0.0  # 1 / z = iza + P (u - ua) + Q (v - va), from the exact corners
    det = (ub - ua) * (vc - va) - (uc - ua) * (vb - va)
    if det != 0.0:
        inv = 1.0 / det
        P = ((izb - iza) * (vc - va) - (izc - iza) * (vb - va)) * inv
        Q = ((izc - iza) * (ub - ua) - (izb - iza) * (uc - ua)) * inv
    # Each sample is kept or not by a select, not a branch: whether a sample is inside is what the CPU
    # cannot predict (1.4x faster than branching on it, the same bits).
    for r in range(r0, r1 + 1):
        py = r + 0.5
        ra, rb, rc = Ba * py + Ca, Bb * py + Cb, Bc * py + Cc
        qrow = Q * (py - va)
        row = out[r - y0]
        for col in range(c0, c1 + 1):
            px = col + 0.5
            ea = Aa * px + ra
            eb = Ab * px + rb
            ec = Ac * px + rc
            iz = iza + P * (px - ua) + qrow  # (<= 0 on a sliver whose plane overshoots: not drawn)
            cur = row[col - x0]
            row[col - x0] = iz if ((ea >= 0.0) & (eb >= 0.0) & (ec >= 0.0) & (iz > cur)) else cur


@njit(cache=True, nogil=True)
def draw_mesh(out, vertices, faces, R, t, fx, fy, cx, cy, x0, y0, znear, cull):
    """1/z-buffer ``out`` (window at ``x0, y0``, 0 where empty) with the mesh at ``R``, ``t``,
    clipped by the plane z = znear; ``cull``: the sign of the back faces' snapped area when the mesh
    is closed (:func:`cosy_lite.render.depth_raster.back_face_sign`), 0 to draw both sides (also
    done whenever the plane cuts the mesh: the camera may then see its inside)."""
    n = vertices.shape[0]
    cam = np.empty((n, 3))
    u = np.empty(n)
    v = np.empty(n)
    su = np.empty(n)
    sv = np.empty(n)
    iz = np.empty(n)
    for i in range(n):
        for k in range(3):
            cam[i, k] = R[k, 0] * vertices[i, 0] + R[k, 1] * vertices[i, 1] + R[k, 2] * vertices[i, 2] + t[k]
        if cam[i, 2] >= znear:
            iz[i] = 1.0 / cam[i, 2]
            u[i] = fx * cam[i, 0] * iz[i] + cx
            v[i] = fy * cam[i, 1] * iz[i] + cy
            su[i], sv[i] = snap(u[i]), snap(v[i])
        else:
            cull = 0.0
    poly = np.empty((4, 3))
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        front = (cam[a, 2] >= znear) + (cam[b, 2] >= znear) + (cam[c, 2] >= znear)
        if front == 3:
            draw_triangle(out, x0, y0, u[a], v[a], iz[a], u[b], v[b], iz[b], u[c], v[c], iz[c],
                          su[a], sv[a], su[b], sv[b], su[c], sv[c], cull)
            continue
        if front == 0:
            continue
        # clip the triangle by z = znear (Sutherland-Hodgman, one plane): 3 or 4 vertices
        m = 0
        corners = (a, b, c)
        for i in range(3):
            s, e = corners[i], corners[(i + 1) % 3]
            if cam[s, 2] >= znear:
                poly[m] = cam[s]
                m += 1
            if (cam[s, 2] >= znear) != (cam[e, 2] >= znear):
                p, q = (s, e) if cam[s, 2] >= znear else (e, s)  # from the front end: the same point both ways
                k = (znear - cam[p, 2]) / (cam[q, 2] - cam[p, 2])
                poly[m] = cam[p] + k * (cam[q] - cam[p])
                poly[m, 2] = znear
                m += 1
        for i in range(1, m - 1):
            j = (0, i, i + 1)
            pu = np.empty(3)
            pv = np.empty(3)
            pz = np.empty(3)
            for k in range(3):
                pz[k] = 1.0 / poly[j[k], 2]
                pu[k] = fx * poly[j[k], 0] * pz[k] + cx
                pv[k] = fy * poly[j[k], 1] * pz[k] + cy
            draw_triangle(out, x0, y0, pu[0], pv[0], pz[0], pu[1], pv[1], pz[1], pu[2], pv[2], pz[2],
                          snap(pu[0]), snap(pv[0]), snap(pu[1]), snap(pv[1]), snap(pu[2]), snap(pv[2]), 0.0)


@njit(cache=True, nogil=True)
def projected_bounds(pts, R, t, K):
    """(u min, u max, v min, v max, z min, z max) of the points ``pts`` [N,3] at ``R``, ``t``, seen
    by ``K`` [3,3] (u, v = (K p)[:2] / z; meaningful where every z > 0)."""
    lo_u = lo_v = lo_z = np.inf
    hi_u = hi_v = hi_z = -np.inf
    for i in range(pts.shape[0]):
        x = R[0, 0] * pts[i, 0] + R[0, 1] * pts[i, 1] + R[0, 2] * pts[i, 2] + t[0]
        y = R[1, 0] * pts[i, 0] + R[1, 1] * pts[i, 1] + R[1, 2] * pts[i, 2] + t[1]
        z = R[2, 0] * pts[i, 0] + R[2, 1] * pts[i, 1] + R[2, 2] * pts[i, 2] + t[2]
        u = (K[0, 0] * x + K[0, 1] * y + K[0, 2] * z) / z
        v = (K[1, 0] * x + K[1, 1] * y + K[1, 2] * z) / z
        lo_u, hi_u = min(lo_u, u), max(hi_u, u)
        lo_v, hi_v = min(lo_v, v), max(hi_v, v)
        lo_z, hi_z = min(lo_z, z), max(hi_z, z)
    return lo_u, hi_u, lo_v, hi_v, lo_z, hi_z


@njit(cache=True, nogil=True)
def finish(out, depth):
    """The 1/z-buffer ``out`` (0 where empty) -> ``depth`` (float32, 0 where empty)."""
    h, w = out.shape
    for r in range(h):
        for col in range(w):
            iz = out[r, col]
            if iz != 0.0:
                depth[r, col] = np.float32(1.0 / iz)


@njit(cache=True, nogil=True)
def component_labels(faces, n):
    """Per vertex the smallest vertex index of its connected component (edges of ``faces``), [n]."""
    parent = np.arange(n)
    for f in range(faces.shape[0]):
        for k in range(3):
            a, b = faces[f, k], faces[f, (k + 1) % 3]
            while parent[a] != a:
                parent[a] = parent[parent[a]]
                a = parent[a]
            while parent[b] != b:
                parent[b] = parent[parent[b]]
                b = parent[b]
            if a < b:
                parent[b] = a
            elif b < a:
                parent[a] = b
    for i in range(n):
        r = i
        while parent[r] != r:
            r = parent[r]
        parent[i] = r
    return parent
