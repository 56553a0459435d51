"""The piecewise-linear model of one pixel: its design, the algebra of its fit, and its scores.

Ikehata, Wipf, Matsushita & Aizawa (TPAMI 2014): the diffuse intensity is an unknown monotonic
function of ``n.l``; turned around, ``n.l = f(y)`` with ``f`` piecewise linear in the observed
intensity ``y``, ``K`` segments with break points from the pixel's own usable observations
(``b_0 = 0``, ``b_k`` = the ``floor(k u / K)``-th smallest of the ``u`` usable ones, ``b_K`` the
largest). With ``phi_k(y) = clip(y - b_k, 0, b_{k+1} - b_k)`` and slopes ``s``,
``f(y) = sum_k s_k phi_k(y)``. The slopes sum to 1 (the scale); the constraint is eliminated,
``s_{K-1} = 1 - sum_{k<K-1} s_k``, so the unknowns are ``x = (s_0 .. s_{K-2}, n)`` (``U = K + 2``)
and observation i reads ``t_i = a_i . x + e_i`` with ``a_i = (phi_k - phi_{K-1} (k < K-1), -l_i)``
and ``t_i = -phi_{K-1}(y_i)``. ``K = 1`` is exactly the Lambertian model of SBL (``t = -y``,
``a = -l``).

Per pixel, inlined into the tile kernel of :mod:`._pl_kernels` (which iterates the fit):

- the design: the rows of the per-pixel state, the pixel's usable observations and break points
  (by selection), and the design rows ``a_i``, targets ``t_i`` and segment of every observation,
  for any ``K`` (:func:`_design`) and written out for the default three segments
  (:func:`_design3`, one pass);
- the fit's algebra: the slopes' prior (:func:`_prior`), the normal equations, the slopes from
  ``x``;
- the scores: the log evidence of a fit (:func:`_log_evidence`), the closed-form leave-one-out
  scores of the Lambertian and the PL fit and the default's choice between them
  (:func:`_choose`), and the robust score test of the Lambertian fit towards ``K`` segments
  (:func:`_bend_score`).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit
from scipy.special import chdtri  # chi^2 upper quantile: scipy.stats costs 0.7 s to import

from ps_lab.jit import INLINE

from . import _kernels
from ._linalg import SINGULAR_REL_DET, cholesky_inverse, inverse3, select_kth, weighted_sums3

# Rows of the per-pixel state: usable (1/0), observation noise in y units, in f units, gamma,
# d = w / (gamma + lambda), corruption estimate of the last iteration, residual, a^T M^-1 a,
# segment of the observation, target t.
_W, _LAM0, _LAM, _G, _D, _Z, _R, _Q, _SEG, _T = range(10)
STATE_ROWS = 10
MAX_SEGMENTS = 8
MIN_PER_SEGMENT = 4
# Smallest slope (times 1/K) used for an observation's noise and the Jacobian.
SLOPE_FLOOR = 1e-3
TAU_FLOOR = 1e-10
# The default's choice (:func:`_choose`): PL-SBL only with at least this many scored observations
# per unknown of the PL model: the mean leverage is then at most 1/4, so that a left-out residual
# measures prediction (with fewer, it is dominated by the 1 / (1 - h) inflation of interpolated
# observations; docs/solvers.md).
CHOICE_PER_UNKNOWN = 4
# The default's choice: PL-SBL replaces SBL where its leave-one-out gain exceeds this many standard
# errors of the gain (the one-standard-error rule of model selection, docs/solvers.md).
CHOICE_Z = 1.0
# The Lambertian model's score test: PL-SBL (which nests it) is fitted and compared only
# where the score statistic of SBL's fit exceeds its chi^2 quantile at this false-alarm rate.
GATE_FALSE_ALARM = 0.01
# The score test's noise level is never below the smallest corruption SBL resolves: an inlier may
# deviate by up to the outlier threshold (at least 0.05 of the pixel scale, _solve's
# MIN_OUTLIER_THRESHOLD, "3 sigma"), so a residual the Lambertian fit calls noise does not make
# it fail (float renders estimate sigma ~ 0 and would fail on any sub-threshold sparse corruption).
GATE_NOISE = 0.05 / 3.0
# Residuals enter the score test clipped at this many noise levels (Huber's psi; SBL's flag).
GATE_CLIP = 3.0


# --- the design: usable observations, break points, design rows and the state's start ------


@njit(**INLINE)
def _usable(y, w, p, n, vals):
    """Pack pixel p's usable observations into ``vals[:count]`` (no branch); their count."""
    cnt = 0
    for i in range(n):
        vals[cnt] = y[p, i]  # a dropped one is overwritten by the next
        cnt += w[p, i] > 0.0
    return cnt


