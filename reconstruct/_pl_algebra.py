"""Small per-pixel algebra of the PL kernels (:mod:`._pl_kernels`), inlined into them.

A selection for the break points, a Cholesky inverse of the (K+2)x(K+2) normal equations, and a
sum of logs by running products.
"""

from __future__ import annotations

import math

from numba import njit

from ._kernels import INLINE


@njit(**INLINE)
def _select(a, lo, hi, kth):
    """The value of rank ``kth`` of ``a[lo:hi]`` (Hoare's selection, in place, O(n) expected).

    Afterwards ``a[lo:kth] <= a[kth] <= a[kth + 1:hi]``, so a larger rank can be selected in
    ``a[kth:hi]``. The pivot is the median of three (deterministic); the value equals a sort's.
    """
    left = lo
    right = hi - 1
    while right > left:
        mid = (left + right) // 2
        p0, p1, p2 = a[left], a[mid], a[right]
        if p0 > p1:
            p0, p1 = p1, p0
        if p1 > p2:
            p1 = p2
            if p0 > p1:
                p1 = p0
        i = left
        j = right
        while i <= j:
            while a[i] < p1:
                i += 1
            while a[j] > p1:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if kth <= j:
            right = j
        elif kth >= i:
            left = i
        else:
            break
    return a[kth]


@njit(**INLINE)
def _cholesky_inverse(mat, inv, low, u):
    """``inv = mat^-1`` (u x u, symmetric positive definite) and ``log det mat``; NaN if not."""
    for j in range(u):
        s = mat[j, j]
        for q in range(j):
            s -= low[j, q] * low[j, q]
        if not s > 0.0:
            return math.nan
        low[j, j] = math.sqrt(s)
        for r in range(j + 1, u):
            s = mat[r, j]
            for q in range(j):
                s -= low[r, q] * low[j, q]
            low[r, j] = s / low[j, j]
    logdet = 0.0
    for j in range(u):
        logdet += 2.0 * math.log(low[j, j])
    # inverse of the lower factor (in place of its upper part: use inv as scratch), then L^-T L^-1
    for c in range(u):
        for r in range(u):
            s = 1.0 if r == c else 0.0
            for q in range(r):
                s -= low[r, q] * inv[q, c]
            inv[r, c] = s / low[r, r] if r >= c else 0.0
    for r in range(u):
        for c in range(r, u):
            s = 0.0
            for q in range(c, u):
                s += inv[q, r] * inv[q, c]
            low[r, c] = s
    for r in range(u):
        for c in range(r, u):
            inv[r, c] = low[r, c]
            inv[c, r] = low[r, c]
    return logdet


@njit(**INLINE)
def _sum_log(st, w_row, a_row, b_row, n):
    """``sum_i log(st[a_row, i] + st[b_row, i])`` over the usable observations.

    As the log of running products, renormalised before they leave [1e-150, 1e150]: a log per
    observation would cost more than an SBL iteration.
    """
    acc = 0.0
    prod = 1.0
    for i in range(n):
        if st[w_row, i] > 0.0:
            prod *= st[a_row, i] + st[b_row, i]
            if prod > 1e150 or prod < 1e-150:
                acc += math.log(prod)
                prod = 1.0
    return acc + math.log(prod)


