"""The piecewise-linear model's design per pixel: usable values, break points, design rows, the
normal equations and prior of ``K`` segments; the fit's flags and the default's choice.

Shared by the tile kernels of :mod:`._pl_kernels` (inlined into them): the rows of the per-pixel
state, the pixel's usable observations and break points (``b_k`` the ``floor(k u / K)``-th
smallest usable value, by selection), and the design rows ``a_i``, targets ``t_i`` and segment of
every observation, for any ``K`` (:func:`_design`) and written out for the default three
segments (:func:`_design3`, one pass). See :mod:`._pl_kernels` for the model.
"""

from __future__ import annotations

import math

from numba import njit

from . import _kernels
from ._kernels import INLINE
from ._pl_algebra import _loo_lambertian, _loo_pl, _select

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
        breaks[j] = _select(vals, lo, cnt, kth)
        lo = kth


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
def _design(y, w, lights, p, k, st, tab, breaks):
    """Design rows and products of pixel p for ``k`` segments (``breaks``: :func:`_breaks`)."""
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


@njit(**INLINE)
def _normal_equations(st, tab, n, u, mat, rhs, prior, prior_rhs):
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
def _slopes(x, k, slopes):
    last = 1.0
    for j in range(k - 1):
        slopes[j] = x[j]
        last -= x[j]
    slopes[k - 1] = last


@njit(**INLINE)
def _loo_pl3(st, tab, n, inv, sw, slope_of, out):
    """:func:`._pl_algebra._loo_pl` of the three-segment fit that :func:`_iterate3` left.

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
def _finish(p, k, x, slopes, breaks, st, n, threshold, x_out, outliers, segments_out):
    """Albedo-normal of pixel p (the normal times the secant slope ``b_K / f(b_K)``), flags."""
    ns = k - 1
    fb = 0.0
    for j in range(k):
        fb += slopes[j] * (breaks[j + 1] - breaks[j])
    gain = breaks[k] / fb if fb > 0.0 else 0.0
    x_out[p, 0] = x[ns] * gain
    x_out[p, 1] = x[ns + 1] * gain
    x_out[p, 2] = x[ns + 2] * gain
    segments_out[p] = k
    for i in range(n):
        sl = slopes[int(st[_SEG, i])]
        sl = sl if sl > SLOPE_FLOOR / k else SLOPE_FLOOR / k
        # the corruption in the pixel's units: e = Gamma S t = gamma d r, over the slope
        e = st[_G, i] * st[_D, i] * st[_R, i] / sl
        outliers[p, i] = st[_W, i] > 0.0 and abs(e) > threshold


@njit(**INLINE)
def _choose(y, p, n, k, threshold, lam_row, outliers, st, tab, sbl_st, sbl_tab, slopes, tau2,
            ridge, sw, slope_of, prior, prior_rhs, mat, inv, low, scratch, loo, z):
    """The piecewise-linear model's predictive gain over the Lambertian one at pixel p.

    Scored: the usable observations that at least one robust fit accepts as uncorrupted (SBL's
    flags in ``outliers[p]``, the PL fit's from its final state): a model that calls corrupted
    what the other explains pays for it; what both call corrupted says nothing about either.
    Each model is scored as fitted (its final weights ``d``; PL with its slopes' prior)
    by its closed-form leave-one-out residuals in ``y``'s units, under the same noise (SBL's
    ``lambda_i``): :func:`._pl_algebra._loo_lambertian`, :func:`._pl_algebra._loo_pl`. The gain
    is the sum of the paired differences ``d_i`` of the two squared left-out residuals
    (Lambertian minus PL) less ``z`` standard errors of that sum (``z sqrt(N) sd(d)``): positive
    when PL predicts better by more than chance gives a model with more unknowns; -inf when
    fewer than ``CHOICE_PER_UNKNOWN`` observations per PL unknown are scored or a fit fails.
    Three segments: PL's fit is :func:`_pl_pixel`'s final one (its ``M^-1`` in ``inv``, its
    residuals in the state), not formed again (:func:`_loo_pl3`).
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