@njit(**INLINE)
def _lit(y, w, lights, p, n, x0, x1, x2, vals):
    """Pack pixel p's usable observations that the Lambertian fit ``x`` predicts lit
    (``l_i . x > 0``) into ``vals[:count]`` (no branch); their count.

    The observations the break points are chosen from: the response ``f`` maps a shading
    ``n.l >= 0`` to an intensity, and an attached shadow (kept where no black level was found,
    a 16-bit capture's noise above 0) is not on it. Where shadows are a third of a pixel's
    observations, the first break would fall in their noise: a segment narrower than the noise,
    whose slope the constraint ``sum s = 1`` lets take all the scale, ``f`` and the normal
    collapsing towards 0 (docs/solvers.md).
    """
    cnt = 0
    for i in range(n):
        vals[cnt] = y[p, i]
        v = lights[i, 0] * x0 + lights[i, 1] * x1 + lights[i, 2] * x2
        cnt += w[p, i] > 0.0 and v > 0.0
    return cnt


@njit(**INLINE)
def _breaks(vals, cnt, k, breaks):
    """Break points of ``k`` segments from the ``cnt`` usable observations in ``vals``.

    ``b_0 = 0``, ``b_j`` the ``(j cnt) // k``-th smallest (a selection: ``vals`` is reordered),
    ``b_k`` the largest.
    """
    breaks[0] = 0.0
    top = vals[0]
    for i in range(1, cnt):
        top = vals[i] if vals[i] > top else top
    breaks[k] = top
    # the order statistics (j cnt) // K, increasing, each selected in the part right of the last
    lo = 0
    for j in range(1, k):
        kth = (j * cnt) // k
        breaks[j] = select_kth(vals, lo, cnt, kth)
        lo = kth


@njit(**INLINE)
def _break_points(y, w, lights, p, n, k_max, fit, use_fit, vals, breaks):
    """Pixel p's segments (up to ``k_max``) and their break points (``breaks[:k + 1]``); ``k``.

    At least ``MIN_PER_SEGMENT`` usable observations per segment (a segment's slope is fitted
    on its own observations: with fewer, it can bend to fit a corrupted one). The interior break
    points from the observations the Lambertian fit ``fit`` sees lit (:func:`_lit`, where
    ``use_fit``; all usable ones without that fit or with fewer than ``MIN_PER_SEGMENT`` a
    segment); ``b_K`` the largest usable observation.
    """
    cnt = _usable(y, w, p, n, vals)
    k = k_max if k_max < cnt // MIN_PER_SEGMENT else cnt // MIN_PER_SEGMENT
    k = k if k > 1 else 1
    top = breaks[0]
    if use_fit and k > 1:
        top = vals[0]
        for i in range(1, cnt):
            top = vals[i] if vals[i] > top else top
    lit = _lit(y, w, lights, p, n, fit[0], fit[1], fit[2], vals) if use_fit and k > 1 else 0
    if lit < k * MIN_PER_SEGMENT:
        _usable(y, w, p, n, vals)
        lit = cnt
    _breaks(vals, lit, k, breaks)
    breaks[k] = top if lit < cnt else breaks[k]
    return k


@njit(**INLINE)
def _design3(y, w, lights, p, lam_row, scale2, gamma, sbl, st, tab, breaks):
    """:func:`_design` and the start of the state for three segments, one vectorised pass.

    The same numbers as the generic path: design rows (0-4), target, segment, and each
    observation's noise (``lam_row``; times ``scale2`` in ``f``'s units), variance ``gamma`` and
    weight ``d`` (``gamma`` left out of ``d`` without ``sbl``).
    """
    n = y.shape[1]
    b1 = breaks[1]
    b2 = breaks[2]
    w0 = b1 - breaks[0]
    w1 = b2 - b1
    w2 = breaks[3] - b2
    lo0 = breaks[0]
    g_d = gamma if sbl else 0.0
    for i in range(n):
        yi = y[p, i]
        wi = w[p, i]
        ph = yi - b2
        ph = ph if ph > 0.0 else 0.0
        ph = ph if ph < w2 else w2
        t = -ph * wi
        st[_T, i] = t
        st[_W, i] = wi
        st[_SEG, i] = (1.0 if yi > b1 else 0.0) + (1.0 if yi > b2 else 0.0)
        ph = yi - lo0
        ph = ph if ph > 0.0 else 0.0
        ph = ph if ph < w0 else w0
        tab[0, i] = ph * wi + t
        ph = yi - b1
        ph = ph if ph > 0.0 else 0.0
        ph = ph if ph < w1 else w1
        tab[1, i] = ph * wi + t
        tab[2, i] = -lights[i, 0] * wi
        tab[3, i] = -lights[i, 1] * wi
        tab[4, i] = -lights[i, 2] * wi
        lam = lam_row[i]
        st[_LAM0, i] = lam
        st[_LAM, i] = lam * scale2
        st[_G, i] = gamma
        st[_D, i] = wi / (g_d + lam * scale2)
        st[_Z, i] = 0.0