@njit(**INLINE)
def _loo_lambertian(y, fw, sw, tab, n, ridge, out):
    """Leave-one-out score of a weighted Lambertian fit of one pixel.

    ``y`` (n,) scaled observations; ``fw`` (n,) the fit's weights (SBL: ``d_i = 1 / (gamma_i +
    lambda_i)``, 0 for dropped observations); ``sw`` (n,) the scoring weights (``1 / lambda_i``
    on the scored observations, 0 elsewhere); ``tab`` (9, n) the SBL light table (``a a^T`` on
    rows 0-5, ``a`` on 6-8). The fit ``x = M^-1 sum_i fw_i y_i a_i`` (``M = ridge I + sum fw a
    a^T``: SBL's posterior mean at fixed ``gamma``) is linear in ``y``, so observation i's
    prediction with itself left out has the residual ``r_i / (1 - h_i)``, ``h_i = fw_i a_i^T M^-1
    a_i``. Returns ``sum_i sw_i (r_i / (1 - h_i))^2`` (the predictive error in noise units), its
    terms in ``out`` (n,; 0 where ``sw`` is 0); NaN when ``M`` is singular, infinity when a scored
    ``h_i`` is 1.
    """
    xx = yy = zz = xy = xz = yz = 0.0
    t0 = t1 = t2 = 0.0
    for i in range(n):
        v = fw[i]
        xx += v * tab[0, i]
        yy += v * tab[1, i]
        zz += v * tab[2, i]
        xy += v * tab[3, i]
        xz += v * tab[4, i]
        yz += v * tab[5, i]
        vy = v * y[i]
        t0 += vy * tab[6, i]
        t1 += vy * tab[7, i]
        t2 += vy * tab[8, i]
    xx += ridge
    yy += ridge
    zz += ridge
    c00 = yy * zz - yz * yz
    c11 = xx * zz - xz * xz
    c22 = xx * yy - xy * xy
    c01 = xz * yz - xy * zz
    c02 = xy * yz - xz * yy
    c12 = xy * xz - xx * yz
    det = xx * c00 + xy * c01 + xz * c02
    if not det > 0.0:
        return math.nan
    d = 1.0 / det
    i00, i11, i22, j01, j02, j12 = c00 * d, c11 * d, c22 * d, 2 * c01 * d, 2 * c02 * d, 2 * c12 * d
    x0 = (c00 * t0 + c01 * t1 + c02 * t2) * d
    x1 = (c01 * t0 + c11 * t1 + c12 * t2) * d
    x2 = (c02 * t0 + c12 * t1 + c22 * t2) * d
    score = 0.0
    for i in range(n):
        out[i] = 0.0
        if sw[i] > 0.0:
            r = y[i] - (x0 * tab[6, i] + x1 * tab[7, i] + x2 * tab[8, i])
            h = fw[i] * (i00 * tab[0, i] + i11 * tab[1, i] + i22 * tab[2, i]
                         + j01 * tab[3, i] + j02 * tab[4, i] + j12 * tab[5, i])
            if not h < 1.0:
                return math.inf
            e = r / (1.0 - h)
            out[i] = sw[i] * e * e
            score += out[i]
    return score


@njit(**INLINE)
def _loo_pl(target, fw, sw, slope_of, tab, n, u, prior, prior_rhs, mat, inv, low, x, out):
    """Leave-one-out score of a weighted piecewise-linear fit of one pixel.

    ``target`` (n,) the design's targets ``t_i``, ``tab`` rows 0..u-1 its rows ``a_i`` (K + 2
    unknowns), ``fw`` (n,) the fit's weights in ``f``'s units (PL-SBL: ``d_i``), ``prior`` and
    ``prior_rhs`` the slopes' prior precision and its right-hand side: the MAP fit is linear in
    the targets, and a left-out residual is ``r_i / (1 - h_i)`` in ``f``'s units, divided by the
    observation's segment slope ``slope_of[i]`` in ``y``'s. Returns ``sum_i sw_i (r_i / ((1 -
    h_i) s_i))^2``, the measure of :func:`_loo_lambertian` (terms in ``out``); NaN when the
    normal equations are not positive definite.
    """
    for r in range(u):
        acc = prior_rhs[r]
        for i in range(n):
            acc += fw[i] * target[i] * tab[r, i]
        x[r] = acc
        for c in range(r, u):
            acc = prior[r, c]
            for i in range(n):
                acc += fw[i] * tab[r, i] * tab[c, i]
            mat[r, c] = acc
            mat[c, r] = acc
    logdet = _cholesky_inverse(mat, inv, low, u)
    if not logdet == logdet:
        return math.nan
    # x = M^-1 rhs (rhs held in x; row 0 of low as scratch)
    for r in range(u):
        acc = 0.0
        for c in range(u):
            acc += inv[r, c] * x[c]
        low[0, r] = acc
    score = 0.0
    for i in range(n):
        out[i] = 0.0
        if sw[i] > 0.0:
            fit = 0.0
            q = 0.0
            for r in range(u):
                fit += low[0, r] * tab[r, i]
                acc = 0.0
                for c in range(u):
                    acc += inv[r, c] * tab[c, i]
                q += tab[r, i] * acc
            h = fw[i] * q
            if not h < 1.0:
                return math.inf
            e = (target[i] - fit) / ((1.0 - h) * slope_of[i])
            out[i] = sw[i] * e * e
            score += out[i]
    return score
