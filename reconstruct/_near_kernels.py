"""Tile kernels with per-pixel light vectors: LS, L1-IRLS and SBL for lights at a finite distance.

The same per-pixel algebra as :mod:`._kernels` (whose docstrings give the maths and whose 3x3
solve :func:`._kernels._solve3` is shared), with ``lights`` of shape (m, n, 3): pixel p's own
light vectors ``lights[p]``. Each pixel's six products ``a_i a_i^T`` are formed once into a
scratch row (n, 6) when the pixel starts, so an iteration costs what the directional kernel's
does (``benchmarks/near.py``: 1.0-1.2x per pixel-iteration). Kept in their own module so that
changes to the directional kernels (start, tolerance) merge cleanly; a change to the SBL update
there must be mirrored in :func:`_sbl_kernel_pp`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._kernels import TileResult, _solve3


@njit(nogil=True, cache=True)
def _outer6_pixel(lights, p, aa):
    """``aa[i] = unique entries of a_i a_i^T`` for pixel p's light vectors."""
    for i in range(lights.shape[1]):
        a0, a1, a2 = lights[p, i, 0], lights[p, i, 1], lights[p, i, 2]
        aa[i, 0] = a0 * a0
        aa[i, 1] = a1 * a1
        aa[i, 2] = a2 * a2
        aa[i, 3] = a0 * a1
        aa[i, 4] = a0 * a2
        aa[i, 5] = a1 * a2


@njit(nogil=True, cache=True)
def _weighted_fit_pp(y, v, lights, aa, p):
    """X minimising sum_i v_i (y_pi - a_pi.x)^2."""
    xx = yy = zz = xy = xz = yz = 0.0
    t0 = t1 = t2 = 0.0
    for i in range(lights.shape[1]):
        vi = v[i]
        xx += vi * aa[i, 0]
        yy += vi * aa[i, 1]
        zz += vi * aa[i, 2]
        xy += vi * aa[i, 3]
        xz += vi * aa[i, 4]
        yz += vi * aa[i, 5]
        vy = vi * y[p, i]
        t0 += vy * lights[p, i, 0]
        t1 += vy * lights[p, i, 1]
        t2 += vy * lights[p, i, 2]
    s = _solve3(xx, yy, zz, xy, xz, yz, t0, t1, t2)
    return s[0], s[1], s[2]


@njit(nogil=True, cache=True)
def _residual(y, lights, p, i, x0, x1, x2):
    return y[p, i] - (x0 * lights[p, i, 0] + x1 * lights[p, i, 1] + x2 * lights[p, i, 2])


@njit(nogil=True, cache=True)
def _l1_kernel_pp(y, w, lights, max_iter, tol, delta, threshold, x_out, outliers, iters):
    m, n = y.shape
    v = np.empty(n)
    aa = np.empty((n, 6))
    for p in range(m):
        _outer6_pixel(lights, p, aa)
        for i in range(n):
            v[i] = w[p, i]
        x0, x1, x2 = _weighted_fit_pp(y, v, lights, aa, p)
        iters[p] = max(max_iter, 1)
        for it in range(1, max_iter + 1):
            for i in range(n):
                r = abs(_residual(y, lights, p, i, x0, x1, x2))
                v[i] = w[p, i] / (r if r > delta else delta)
            n0, n1, n2 = _weighted_fit_pp(y, v, lights, aa, p)
            step = max(abs(n0 - x0), abs(n1 - x1), abs(n2 - x2))
            x0, x1, x2 = n0, n1, n2
            if step < tol:
                iters[p] = it
                break
        x_out[p, 0], x_out[p, 1], x_out[p, 2] = x0, x1, x2
        for i in range(n):
            r = _residual(y, lights, p, i, x0, x1, x2)
            outliers[p, i] = w[p, i] > 0.0 and abs(r) > threshold