@njit(**INLINE)
def _design(y, w, lights, p, k, lam_row, scale2, start, sbl, st, tab, breaks):
    """Design rows and products of pixel p for ``k`` segments (``breaks``: :func:`_breaks`) and
    the start of the state (as :func:`_design3`, ``gamma = start scale2``)."""
    n = y.shape[1]
    u = k + 2
    ns = k - 1
    # phi_j(y) = clip(y - b_j, 0, b_{j+1} - b_j), one vectorised loop per segment; the last
    # segment's phi is the target (in row _T, negated), the others are differences to it
    lo = breaks[ns]
    width = breaks[k] - lo
    for i in range(n):
        ph = y[p, i] - lo
        ph = ph if ph > 0.0 else 0.0
        ph = ph if ph < width else width
        st[_T, i] = -ph * w[p, i]
        st[_W, i] = w[p, i]
        st[_SEG, i] = 0.0
    for j in range(ns):
        lo = breaks[j]
        width = breaks[j + 1] - lo
        cut = breaks[j + 1]
        for i in range(n):
            ph = y[p, i] - lo
            ph = ph if ph > 0.0 else 0.0
            ph = ph if ph < width else width
            tab[j, i] = ph * w[p, i] + st[_T, i]
            st[_SEG, i] += 1.0 if y[p, i] > cut else 0.0
    for i in range(n):
        wi = w[p, i]
        tab[ns, i] = -lights[i, 0] * wi
        tab[ns + 1, i] = -lights[i, 1] * wi
        tab[ns + 2, i] = -lights[i, 2] * wi
    # products a_a^T (upper triangle, row-major) on rows u .. u + u(u+1)/2
    e = u
    for r in range(u):
        for c in range(r, u):
            for i in range(n):
                tab[e, i] = tab[r, i] * tab[c, i]
            e += 1
    for i in range(n):
        st[_LAM0, i] = lam_row[i]
        st[_LAM, i] = lam_row[i] * scale2
        st[_G, i] = start * scale2
        st[_D, i] = st[_W, i] / ((st[_G, i] if sbl else 0.0) + st[_LAM, i])
        st[_Z, i] = 0.0


# --- the fit's algebra: prior, normal equations, slopes, log evidence ----------------------


@njit(**INLINE)
def _prior(k, tau2, ridge, prior, prior_rhs):
    """Prior precision of x: ``(I + 11^T) / tau2`` on the free slopes, ``ridge`` on the normal."""
    u = k + 2
    ns = k - 1
    for r in range(u):
        prior_rhs[r] = 1.0 / tau2 if r < ns else 0.0
        for c in range(u):
            if r < ns and c < ns:
                prior[r, c] = (2.0 if r == c else 1.0) / tau2
            elif r == c:
                prior[r, c] = ridge
            else:
                prior[r, c] = 0.0


@njit(**INLINE)
def _normal_equations(st, tab, n, u, mat, rhs, prior, prior_rhs):
    """``mat = prior + sum_i d_i a_i a_i^T`` and ``rhs = prior_rhs + sum_i d_i t_i a_i`` (u x u, u).

    From the state's weights ``d`` and targets ``t`` and the design's rows and products
    (:func:`_design`); ``prior``, ``prior_rhs``: :func:`_prior`.
    """
    e = u
    for r in range(u):
        acc = 0.0
        for i in range(n):
            acc += st[_D, i] * st[_T, i] * tab[r, i]
        rhs[r] = prior_rhs[r] + acc
        for c in range(r, u):
            acc = 0.0
            for i in range(n):
                acc += st[_D, i] * tab[e, i]
            mat[r, c] = prior[r, c] + acc
            mat[c, r] = mat[r, c]
            e += 1


