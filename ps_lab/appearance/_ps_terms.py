"""The ps kernel's light table and per-pixel rows (:mod:`._ps_kernel`, inlined into it).

The model's terms as codes (:func:`_term_codes`), each light's row of the table the kernel reads
(given and unit vector, half vector, products, HSH terms: :func:`_fill_table`), a tile of
observations copied pixel-major (:func:`_load_tile`), and a pixel's work rows (channel mean,
``n·l``, facing, labels) and term values (:func:`_pixel_rows`, :func:`_terms_pixel`).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numba import njit

from ps_lab.appearance.models import is_direct
from ps_lab.jit import INLINE, VECTOR

# Term kinds of the kernel (``_term_codes``).
_LAMBERT, _AMBIENT, _LX, _LY, _LZ, _LOBE, _LOBEX, _LOBEY, _HSH = range(9)
# Rows of the kernel's light table (one column per light): the light vector as given (the
# visibility's features and ``n·l`` of the Lambertian term), normalised (the terms' ``l``), the
# half vector, the given vector's products (the visibility's normal matrix), the HSH terms.
_DX, _DY, _DZ, _UX, _UY, _UZ, _HX, _HY, _HZ = range(9)
_XX, _YY, _ZZ, _XY, _XZ, _YZ = range(9, 15)
_H0 = 15
TABLE_ROWS = 24
# Rows of the kernel's per-pixel work array (one per lane): observed channels, channel mean,
# n·l (given vector), facing (1/0), label (1/0), V, V·max(n·l, 0), n·l (unit vector),
# max(n·h, 0), step(n·l), step(n·l)·V, and a row for powers.
_CNT, _MEAN, _S, _F, _L, _V, _SH, _U, _NH, _LIT, _LV, _P = range(12)
WORK_ROWS = 12
# Pixels handled together: their solves (the visibility's 4 x 4 rounds, the K x K systems) run
# side by side, one pixel per SIMD lane.
LANES = 8
# Pixels whose observations are copied (as float64, pixel-major) at a time: (TILE, C, n) stays in
# the L2 cache.
TILE = 8 * LANES
PART = {"nogil": True, "cache": True, **VECTOR}
# Integer lobe exponents up to this are powers by repeated squaring (exact up to rounding).
_MAX_INT_POWER = 1 << 12


@lru_cache(maxsize=64)
def _term_codes(terms: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kernel's description of ps terms: kind (K,) int64, parameter (K,) float64 (the
    exponent of a lobe, the index of an HSH term), direct (K,) bool.

    Raises
    ------
    ValueError
        An unknown term (as :func:`ps_lab.appearance.models.ps_term`).

    """
    kinds, params = [], []
    for term in terms:
        kind, param = _term_code(term)
        kinds.append(kind)
        params.append(param)
    direct = np.array([is_direct(t) for t in terms], bool)
    return np.array(kinds, np.int64), np.array(params, np.float64), direct


def _term_code(term: str) -> tuple[int, float]:
    simple = {"lambert": _LAMBERT, "ambient": _AMBIENT, "lx": _LX, "ly": _LY, "lz": _LZ}
    if term in simple:
        return simple[term], 0.0
    if term.startswith("lobe"):
        kind, _, power_text = term.partition(":")
        lobes = {"lobe": _LOBE, "lobex": _LOBEX, "lobey": _LOBEY}
        if kind in lobes:
            return lobes[kind], float(power_text)
    if term.startswith("hsh:"):
        index = int(term[4:])
        if 0 <= index < 9:
            return _HSH, float(index)
    raise ValueError(f"unknown ps term {term!r}")