@njit(nogil=True, cache=True)
def _sbl_kernel_pp(y, w, lights, lam, ridge, max_iter, tol, floor, start, threshold, x_out,
                   outliers, iters):
    m, n = y.shape
    g = np.empty(n)
    z_old = np.empty(n)
    d = np.empty(n)
    aa = np.empty((n, 6))
    for p in range(m):
        _outer6_pixel(lights, p, aa)
        for i in range(n):
            g[i] = start
            z_old[i] = 0.0
        iters[p] = max_iter
        for it in range(0, max_iter + 1):
            xx = yy = zz = xy = xz = yz = 0.0
            t0 = t1 = t2 = 0.0
            for i in range(n):
                di = w[p, i] / (g[i] + lam)
                d[i] = di
                xx += di * aa[i, 0]
                yy += di * aa[i, 1]
                zz += di * aa[i, 2]
                xy += di * aa[i, 3]
                xz += di * aa[i, 4]
                yz += di * aa[i, 5]
                dy = di * y[p, i]
                t0 += dy * lights[p, i, 0]
                t1 += dy * lights[p, i, 1]
                t2 += dy * lights[p, i, 2]
            x0, x1, x2, i00, i11, i22, i01, i02, i12 = _solve3(
                xx + ridge, yy + ridge, zz + ridge, xy, xz, yz, t0, t1, t2)
            if it == max_iter or (it > 0 and iters[p] < max_iter):
                x_out[p, 0], x_out[p, 1], x_out[p, 2] = x0, x1, x2
                for i in range(n):
                    r = _residual(y, lights, p, i, x0, x1, x2)
                    outliers[p, i] = w[p, i] > 0.0 and abs(g[i] * d[i] * r) > threshold
                break
            j01, j02, j12 = 2.0 * i01, 2.0 * i02, 2.0 * i12
            step = 0.0
            for i in range(n):
                gi = g[i]
                di = d[i]
                gd = gi * di
                z = gd * _residual(y, lights, p, i, x0, x1, x2)
                q = (i00 * aa[i, 0] + i11 * aa[i, 1] + i22 * aa[i, 2]
                     + j01 * aa[i, 3] + j02 * aa[i, 4] + j12 * aa[i, 5])
                gn = z * z + (gi - gi * gd * (1.0 - di * q))
                g[i] = gn if gn > floor else floor
                s = abs(z - z_old[i])
                if s > step:
                    step = s
                z_old[i] = z
            if step < tol:
                iters[p] = it + 1


def _run(kernel, y, *args) -> TileResult:
    m = y.shape[0]
    x = np.zeros((m, 3))
    outliers = np.zeros(y.shape, np.bool_)
    iters = np.zeros(m, np.int64)
    kernel(y, *args, x, outliers, iters)
    return TileResult(x, outliers, iters)


def ls_tile_pp(y, w, lights, *, outlier_threshold: float) -> TileResult:
    """Woodham's least squares with per-pixel lights (the L1 kernel's start); no outliers."""
    res = _run(_l1_kernel_pp, y, w, lights, 0, 0.0, 1.0, np.inf)
    return TileResult(res.x, np.zeros(y.shape, bool), np.ones(y.shape[0], np.int64))


def l1_tile_pp(y, w, lights, *, max_iter: int, tol: float, delta: float,
               outlier_threshold: float) -> TileResult:
    """:func:`._kernels.l1_tile` with per-pixel lights (m, n, 3)."""
    return _run(_l1_kernel_pp, y, w, lights, int(max_iter), float(tol), float(delta),
                float(outlier_threshold))


def sbl_tile_pp(y, w, lights, *, lam: float, sigma_x2: float, max_iter: int, tol: float,
                gamma_floor: float, gamma_start: float, outlier_threshold: float) -> TileResult:
    """:func:`._kernels.sbl_tile` with per-pixel lights (m, n, 3) and one ``lam``."""
    return _run(_sbl_kernel_pp, y, w, lights, float(lam), 1.0 / float(sigma_x2), int(max_iter),
                float(tol), float(gamma_floor), float(gamma_start), float(outlier_threshold))
