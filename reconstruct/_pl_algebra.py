"""Small per-pixel algebra of the PL kernels (:mod:`._pl_kernels`), inlined into them.

A selection for the break points (without branches on the data), a Cholesky inverse of the
(K+2)x(K+2) normal equations and, for three segments, a 5x5 inverse by blocks held in registers,
a sum of logs by running products, the closed-form leave-one-out scores of the default's choice
and its score test.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit
from scipy.special import chdtri  # chi^2 upper quantile: scipy.stats costs 0.7 s to import

from ._kernels import INLINE
from ._linalg import SINGULAR_REL_DET, cofactors3, inverse3


@njit(**INLINE)
def _select(a, lo, hi, kth):
    """The value of rank ``kth`` of ``a[lo:hi]`` (a selection, in place, O(n) expected).

    Afterwards ``a[lo:kth] <= a[kth] <= a[kth + 1:hi]``, so a larger rank can be selected in
    ``a[kth:hi]``. The pivot is the median of three (deterministic); the value equals a sort's.
    Each partition is Lomuto's without a branch on the data (a swap and a count per element:
    a mispredicted branch per element cost more than the rest of the selection), in two passes:
    the values below the pivot, then, if the rank lies right of them, those equal to it (ties:
    8-bit data).
    """
    while hi - lo > 2:
        mid = (lo + hi) // 2
        p0, p1, p2 = a[lo], a[mid], a[hi - 1]
        small = p0 if p0 < p1 else p1
        large = p1 if p0 < p1 else p0
        large = large if large < p2 else p2
        pivot = small if small > large else large  # the median of the three
        # a[lo:store] < pivot <= a[store:i]
        store = lo
        for i in range(lo, hi):
            t = a[i]
            a[i] = a[store]
            a[store] = t
            store += t < pivot
        if kth < store:
            hi = store
            continue
        # a[store:equal] == pivot < a[equal:i]
        equal = store
        for i in range(store, hi):
            t = a[i]
            a[i] = a[equal]
            a[equal] = t
            equal += t <= pivot
        if kth < equal or equal == store:  # (equal == store: only with a NaN pivot)
            return pivot
        lo = equal
    if hi - lo == 2 and a[lo] > a[lo + 1]:
        a[lo], a[lo + 1] = a[lo + 1], a[lo]
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
def _inverse5(m00, m01, m02, m03, m04, m11, m12, m13, m14, m22, m23, m24, m33, m34, m44):
    """``M^-1`` of a symmetric 5x5 ``M`` (upper triangle given) and ``det M``, in scalars.

    The three-segment iteration's (slopes 0-1, normal 2-4) by blocks: ``N`` (rows 2-4) by
    cofactors, then the slopes' 2x2 Schur complement ``S = M_ss - C N^-1 C^T``; ``M^-1`` is
    ``S^-1`` on the slopes, ``-S^-1 C N^-1`` beside and ``N^-1 + (N^-1 C^T) S^-1 (C N^-1)``
    on the normal. ``M`` is positive definite exactly where ``N`` and ``S`` are (what
    :func:`_cholesky_inverse` tests by its pivots); else NaN (and zeros). Two divisions, no
    square root and no log (the caller takes ``log det`` once): held in registers, 17 ns a call
    against the generic Cholesky's 131 ns (both with their log, one thread, Zen 4).

    Returns
    -------
    det : float
        ``det M = det N det S``; NaN where ``M`` is not positive definite.
    inverse : tuple of 15 floats
        The upper triangle of ``M^-1``, row-major.
    """
    z = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    # N's cofactors; N and S must be positive definite (the Cholesky pivots' test), not only
    # invertible (inverse3's rule)
    det_n, c22, c33, c44, c23, c24, c34 = cofactors3(m22, m33, m44, m23, m24, m34)
    if not det_n > 0.0:
        return math.nan, z
    r = 1.0 / det_n
    n22, n33, n44, n23, n24, n34 = c22 * r, c33 * r, c44 * r, c23 * r, c24 * r, c34 * r
    # P = C N^-1 (2x3; C = M[0:2, 2:5])
    p02 = m02 * n22 + m03 * n23 + m04 * n24
    p03 = m02 * n23 + m03 * n33 + m04 * n34
    p04 = m02 * n24 + m03 * n34 + m04 * n44
    p12 = m12 * n22 + m13 * n23 + m14 * n24
    p13 = m12 * n23 + m13 * n33 + m14 * n34
    p14 = m12 * n24 + m13 * n34 + m14 * n44
    s00 = m00 - (p02 * m02 + p03 * m03 + p04 * m04)
    s01 = m01 - (p02 * m12 + p03 * m13 + p04 * m14)
    s11 = m11 - (p12 * m12 + p13 * m13 + p14 * m14)
    det_s = s00 * s11 - s01 * s01
    if not (s00 > 0.0 and det_s > 0.0):
        return math.nan, z
    r = 1.0 / det_s
    i00 = s11 * r
    i11 = s00 * r
    i01 = -s01 * r
    i02 = -(i00 * p02 + i01 * p12)
    i03 = -(i00 * p03 + i01 * p13)
    i04 = -(i00 * p04 + i01 * p14)
    i12 = -(i01 * p02 + i11 * p12)
    i13 = -(i01 * p03 + i11 * p13)
    i14 = -(i01 * p04 + i11 * p14)
    i22 = n22 - (p02 * i02 + p12 * i12)
    i23 = n23 - (p02 * i03 + p12 * i13)
    i24 = n24 - (p02 * i04 + p12 * i14)
    i33 = n33 - (p03 * i03 + p13 * i13)
    i34 = n34 - (p03 * i04 + p13 * i14)
    i44 = n44 - (p04 * i04 + p14 * i14)
    return det_n * det_s, (i00, i01, i02, i03, i04, i11, i12, i13, i14, i22, i23, i24, i33, i34,
                           i44)


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
    ok, i00, i11, i22, i01, i02, i12 = inverse3(xx + ridge, yy + ridge, zz + ridge, xy, xz, yz,
                                                SINGULAR_REL_DET)
    if not ok:
        return math.nan
    j01, j02, j12 = 2.0 * i01, 2.0 * i02, 2.0 * i12
    x0 = i00 * t0 + i01 * t1 + i02 * t2
    x1 = i01 * t0 + i11 * t1 + i12 * t2
    x2 = i02 * t0 + i12 * t1 + i22 * t2
    score = 0.0
    bad = 0
    for i in range(n):  # (one vectorised pass: no branch, a failed leverage is counted)
        r = y[i] - (x0 * tab[6, i] + x1 * tab[7, i] + x2 * tab[8, i])
        h = fw[i] * (i00 * tab[0, i] + i11 * tab[1, i] + i22 * tab[2, i]
                     + j01 * tab[3, i] + j02 * tab[4, i] + j12 * tab[5, i])
        scored = sw[i] > 0.0
        bad += scored and not h < 1.0
        e = r / (1.0 - h)
        term = sw[i] * e * e if scored else 0.0
        out[i] = term
        score += term
    return math.inf if bad else score


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


@njit(**INLINE)
def _bend_score(y, w, tab, p, n, k_max, x_out, lam_row, q_table, vals, mat, inv, low, g, col,
                breaks, known):
    """Robust score test at pixel p of the Lambertian fit against ``k`` segments; its excess.

    ``tab`` (9, n): the pixel's light table (``a a^T`` on rows 0-5, the lights ``a`` on 6-8, as
    :func:`._kernels._light_table`). ``k = min(k_max, usable // 4)`` as the PL fit's; ``g``,
    ``col``: scratch of ``k + 2``. ``breaks`` (``k_max - 1``,): the break points, written, or
    read where ``known`` (a second test of the same fit at another noise level: they depend
    on the fit alone, and their selection is half the test's cost).

    SBL's fit ``x`` (posterior mean) is the restricted model. On the pixel's usable
    observations, fitted values ``v_i = l_i . x``, residuals ``r_i = y_i - v_i`` clipped to
    ``+-GATE_CLIP sqrt(lam_i)`` (Huber's psi at SBL's "3 sigma": a corruption counts no more than
    one at the outlier threshold, but counts; SBL's own flags are not trusted, since they are
    what the larger model disputes) and weights ``1 / lam_i``. The piecewise-linear model bends
    the response at the ``j u / k``-th smallest value (``j = 1 .. k - 1``); to first order at the
    Lambertian fit that adds the hinges ``h_j = max(v - b_j, 0)`` of the fitted values (breaks at
    their order statistics) to the design. The score statistic is the weighted residual sum of
    squares that the hinges remove from the regression of ``r`` on the lights,
    ``g^T G^-1 g - g_L^T G_LL^-1 g_L`` (``G``, ``g``: the weighted products of ``[l, h]`` with
    themselves and with ``r``), chi^2 with ``k - 1`` degrees of freedom under the Lambertian
    model; ``q_table[k - 1]`` is its quantile. Returns the statistic less the quantile (> 0: the
    Lambertian model fails towards the bent one), or -inf with fewer than four observations per
    unknown of the ``k``-segment model or a singular design (no power: the smaller model is kept).

    The statistic is computed as the hinges' part of the regression after the lights' (the Schur
    complement ``S = G_HH - G_HL G_LL^-1 G_LH``, ``s = g_H - G_HL G_LL^-1 g_L``: ``s^T S^-1 s``,
    the same number as the difference above without its cancellation), ``G_LL^-1`` by cofactors;
    for ``k = 3`` (the default) the sums are one vectorised pass over the lights and ``S`` is 2x2.
    """
    x0 = x_out[p, 0]
    x1 = x_out[p, 1]
    x2 = x_out[p, 2]
    cnt = 0
    if known:
        for i in range(n):
            cnt += w[p, i] > 0.0
    else:
        for i in range(n):
            # the usable fitted values, packed without a branch (a dropped one is overwritten)
            vals[cnt] = tab[6, i] * x0 + tab[7, i] * x1 + tab[8, i] * x2
            cnt += w[p, i] > 0.0
    k = k_max if k_max < cnt // 4 else cnt // 4
    u = k + 2
    if k < 2 or cnt < 4 * u:
        return -math.inf
    # breaks: order statistics of the fitted values, as _design's of the observations
    lo = 0
    for j in range(1, k):
        if known:
            col[j] = breaks[j - 1]
        else:
            kth = (j * cnt) // k
            col[j] = _select(vals, lo, cnt, kth)
            breaks[j - 1] = col[j]
            lo = kth
    nh = k - 1
    # weighted sums: G_LL (6), g_L (3) and, per hinge, G_LH (3 each), G_HH, g_H
    a00 = a11 = a22 = a01 = a02 = a12 = 0.0
    gl0 = gl1 = gl2 = 0.0
    if k == 3:
        b1 = col[1]
        b2 = col[2]
        p10 = p11 = p12 = p20 = p21 = p22 = 0.0
        c11 = c12 = c22 = 0.0
        gh1 = gh2 = 0.0
        for i in range(n):
            lam = lam_row[i]
            wt = w[p, i] / lam
            l0 = tab[6, i]
            l1 = tab[7, i]
            l2 = tab[8, i]
            fit = l0 * x0 + l1 * x1 + l2 * x2
            cap = GATE_CLIP * math.sqrt(lam)
            res = y[p, i] - fit
            res = res if res < cap else cap
            res = res if res > -cap else -cap
            h1 = fit - b1
            h1 = h1 if h1 > 0.0 else 0.0
            h2 = fit - b2
            h2 = h2 if h2 > 0.0 else 0.0
            a00 += wt * tab[0, i]
            a11 += wt * tab[1, i]
            a22 += wt * tab[2, i]
            a01 += wt * tab[3, i]
            a02 += wt * tab[4, i]
            a12 += wt * tab[5, i]
            wr = wt * res
            gl0 += wr * l0
            gl1 += wr * l1
            gl2 += wr * l2
            gh1 += wr * h1
            gh2 += wr * h2
            wh1 = wt * h1
            wh2 = wt * h2
            p10 += wh1 * l0
            p11 += wh1 * l1
            p12 += wh1 * l2
            p20 += wh2 * l0
            p21 += wh2 * l1
            p22 += wh2 * l2
            c11 += wh1 * h1
            c12 += wh1 * h2
            c22 += wh2 * h2
        mat[0, 0], mat[0, 1], mat[1, 1] = c11, c12, c22
        low[0, 0], low[0, 1], low[0, 2] = p10, p11, p12
        low[1, 0], low[1, 1], low[1, 2] = p20, p21, p22
        g[0], g[1] = gh1, gh2
    else:
        for r in range(nh):
            g[r] = 0.0
            low[r, 0] = low[r, 1] = low[r, 2] = 0.0
            for c in range(nh):
                mat[r, c] = 0.0
        for i in range(n):
            if not w[p, i] > 0.0:
                continue
            lam = lam_row[i]
            wt = 1.0 / lam
            l0 = tab[6, i]
            l1 = tab[7, i]
            l2 = tab[8, i]
            fit = l0 * x0 + l1 * x1 + l2 * x2
            cap = GATE_CLIP * math.sqrt(lam)
            res = y[p, i] - fit
            res = cap if res > cap else (-cap if res < -cap else res)
            a00 += wt * tab[0, i]
            a11 += wt * tab[1, i]
            a22 += wt * tab[2, i]
            a01 += wt * tab[3, i]
            a02 += wt * tab[4, i]
            a12 += wt * tab[5, i]
            wr = wt * res
            gl0 += wr * l0
            gl1 += wr * l1
            gl2 += wr * l2
            for j in range(nh):
                h = fit - col[j + 1]
                vals[j] = h if h > 0.0 else 0.0  # (vals is free again: the breaks are in col)
            for j in range(nh):
                h = vals[j]
                g[j] += wr * h
                low[j, 0] += wt * h * l0
                low[j, 1] += wt * h * l1
                low[j, 2] += wt * h * l2
                for c in range(j, nh):
                    mat[j, c] += wt * h * vals[c]
    # G_LL^-1
    ok, c00, c11, c22, c01, c02, c12 = inverse3(a00, a11, a22, a01, a02, a12, SINGULAR_REL_DET)
    if not ok:
        return -math.inf
    # s = g_H - G_HL G_LL^-1 g_L; S = G_HH - G_HL G_LL^-1 G_LH (upper triangle, in mat)
    e0 = c00 * gl0 + c01 * gl1 + c02 * gl2
    e1 = c01 * gl0 + c11 * gl1 + c12 * gl2
    e2 = c02 * gl0 + c12 * gl1 + c22 * gl2
    for r in range(nh):
        q0 = c00 * low[r, 0] + c01 * low[r, 1] + c02 * low[r, 2]
        q1 = c01 * low[r, 0] + c11 * low[r, 1] + c12 * low[r, 2]
        q2 = c02 * low[r, 0] + c12 * low[r, 1] + c22 * low[r, 2]
        g[r] -= low[r, 0] * e0 + low[r, 1] * e1 + low[r, 2] * e2
        for c in range(r, nh):
            mat[r, c] -= low[c, 0] * q0 + low[c, 1] * q1 + low[c, 2] * q2
    if nh == 2:
        s11, s12, s22 = mat[0, 0], mat[0, 1], mat[1, 1]
        det = s11 * s22 - s12 * s12
        if not (s11 > 0.0 and det > 0.0):
            return -math.inf
        stat = (s22 * g[0] * g[0] - 2.0 * s12 * g[0] * g[1] + s11 * g[1] * g[1]) / det
        return stat - q_table[k - 1]
    for r in range(nh):
        for c in range(r):
            mat[r, c] = mat[c, r]
    logdet = _cholesky_inverse(mat, inv, low, nh)  # (G_HL in low is used up)
    if not logdet == logdet:
        return -math.inf
    stat = 0.0
    for r in range(nh):
        for c in range(nh):
            stat += g[r] * inv[r, c] * g[c]
    return stat - q_table[k - 1]


# The score test's noise level is never below the smallest corruption SBL resolves: an inlier may
# deviate by up to the outlier threshold (at least 0.05 of the pixel scale, _solve's
# MIN_OUTLIER_THRESHOLD, "3 sigma"), so a residual the Lambertian fit calls noise does not make
# it fail (float renders estimate sigma ~ 0 and would fail on any sub-threshold sparse corruption).
GATE_NOISE = 0.05 / 3.0
# Residuals enter the score test clipped at this many noise levels (Huber's psi; SBL's flag).
GATE_CLIP = 3.0


def gate_variance(lam):
    """The score test's noise variance from a noise variance ``lam`` (array or float)."""
    return np.maximum(lam, GATE_NOISE**2)


def chi2_quantiles(n: int, false_alarm: float) -> np.ndarray:
    """(n + 1,) the chi^2 quantiles of ``1 - false_alarm`` for 0 .. n degrees of freedom."""
    return np.array(_chi2_quantiles(int(n), float(false_alarm)))


@functools.lru_cache(maxsize=64)
def _chi2_quantiles(n: int, false_alarm: float) -> tuple:
    # each tile asks again (scipy's ppf: ~0.5 ms, a tenth of a small tile's solve)
    return (math.inf, *chdtri(np.arange(1, n + 1), false_alarm).tolist())