@njit(**PART)
def _fill_table(dirs, col, tab, need_hsh):
    """``tab`` (TABLE_ROWS, n) from the light vectors ``dirs[:, col]`` ((n, ·, 3)).

    As :func:`ps_lab.appearance.models.ps_basis` forms them: ``l̂ = l / |l|`` (``l`` where
    ``|l| = 0``), ``h = normalise(l̂ + (0, 0, 1))``, and HSH of ``l̂``.
    """
    for i in range(dirs.shape[0]):
        x, y, z = dirs[i, col, 0], dirs[i, col, 1], dirs[i, col, 2]
        tab[_DX, i], tab[_DY, i], tab[_DZ, i] = x, y, z
        tab[_XX, i], tab[_YY, i], tab[_ZZ, i] = x * x, y * y, z * z
        tab[_XY, i], tab[_XZ, i], tab[_YZ, i] = x * y, x * z, y * z
        norm = math.sqrt(x * x + y * y + z * z)
        norm = norm if norm > 0.0 else 1.0
        ux, uy, uz = x / norm, y / norm, z / norm
        tab[_UX, i], tab[_UY, i], tab[_UZ, i] = ux, uy, uz
        hz = uz + 1.0
        half = math.sqrt(ux * ux + uy * uy + hz * hz)
        half = half if half > 0.0 else 1.0
        tab[_HX, i], tab[_HY, i], tab[_HZ, i] = ux / half, uy / half, hz / half
        if need_hsh:
            c = min(max(uz, 0.0), 1.0)
            phi = math.atan2(uy, ux)
            s = math.sqrt(max(c - c * c, 0.0))
            cp, sp = math.cos(phi), math.sin(phi)
            k = math.sqrt(30.0 / math.pi)
            tab[_H0, i] = 1.0 / math.sqrt(2.0 * math.pi)
            tab[_H0 + 1, i] = math.sqrt(6.0 / math.pi) * cp * s
            tab[_H0 + 2, i] = math.sqrt(3.0 / (2.0 * math.pi)) * (2.0 * c - 1.0)
            tab[_H0 + 3, i] = math.sqrt(6.0 / math.pi) * sp * s
            tab[_H0 + 4, i] = k * math.cos(2.0 * phi) * (c * c - c)
            tab[_H0 + 5, i] = k * cp * (2.0 * c - 1.0) * s
            tab[_H0 + 6, i] = math.sqrt(5.0 / (2.0 * math.pi)) * (6.0 * c * c - 6.0 * c + 1.0)
            tab[_H0 + 7, i] = k * sp * (2.0 * c - 1.0) * s
            tab[_H0 + 8, i] = k * math.sin(2.0 * phi) * (c * c - c)


@njit(**PART)
def _load_tile(flat, first, count, channels, inv, y, n):
    """Observations of pixels ``first .. first + count`` (columns of ``flat`` (n, P·C)) times
    ``inv`` into ``y`` (TILE, C, n) as float64.

    A pixel's observations are ``n`` values far apart in ``flat``: the copy reads eight
    lights' runs of ``count · C`` values side by side (streams the prefetcher follows) and
    writes whole cache lines of ``y``. (Views, so that every index counts from 0: numba then
    drops its negative-index handling.)
    """
    width = count * channels
    src = flat[:, first * channels:first * channels + width]
    dst = y.reshape(y.shape[0] * channels, n)
    for i0 in range(0, n, 8):
        rows = src[i0:i0 + 8]
        cols = dst[:, i0:i0 + 8]
        scale = inv[i0:i0 + 8]
        for m in range(width):
            for di in range(rows.shape[0]):
                cols[m, di] = rows[di, m] * scale[di]


@njit(**INLINE)
def _pixel_rows(y, yo, ok, t, tab, work, n, channels, nx, ny, nz):
    """Lane t's rows ``_CNT``, ``_MEAN`` (count and mean of the finite channels of pixel
    ``yo + t`` of ``y``) and ``_S`` (``n·l`` of the given light vector).

    Non-finite observations of ``y`` become 0 and ``ok[t]`` (C, n) their flags. Returns the
    count of non-finite observations (``ok[t]`` is written only when there are some).
    """
    bad = 0
    for c in range(channels):
        for i in range(n):
            bad += 0 if np.isfinite(y[yo + t, c, i]) else 1
    if bad == 0:
        for i in range(n):
            work[t, _MEAN, i] = y[yo + t, 0, i]
        for c in range(1, channels):
            for i in range(n):
                work[t, _MEAN, i] += y[yo + t, c, i]
        for i in range(n):
            work[t, _MEAN, i] = work[t, _MEAN, i] / channels
        for i in range(n):
            work[t, _CNT, i] = channels
        for i in range(n):
            work[t, _S, i] = tab[_DX, i] * nx + tab[_DY, i] * ny + tab[_DZ, i] * nz
        return 0
    for i in range(n):
        work[t, _CNT, i] = 0.0
        work[t, _MEAN, i] = 0.0
    for c in range(channels):
        for i in range(n):
            value = y[yo + t, c, i]
            finite = np.isfinite(value)
            ok[t, c, i] = 1.0 if finite else 0.0
            y[yo + t, c, i] = value if finite else 0.0
            work[t, _CNT, i] += ok[t, c, i]
            work[t, _MEAN, i] += y[yo + t, c, i]
    for i in range(n):
        count = work[t, _CNT, i]
        work[t, _MEAN, i] = work[t, _MEAN, i] / (count if count > 1.0 else 1.0)
        work[t, _S, i] = tab[_DX, i] * nx + tab[_DY, i] * ny + tab[_DZ, i] * nz
    return bad