@njit(**INLINE)
def _slopes(x, k, slopes):
    """The ``k`` slopes of ``x``: its ``k - 1`` free ones and the last, ``1 -`` their sum."""
    last = 1.0
    for j in range(k - 1):
        slopes[j] = x[j]
        last -= x[j]
    slopes[k - 1] = last


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
def _log_evidence(st, n, k, u, x, slopes, ridge, tau2, logdet, full, vals):
    """Log evidence of the final PL-SBL fit (the state's rows) in the space of ``y``.

    The Gaussian marginal of ``t`` at the learned ``gamma``, ``tau2`` (``logdet``: ``log det M``
    of the final normal equations) plus the log Jacobian ``sum_i log s_{k(i)}`` of ``y -> f(y)``.
    ``full`` False (the choice, which does not use it): only its ``-inf`` cases (a segment holding
    observations with a slope <= 0), else 0. ``vals`` (k,): scratch.
    """
    if not full:
        # only what makes the evidence -inf: the log Jacobian of a populated segment's slope <= 0
        for j in range(k):
            vals[j] = 0.0
        for i in range(n):
            vals[int(st[_SEG, i])] += st[_W, i]
        for j in range(k):
            if vals[j] > 0.0 and not slopes[j] > 0.0:
                return -math.inf
        return 0.0
    # log evidence of y: -1/2 [sum log c + log|M| - log|P| + sum d r^2 + dx^T P dx] + log Jacobian
    quad = 0.0
    for i in range(n):
        quad += st[_D, i] * st[_R, i] * st[_R, i]
    logc = _sum_log(st, _W, _G, _LAM, n)
    # log Jacobian: sum over observations of log(slope of their segment), one log per segment
    for j in range(k):
        vals[j] = 0.0
    for i in range(n):
        if st[_W, i] > 0.0:
            vals[int(st[_SEG, i])] += 1.0
    jac = 0.0
    for j in range(k):
        if vals[j] > 0.0:
            jac += vals[j] * math.log(slopes[j]) if slopes[j] > 0.0 else -math.inf
    ns = k - 1
    logdet_p = 3.0 * math.log(ridge)
    if ns > 0:
        logdet_p += math.log(k) - ns * math.log(tau2)
        dsum = 0.0
        dsq = 0.0
        for j in range(ns):
            dv = x[j] - 1.0 / k
            dsum += dv
            dsq += dv * dv
        quad += (dsq + dsum * dsum) / tau2
    for r in range(ns, u):
        quad += ridge * x[r] * x[r]
    return -0.5 * (logc + logdet - logdet_p + quad) + jac


# --- the scores: leave-one-out, the default's choice, the score test ------------------------


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
    xx, yy, zz, xy, xz, yz, t0, t1, t2 = weighted_sums3(fw, y, tab, n)
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
    logdet = cholesky_inverse(mat, inv, low, u)
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
def _loo_pl3(st, tab, n, inv, sw, slope_of, out):
    """:func:`_loo_pl` of the three-segment fit that :func:`._pl_kernels._iterate3` left.

    Its final solve is the fit that ``_loo_pl`` would form again from the same weights ``d``,
    prior (the ``tau2`` it used) and targets: ``inv`` holds its ``M^-1`` and the state row
    ``_R`` its residuals ``t - a.x``, so only the leverages ``h_i = d_i a_i^T M^-1 a_i`` are
    left, one vectorised pass. Same measure and returns (infinity when a scored ``h_i`` is 1).
    """
    i00, i11, i22, i33, i44 = inv[0, 0], inv[1, 1], inv[2, 2], inv[3, 3], inv[4, 4]
    j01, j02, j03, j04 = 2.0 * inv[0, 1], 2.0 * inv[0, 2], 2.0 * inv[0, 3], 2.0 * inv[0, 4]
    j12, j13, j14 = 2.0 * inv[1, 2], 2.0 * inv[1, 3], 2.0 * inv[1, 4]
    j23, j24, j34 = 2.0 * inv[2, 3], 2.0 * inv[2, 4], 2.0 * inv[3, 4]
    score = 0.0
    bad = 0
    for i in range(n):
        a0 = tab[0, i]
        a1 = tab[1, i]
        a2 = tab[2, i]
        a3 = tab[3, i]
        a4 = tab[4, i]
        q = (a0 * (i00 * a0 + j01 * a1 + j02 * a2 + j03 * a3 + j04 * a4)
             + a1 * (i11 * a1 + j12 * a2 + j13 * a3 + j14 * a4)
             + a2 * (i22 * a2 + j23 * a3 + j24 * a4)
             + a3 * (i33 * a3 + j34 * a4) + a4 * i44 * a4)
        h = st[_D, i] * q
        scored = sw[i] > 0.0
        bad += scored and not h < 1.0
        e = st[_R, i] / ((1.0 - h) * slope_of[i])
        term = sw[i] * e * e if scored else 0.0
        out[i] = term
        score += term
    return math.inf if bad else score


