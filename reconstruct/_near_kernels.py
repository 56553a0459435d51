"""Tile kernels with per-pixel light vectors: LS, L1-IRLS and SBL for lights at a finite distance.

The per-pixel algebra of :mod:`._kernels` (whose docstrings give the maths), with ``lights`` of
shape (m, n, 3): pixel p's own light vectors ``lights[p]``. Each pixel's light table (the six
products ``a_i a_i^T`` and ``a_i``, (9, n)) is formed once when the pixel starts; then the very
per-pixel iteration of the directional kernels runs on it (:func:`._kernels._l1_pixel`,
:func:`._kernels._sbl_pixel`, inlined), so both solve a pixel with the same operations and an
iteration costs what the directional one does plus the table (``benchmarks/near_lights.py speed``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._kernels import (
    _LAM,
    INLINE,
    STATE_ROWS,
    VECTOR,
    TileResult,
    _l1_pixel,
    _load_pixel,
    _sbl_pixel,
)


@njit(**INLINE)
def _pixel_table(lights, p, tab):
    """``tab`` (9, n): pixel p's ``a_i a_i^T`` (rows 0-5, as ``outer6``) and ``a_i`` (6-8).

    :func:`._kernels._light_table` on ``lights[p]``, written out: taking the view per pixel
    measured ~20 % slower near-light SBL (40 lights, 10^5 px, one thread).
    """
    for i in range(lights.shape[1]):
        a0, a1, a2 = lights[p, i, 0], lights[p, i, 1], lights[p, i, 2]
        tab[0, i] = a0 * a0
        tab[1, i] = a1 * a1
        tab[2, i] = a2 * a2
        tab[3, i] = a0 * a1
        tab[4, i] = a0 * a2
        tab[5, i] = a1 * a2
        tab[6, i] = a0
        tab[7, i] = a1
        tab[8, i] = a2


@njit(nogil=True, cache=True, **VECTOR)
def _l1_kernel_pp(y, w, lights, max_iter, tol, delta, threshold, x_out, outliers, iters):
    m, n = y.shape
    st = np.zeros((STATE_ROWS, n))
    tab = np.zeros((9, n))
    for p in range(m):
        _pixel_table(lights, p, tab)
        _load_pixel(st, y, w, p, n)
        _l1_pixel(st, tab, n, max_iter, tol, delta, threshold, x_out, outliers, iters, p)


@njit(nogil=True, cache=True, **VECTOR)
def _sbl_kernel_pp(y, w, lights, lam, ridge, max_iter, tol, floor, start, threshold, x_out,
                   outliers, iters):
    m, n = y.shape
    st = np.zeros((STATE_ROWS, n))
    tab = np.zeros((9, n))
    for p in range(m):
        _pixel_table(lights, p, tab)
        _load_pixel(st, y, w, p, n)
        for i in range(n):
            st[_LAM, i] = lam
        _sbl_pixel(st, tab, n, ridge, max_iter, tol, floor, start, threshold, x_out, outliers,
                   iters, p)


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