@njit(**INLINE)
def _power_row(work, t, n, exponent, out, k):
    """``out[k, i] = work[t, _NH, i] ** exponent`` (integers by repeated squaring; row ``_P``
    is overwritten)."""
    e = int(exponent) if 0.0 <= exponent <= _MAX_INT_POWER else -1
    if e < 0 or e != exponent:
        for i in range(n):
            out[k, i] = work[t, _NH, i] ** exponent
        return
    if e == 0:
        for i in range(n):
            out[k, i] = 1.0
        return
    for i in range(n):
        work[t, _P, i] = work[t, _NH, i]
    first = True
    while True:
        if e & 1:
            if first:
                for i in range(n):
                    out[k, i] = work[t, _P, i]
                first = False
            else:
                for i in range(n):
                    out[k, i] *= work[t, _P, i]
        e >>= 1
        if e == 0:
            break
        for i in range(n):
            work[t, _P, i] *= work[t, _P, i]


@njit(**PART)
def _terms_pixel(tab, work, t, n, nx, ny, nz, v0, v1, v2, v3, use_vis, kinds, params, direct,
                 b):
    """Lane t's terms ``b`` (K, n) and its rows ``_U``, ``_NH``, ``_LIT``, ``_LV``, ``_V``,
    ``_SH`` (``_S``, the given vector's ``n·l``, already there)."""
    # one row per loop: the loops vectorise
    for i in range(n):
        work[t, _U, i] = tab[_UX, i] * nx + tab[_UY, i] * ny + tab[_UZ, i] * nz
    for i in range(n):
        nh = tab[_HX, i] * nx + tab[_HY, i] * ny + tab[_HZ, i] * nz
        work[t, _NH, i] = nh if nh > 0.0 else 0.0
    for i in range(n):
        work[t, _LIT, i] = 1.0 if work[t, _U, i] > 0.0 else 0.0
    if use_vis:
        for i in range(n):
            v = tab[_UX, i] * v0 + tab[_UY, i] * v1 + tab[_UZ, i] * v2 + v3
            work[t, _V, i] = min(max(v, 0.0), 1.0)
    else:
        for i in range(n):
            work[t, _V, i] = 1.0
    for i in range(n):
        work[t, _LV, i] = work[t, _LIT, i] * work[t, _V, i]
    for i in range(n):
        s = work[t, _S, i]
        work[t, _SH, i] = (s if s > 0.0 else 0.0) * work[t, _V, i]
    for k in range(kinds.shape[0]):
        kind = kinds[k]
        gated = use_vis and direct[k]
        gate = _LV if gated else _LIT
        if kind == _LAMBERT:
            for i in range(n):
                u = work[t, _U, i]
                b[k, i] = u if u > 0.0 else 0.0
        elif kind == _AMBIENT:
            for i in range(n):
                b[k, i] = 1.0
        elif kind == _LX or kind == _LY or kind == _LZ:
            row = _UX + (kind - _LX)
            for i in range(n):
                b[k, i] = tab[row, i] * work[t, gate, i]
            gated = False
        elif kind == _LOBE:
            _power_row(work, t, n, params[k], b, k)
            for i in range(n):
                b[k, i] *= work[t, gate, i]
            gated = False
        elif kind == _LOBEX or kind == _LOBEY:
            _power_row(work, t, n, params[k] - 1.0, b, k)
            row = _HX + (kind - _LOBEX)
            for i in range(n):
                b[k, i] = b[k, i] * tab[row, i] * work[t, gate, i]
            gated = False
        else:  # _HSH
            row = _H0 + int(params[k])
            for i in range(n):
                b[k, i] = tab[row, i]
        if gated:
            for i in range(n):
                b[k, i] *= work[t, _V, i]