@njit(**INLINE)
def _choose(y, p, n, k, threshold, lam_row, outliers, st, tab, sbl_st, sbl_tab, slopes, tau2,
            ridge, sw, slope_of, prior, prior_rhs, mat, inv, low, scratch, loo, z):
    """The piecewise-linear model's predictive gain over the Lambertian one at pixel p.

    Scored: the usable observations that at least one robust fit accepts as uncorrupted (SBL's
    flags in ``outliers[p]``, the PL fit's from its final state): a model that calls corrupted
    what the other explains pays for it; what both call corrupted says nothing about either.
    Each model is scored as fitted (its final weights ``d``; PL with its slopes' prior)
    by its closed-form leave-one-out residuals in ``y``'s units, under the same noise (SBL's
    ``lambda_i``): :func:`_loo_lambertian`, :func:`_loo_pl`. The gain
    is the sum of the paired differences ``d_i`` of the two squared left-out residuals
    (Lambertian minus PL) less ``z`` standard errors of that sum (``z sqrt(N) sd(d)``): positive
    when PL predicts better by more than chance gives a model with more unknowns; -inf when
    fewer than ``CHOICE_PER_UNKNOWN`` observations per PL unknown are scored or a fit fails.
    Three segments: PL's fit is :func:`._pl_kernels._pl_pixel`'s final one (its ``M^-1`` in
    ``inv``, its residuals in the state), not formed again (:func:`_loo_pl3`).
    """
    u = k + 2
    kept = 0
    fl = SLOPE_FLOOR / k
    s0 = slopes[0] if slopes[0] > fl else fl
    s1 = slopes[1 % k] if slopes[1 % k] > fl else fl
    s2 = slopes[2 % k] if slopes[2 % k] > fl else fl
    for i in range(n):
        if k == 3:  # (one vectorised pass: the slope by selects, not by an index)
            seg = st[_SEG, i]
            sl = s2 if seg > 1.5 else (s1 if seg > 0.5 else s0)
        else:
            sl = slopes[int(st[_SEG, i])]
            sl = sl if sl > fl else fl
        slope_of[i] = sl
        e = st[_G, i] * st[_D, i] * st[_R, i] / sl
        flagged = outliers[p, i] and abs(e) > threshold
        ok = st[_W, i] > 0.0 and not flagged
        sw[i] = 1.0 / lam_row[i] if ok else 0.0
        kept += ok
    if kept < CHOICE_PER_UNKNOWN * u:
        return -math.inf
    score_sbl = _loo_lambertian(y[p], sbl_st[_kernels._V], sw, sbl_tab, n, ridge, loo[0])
    if k == 3:
        score_pl = _loo_pl3(st, tab, n, inv, sw, slope_of, loo[1])
    else:
        _prior(k, tau2, ridge, prior, prior_rhs)
        score_pl = _loo_pl(st[_T], st[_D], sw, slope_of, tab, n, u, prior, prior_rhs, mat, inv,
                           low, scratch, loo[1])
    if not (score_pl < math.inf and score_sbl == score_sbl):
        return -math.inf
    if not score_sbl < math.inf:
        return math.inf
    mean = (score_sbl - score_pl) / kept
    var = 0.0
    for i in range(n):
        d = loo[0, i] - loo[1, i] - mean
        var += d * d if sw[i] > 0.0 else 0.0
    return (score_sbl - score_pl) - z * math.sqrt(kept * var / (kept - 1))


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
            col[j] = select_kth(vals, lo, cnt, kth)
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
    logdet = cholesky_inverse(mat, inv, low, nh)  # (G_HL in low is used up)
    if not logdet == logdet:
        return -math.inf
    stat = 0.0
    for r in range(nh):
        for c in range(nh):
            stat += g[r] * inv[r, c] * g[c]
    return stat - q_table[k - 1]


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
