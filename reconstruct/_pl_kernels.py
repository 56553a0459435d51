"""Tile kernels of the piecewise-linear models: PL-LS, PL-SBL and the per-pixel choice (numba).

The model of Ikehata, Wipf, Matsushita & Aizawa (TPAMI 2014), ``n.l = f(y)`` with ``f`` piecewise
linear in the observed intensity, its design, the algebra of its fit and its scores, is
:mod:`._pl_model`; here each pixel's fit is iterated (:func:`_pl_pixel`, written out for three
segments in :func:`_iterate3`) and a tile's pixels are run (:func:`_pl_kernel`, :func:`pl_tile`).

The sparse errors ``e`` are learned with the SBL of Ikehata et al. 2012 (see :mod:`._kernels`):
one variance ``gamma_i`` per observation, ``gamma <- z^2 + u``. Here the normal equations are
``U x U`` (``M = P + sum_i d_i a_i a_i^T``, ``P`` the prior precision) and are inverted by
Cholesky. Beyond the paper (docs/solvers.md has the measurements):

- the slopes' Gaussian prior is centred on equal slopes (under the sum constraint the authors'
  zero-mean prior of variance 1 is the same thing) and its variance ``tau^2`` (start 1, the
  authors') is learned per pixel by the same EM (``tau^2 <- E|s - 1/K|^2 / (K - 1)``), so a
  pixel whose data are linear shrinks to the Lambertian model;
- the noise of an observation in ``f``'s units is its noise in ``y`` times its segment's slope:
  ``lambda_i = lam_i s_{k(i)}^2`` (``lam_i`` the SBL noise variance of the observation in the
  pixel's relative units), updated with the slopes;
- each pixel's log evidence in the space of ``y`` (the Gaussian marginal of ``t`` at the learned
  ``gamma``, ``tau^2``, plus the log Jacobian ``sum_i log s_{k(i)}`` of ``y -> f(y)``; recorded,
  no longer used for the choice);
- PL-SBL alone (issue 42) fits SBL first (the Lambertian model it nests) and the PL model
  twice: as above (break points from all usable observations, the EM from ``gamma_start``),
  and with the interior break points from the observations SBL's fit sees lit (``l_i . x >
  0``) and the EM from SBL's final ``gamma``; the fit of the higher log evidence is kept (the
  break points and the start are choices of the same model). Kept shadows (no black level
  found) put the first break in their noise, and the EM all the scale on that segment's slope
  (``f`` and the normal collapse); a glossy pixel's EM from the flat start flattens the top
  segment to take the specular lobe as response;
- the ``auto`` kernel solves every pixel with ``K = 1`` (SBL, its own kernel and iterations);
  where SBL's fit fails a chi^2 score test towards K segments it fits them too, and keeps PL
  only where it predicts the pixel's observations better (closed-form leave-one-out residuals
  by more than one standard error of the gain: :func:`._pl_model._choose`, docs/solvers.md).

Inputs are those of :mod:`._kernels` (``y`` (m, n) scaled, ``w`` (m, n) 1/0, lights (n, 3) or,
for near lights, (m, n, 3)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from ps_lab.jit import INLINE, VECTOR

from . import _kernels
from ._kernels import TileResult, _light_table, _sbl_pixel
from ._linalg import cholesky_inverse, inverse5
from ._pl_model import (
    _W,
    _LAM0,
    _LAM,
    _G,
    _D,
    _Z,
    _R,
    _Q,
    _SEG,
    _T,
    STATE_ROWS,
    SLOPE_FLOOR,
    TAU_FLOOR,
    CHOICE_Z,
    GATE_FALSE_ALARM,
    _break_points,
    _design3,
    _design,
    _normal_equations,
    _prior,
    _slopes,
    _log_evidence,
    _choose,
    _bend_score,
    chi2_quantiles,
)


@njit(**INLINE)
def _iterate3(st, tab, n, ridge, learn_tau, max_iter, ftol, floor, sbl, inv, x, slopes, tau2):
    """The iteration of :func:`_pl_pixel` for three segments (the default), written out.

    The five unknowns' normal equations (15 products, 5 right-hand sides) are summed in one
    loop and the residual, ``a^T M^-1 a``, the gamma, lambda and d updates in a second one, so
    each loop runs over the lights once, vectorised (the generic path makes ~40 passes); ``M``
    is inverted by :func:`._linalg.inverse5` (blocks, in registers, no log per step).
    Same algebra as the generic path (rounding-level differences). Returns (iterations,
    log det M, tau2); log det is NaN when ``M`` is not positive definite. Leaves the final
    ``M^-1`` in ``inv`` (for :func:`._pl_model._loo_pl3`).
    """
    iters = max_iter if sbl else 1
    it = 0
    done = not sbl
    fl = SLOPE_FLOOR / 3.0
    while True:
        m00 = m01 = m02 = m03 = m04 = m11 = m12 = m13 = m14 = 0.0
        m22 = m23 = m24 = m33 = m34 = m44 = 0.0
        r0 = r1 = r2 = r3 = r4 = 0.0
        for i in range(n):
            d = st[_D, i]
            a0 = tab[0, i]
            a1 = tab[1, i]
            a2 = tab[2, i]
            a3 = tab[3, i]
            a4 = tab[4, i]
            dt = d * st[_T, i]
            r0 += dt * a0
            r1 += dt * a1
            r2 += dt * a2
            r3 += dt * a3
            r4 += dt * a4
            da0 = d * a0
            da1 = d * a1
            da2 = d * a2
            da3 = d * a3
            m00 += da0 * a0
            m01 += da0 * a1
            m02 += da0 * a2
            m03 += da0 * a3
            m04 += da0 * a4
            m11 += da1 * a1
            m12 += da1 * a2
            m13 += da1 * a3
            m14 += da1 * a4
            m22 += da2 * a2
            m23 += da2 * a3
            m24 += da2 * a4
            m33 += da3 * a3
            m34 += da3 * a4
            m44 += d * a4 * a4
        it2 = 1.0 / tau2
        det, iv = inverse5(m00 + 2.0 * it2, m01 + it2, m02, m03, m04, m11 + 2.0 * it2, m12,
                            m13, m14, m22 + ridge, m23, m24, m33 + ridge, m34, m44 + ridge)
        if not det == det:
            return iters, det, tau2
        i00, i01, i02, i03, i04, i11, i12, i13, i14, i22, i23, i24, i33, i34, i44 = iv
        r0 += it2
        r1 += it2
        x0 = i00 * r0 + i01 * r1 + i02 * r2 + i03 * r3 + i04 * r4
        x1 = i01 * r0 + i11 * r1 + i12 * r2 + i13 * r3 + i14 * r4
        x2 = i02 * r0 + i12 * r1 + i22 * r2 + i23 * r3 + i24 * r4
        x3 = i03 * r0 + i13 * r1 + i23 * r2 + i33 * r3 + i34 * r4
        x4 = i04 * r0 + i14 * r1 + i24 * r2 + i34 * r3 + i44 * r4
        x[0], x[1], x[2], x[3], x[4] = x0, x1, x2, x3, x4
        slopes[0], slopes[1], slopes[2] = x0, x1, 1.0 - x0 - x1
        if done or it == max_iter:
            for i in range(n):
                st[_R, i] = st[_T, i] - (x0 * tab[0, i] + x1 * tab[1, i] + x2 * tab[2, i]
                                         + x3 * tab[3, i] + x4 * tab[4, i])
            # the final M^-1 for the choice (_pl_model._loo_pl3)
            inv[0, 0], inv[1, 1], inv[2, 2], inv[3, 3], inv[4, 4] = i00, i11, i22, i33, i44
            inv[0, 1] = inv[1, 0] = i01
            inv[0, 2] = inv[2, 0] = i02
            inv[0, 3] = inv[3, 0] = i03
            inv[0, 4] = inv[4, 0] = i04
            inv[1, 2] = inv[2, 1] = i12
            inv[1, 3] = inv[3, 1] = i13
            inv[1, 4] = inv[4, 1] = i14
            inv[2, 3] = inv[3, 2] = i23
            inv[2, 4] = inv[4, 2] = i24
            inv[3, 4] = inv[4, 3] = i34
            return iters, math.log(det), tau2
        j01, j02, j03, j04 = 2.0 * i01, 2.0 * i02, 2.0 * i03, 2.0 * i04
        j12, j13, j14 = 2.0 * i12, 2.0 * i13, 2.0 * i14
        j23, j24, j34 = 2.0 * i23, 2.0 * i24, 2.0 * i34
        sl0 = x0 if x0 > fl else fl
        sl1 = x1 if x1 > fl else fl
        sl2 = 1.0 - x0 - x1
        sl2 = sl2 if sl2 > fl else fl
        moved = 0
        for i in range(n):
            a0 = tab[0, i]
            a1 = tab[1, i]
            a2 = tab[2, i]
            a3 = tab[3, i]
            a4 = tab[4, i]
            r = st[_T, i] - (x0 * a0 + x1 * a1 + x2 * a2 + x3 * a3 + x4 * a4)
            q = (a0 * (i00 * a0 + j01 * a1 + j02 * a2 + j03 * a3 + j04 * a4)
                 + a1 * (i11 * a1 + j12 * a2 + j13 * a3 + j14 * a4)
                 + a2 * (i22 * a2 + j23 * a3 + j24 * a4)
                 + a3 * (i33 * a3 + j34 * a4) + a4 * i44 * a4)
            gi = st[_G, i]
            di = st[_D, i]
            gd = gi * di
            z = gd * r
            gn = z * z + (gi - gi * gd * (1.0 - di * q))
            gn = gn if gn > floor else floor
            st[_G, i] = gn
            moved += abs(z - st[_Z, i]) >= ftol
            st[_Z, i] = z
            seg = st[_SEG, i]
            sl = sl2 if seg > 1.5 else (sl1 if seg > 0.5 else sl0)
            lam = st[_LAM0, i] * sl * sl
            st[_LAM, i] = lam
            st[_D, i] = st[_W, i] / (gn + lam)
        if learn_tau:
            dv0 = x0 - 1.0 / 3.0
            dv1 = x1 - 1.0 / 3.0
            tr = 2.0 * (i00 + i11 + i01)
            tau2 = (dv0 * dv0 + dv1 * dv1 + (dv0 + dv1) ** 2 + tr) / 2.0
            tau2 = tau2 if tau2 > TAU_FLOOR else TAU_FLOOR
        it += 1
        if moved == 0:
            iters = it
            done = True


@njit(**INLINE)
def _pl_pixel(y, w, lights, p, k_max, lam_row, ridge, learn_tau, max_iter, tol, floor, start,
              sbl, st, tab, mat, inv, low, x, rhs, prior, prior_rhs, breaks, vals, slopes,
              evidence, g0, use_g0, fit, use_fit):
    """One pixel with up to ``k_max`` segments (fewer when it has few observations).

    Leaves ``x`` (U), ``slopes`` (K) and the state rows of the final iteration (and, for three
    segments, ``inv`` = the final ``M^-1``: :func:`._pl_model._loo_pl3`); returns (segments used,
    iterations, log evidence, the slopes' prior variance). ``sbl`` False: one weighted
    least-squares solve (PL-LS: every observation weight 1, no noise model). ``evidence``
    False (the choice, which does not use it): the log evidence is only its ``-inf`` cases (a
    failed solve, a segment holding observations with a slope <= 0), else 0.
    """
    n = y.shape[1]
    k = _break_points(y, w, lights, p, n, k_max, fit, use_fit, vals, breaks)
    u = k + 2
    tau2 = 1.0
    scale2 = 1.0 / (k * k)
    if k == 3:
        _design3(y, w, lights, p, lam_row, scale2, start * scale2, sbl, st, tab, breaks)
    else:
        _design(y, w, lights, p, k, lam_row, scale2, start, sbl, st, tab, breaks)
    if use_g0 and sbl:
        # the EM starts from the Lambertian model's robust fit (SBL's final gamma, in f's units)
        for i in range(n):
            g = g0[i] * scale2
            st[_G, i] = g
            st[_D, i] = st[_W, i] / (g + st[_LAM, i])
    for j in range(k):
        slopes[j] = 1.0 / k
    ftol = tol / k
    iters = max_iter if sbl else 1
    logdet = math.nan
    it = 0
    done = not sbl
    if k == 3:
        iters, logdet, tau2 = _iterate3(st, tab, n, ridge, learn_tau, max_iter, ftol, floor, sbl,
                                        inv, x, slopes, tau2)
        if not logdet == logdet:
            for r in range(u):
                x[r] = 0.0
            return k, iters, -math.inf, tau2
        done = True  # skip the generic loop
    while not (k == 3):
        _prior(k, tau2, ridge, prior, prior_rhs)
        _normal_equations(st, tab, n, u, mat, rhs, prior, prior_rhs)
        logdet = cholesky_inverse(mat, inv, low, u)
        if not logdet == logdet:
            for r in range(u):
                x[r] = 0.0
            return k, iters, -math.inf, tau2
        for r in range(u):
            acc = 0.0
            for c in range(u):
                acc += inv[r, c] * rhs[c]
            x[r] = acc
        _slopes(x, k, slopes)
        # residuals t - a.x and q = a^T M^-1 a (vectorised over the lights)
        for i in range(n):
            st[_R, i] = st[_T, i]
            st[_Q, i] = 0.0
        for r in range(u):
            xr = x[r]
            for i in range(n):
                st[_R, i] -= xr * tab[r, i]
        e = u
        for r in range(u):
            for c in range(r, u):
                coef = inv[r, c] if r == c else 2.0 * inv[r, c]
                for i in range(n):
                    st[_Q, i] += coef * tab[e, i]
                e += 1
        if done or it == max_iter:
            break
        moved = 0
        for i in range(n):
            gi = st[_G, i]
            di = st[_D, i]
            gd = gi * di
            z = gd * st[_R, i]
            gn = z * z + (gi - gi * gd * (1.0 - di * st[_Q, i]))
            gn = gn if gn > floor else floor
            st[_G, i] = gn
            moved += abs(z - st[_Z, i]) >= ftol
            st[_Z, i] = z
        if k > 1:
            if learn_tau:
                # E|s - 1/K|^2 over the K slopes = dev^T (I + 11^T) dev + tr((I + 11^T) Cov)
                ns = k - 1
                dsum = 0.0
                dsq = 0.0
                tr = 0.0
                for j in range(ns):
                    dv = x[j] - 1.0 / k
                    dsum += dv
                    dsq += dv * dv
                    for c in range(ns):
                        tr += inv[j, c]
                    tr += inv[j, j]
                tau2 = (dsq + dsum * dsum + tr) / ns
                tau2 = tau2 if tau2 > TAU_FLOOR else TAU_FLOOR
            for i in range(n):
                sl = slopes[int(st[_SEG, i])]
                sl = sl if sl > SLOPE_FLOOR / k else SLOPE_FLOOR / k
                st[_LAM, i] = st[_LAM0, i] * sl * sl
        for i in range(n):
            st[_D, i] = st[_W, i] / (st[_G, i] + st[_LAM, i])
        it += 1
        if moved == 0:
            iters = it
            done = True
    if not sbl:
        return k, 1, 0.0, tau2
    return k, iters, _log_evidence(st, n, k, u, x, slopes, ridge, tau2, logdet, evidence,
                                   vals), tau2


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


@njit(nogil=True, cache=True, **VECTOR)
def _pl_kernel(y, w, lights, per_pixel, lam, lam_pl, k_max, choose, sbl, ridge, learn_tau,
               max_iter,
               sbl_max_iter, tol, floor, start, threshold, x_out, outliers, iters, segments_out,
               evidence_out, want_residuals, resid_out, choice_z, gate, lam_test, q_table,
               run_sbl, run_pl, v_io, stat_out, breaks_io, breaks_known, sbl_start):
    m, n = y.shape
    umax = k_max + 2
    st = np.zeros((STATE_ROWS, n))
    tab = np.zeros((umax + umax * (umax + 1) // 2, n))
    mat = np.zeros((umax, umax))
    inv = np.zeros((umax, umax))
    low = np.zeros((umax, umax))
    prior = np.zeros((umax, umax))
    x = np.zeros(umax)
    rhs = np.zeros(umax)
    prior_rhs = np.zeros(umax)
    breaks = np.zeros(k_max + 1)
    vals = np.zeros(n)
    slopes = np.zeros(k_max)
    sbl_st = np.zeros((_kernels.STATE_ROWS, n))
    sbl_tab = np.zeros((9, n))
    kv = np.zeros(n)
    slope_of = np.zeros(n)
    loo = np.zeros((2, n))
    scratch = np.zeros(umax)
    g0 = np.zeros(n)
    fit = np.zeros(3)
    start_sbl = sbl and sbl_start and not choose
    if (choose or start_sbl) and not per_pixel:
        _light_table(lights[0], sbl_tab)
    for p in range(m):
        lp = lights[p] if per_pixel else lights[0]
        lam_row = lam[p]
        if choose or start_sbl:
            # the Lambertian model (K = 1: SBL, its own kernel) first: the choice keeps it unless
            # K segments predict the pixel's kept observations better (_choose); PL-SBL alone
            # starts its EM from its robust fit
            if per_pixel:
                _light_table(lp, sbl_tab)
            for i in range(n):
                sbl_st[_kernels._Y, i] = y[p, i]
                sbl_st[_kernels._W, i] = w[p, i]
                sbl_st[_kernels._LAM, i] = lam_row[i]
            if run_sbl or start_sbl:
                _sbl_pixel(sbl_st, sbl_tab, n, ridge, sbl_max_iter, tol, floor, start, threshold,
                           x_out, outliers, iters, p)
        if choose:
            if run_sbl:
                segments_out[p] = 1
                for i in range(n):
                    v_io[p, i] = sbl_st[_kernels._V, i]
            else:  # SBL's fit of an earlier pass (x_out, outliers, iters and its weights)
                for i in range(n):
                    sbl_st[_kernels._V, i] = v_io[p, i]
            if k_max == 1:
                continue
            if gate:
                # the Lambertian model's score test towards K segments: PL only where it fails
                stat_out[p] = _bend_score(y, w, sbl_tab, p, n, k_max, x_out, lam_test[p], q_table,
                                          vals, mat, inv, low, x, rhs, breaks_io[p], breaks_known)
                if not stat_out[p] > 0.0:
                    continue
            if not run_pl:
                continue
        fit[0], fit[1], fit[2] = x_out[p, 0], x_out[p, 1], x_out[p, 2]  # SBL's, if it ran
        full = start_sbl or not choose  # the log evidence itself, not only its -inf cases
        k, it, ev, tau2 = _pl_pixel(y, w, lp, p, k_max, lam_pl[p], ridge, learn_tau, max_iter,
                                    tol, floor, start, sbl, st, tab, mat, inv, low, x, rhs, prior,
                                    prior_rhs, breaks, vals, slopes, full, g0, False, fit, False)
        if start_sbl and k > 1:
            # the second fit: break points from what SBL's fit sees lit, the EM from SBL's final
            # gamma (from its weights d = w / (gamma + lambda)); the fit of the higher log
            # evidence is kept (the first, where it wins, fitted again: its state is the kept
            # fit's for the choice and _finish)
            for i in range(n):
                v = sbl_st[_kernels._V, i]
                g = 1.0 / v - lam_row[i] if v > 0.0 else start
                g0[i] = g if g > floor else floor
            _, it2, ev2, tau22 = _pl_pixel(y, w, lp, p, k_max, lam_pl[p], ridge, learn_tau,
                                           max_iter, tol, floor, start, sbl, st, tab, mat, inv,
                                           low, x, rhs, prior, prior_rhs, breaks, vals, slopes,
                                           True, g0, True, fit, True)
            if ev2 >= ev or not ev == ev:
                it, ev, tau2 = it2, ev2, tau22
            else:
                k, it, ev, tau2 = _pl_pixel(y, w, lp, p, k_max, lam_pl[p], ridge, learn_tau,
                                            max_iter, tol, floor, start, sbl, st, tab, mat, inv,
                                            low, x, rhs, prior, prior_rhs, breaks, vals, slopes,
                                            full, g0, False, fit, False)
        if choose:
            if k == 1 or not ev > -math.inf:
                continue  # one segment is the Lambertian model; a failed PL fit
            gain = _choose(y, p, n, k, threshold, lam_row, outliers, st, tab, sbl_st, sbl_tab,
                           slopes, tau2, ridge, kv, slope_of, prior, prior_rhs, mat, inv, low,
                           scratch, loo, choice_z)
            evidence_out[p] = gain
            if not gain > 0.0:
                continue
        else:
            evidence_out[p] = ev
        _finish(p, k, x, slopes, breaks, st, n, threshold, x_out, outliers, segments_out)
        iters[p] = it  # the iterations of the model kept
        if want_residuals:
            for i in range(n):
                sl = slopes[int(st[_SEG, i])]
                sl = sl if sl > SLOPE_FLOOR / k else SLOPE_FLOOR / k
                resid_out[p, i] = -st[_R, i] / sl * st[_W, i]


@dataclass
class PLTileResult(TileResult):
    """:class:`._kernels.TileResult` plus the segments each pixel used and its log evidence."""

    segments: np.ndarray | None = None  # (m,) int: 1 = the Lambertian model
    evidence: np.ndarray | None = None  # (m,) float
    residuals: np.ndarray | None = None  # (m, n): (f(y) - n.l) / slope, with ``residuals``
    gate: np.ndarray | None = None  # (m,): the score test's statistic over its quantile
    sbl_weights: np.ndarray | None = None  # (m, n): SBL's final d, from stage "sbl"
    gate_breaks: np.ndarray | None = None  # (m, K - 1): the score test's breaks, stage "sbl"


def pl_tile(y, w, lights, *, segments: int, lam, sigma_x2: float = 1e6, max_iter: int = 100,
            tol: float = 1e-4, gamma_floor: float = 1e-10, gamma_start: float = 1e3,
            outlier_threshold: float = np.inf, learn_tau: bool = True, sbl: bool = True,
            choose: bool = False, sbl_max_iter: int = 100, lam_pl=None,
            residuals: bool = False, choice_z: float = CHOICE_Z, lam_test=None,
            false_alarm: float = GATE_FALSE_ALARM, stage: str = "both",
            sbl_fit: PLTileResult | None = None, sbl_start: bool = True) -> PLTileResult:
    """Piecewise-linear model of ``segments`` segments on one tile (module docstring).

    Parameters
    ----------
    y, w : ndarray of shape (m, n)
        Scaled observations and their usable mask (1/0).
    lights : ndarray of shape (n, 3) or (m, n, 3)
        Light vectors: the same for every pixel, or each pixel's own (near lights).
    segments : int
        ``K`` (1 to ``MAX_SEGMENTS``); a pixel with ``u`` usable observations uses at most
        ``u // MIN_PER_SEGMENT`` (at least 1).
    lam : float or ndarray of shape (m, 1) or (m, n)
        Each observation's noise variance in the pixel's relative units.
    residuals : bool
        Also return each observation's residual in the pixel's units, ``(f(y_i) - n.l_i) /
        s_k(i)`` (0 for dropped ones; the noise estimate of the PL models).
    sbl : bool
        False: PL-LS (one least-squares solve of the same design, no sparse errors).
    lam_pl : float or ndarray, optional
        The noise variance of the ``segments`` model when it differs from ``lam`` (``choose``:
        ``lam`` is then the one-segment model's).
    choose : bool
        Solve each pixel with ``K = 1`` (SBL, at most ``sbl_max_iter`` iterations) too and keep
        the ``K``-segment model only where it predicts the pixel's observations better, left out
        in turn, by more than ``choice_z`` standard errors (:func:`._pl_model._choose`);
        ``evidence`` is then that margin (> 0 where PL was kept).
    choice_z : float
        The margin of the choice, in standard errors of the leave-one-out gain.

    sigma_x2, max_iter, tol, gamma_floor, gamma_start, outlier_threshold : float, int, ...
        SBL's (:func:`._kernels.sbl_tile`); ``gamma_start`` and ``tol`` are in the units of ``y``
        (divided by ``K`` in ``f``'s units); ``outlier_threshold`` applies to the corruption in
        ``y``'s units (the equation's error over its segment's slope).
    learn_tau : bool
        Learn the slopes' prior variance per pixel (else the authors' 1).
    sbl_max_iter : int
        With ``choose``: the one-segment model's iterations.
    lam_test : float or ndarray of shape (m, 1) or (m, n), optional
        With ``choose``: the noise variance of the Lambertian model's score test
        (:func:`._pl_model._bend_score`); the ``K``-segment model is fitted and compared only
        where the score statistic of SBL's fit exceeds the chi^2 quantile of
        ``1 - false_alarm`` (``gate`` of the result: that excess). None: no test.
    false_alarm : float
        The score test's false-alarm rate.
    stage : {"both", "sbl", "pl"}
        With ``choose``: "sbl" fits SBL and runs the test only (``sbl_weights``, ``gate`` and
        ``gate_breaks`` kept for a later "pl" pass on the same rows, which takes SBL's fit from
        ``sbl_fit``, and the test's break points from it where it has them).
    sbl_fit : PLTileResult, optional
        Stage "pl": the "sbl" stage's result on the same rows.
    sbl_start : bool
        Without ``choose`` (PL-SBL alone): fit SBL first (``sbl_max_iter``) and the PL model a
        second time, break points from the observations SBL's fit sees lit and the EM from its
        final ``gamma``; the fit of the higher log evidence is kept (module docstring). False:
        the issue-23 PL-SBL (that first fit alone).
    """
    y = np.ascontiguousarray(y, dtype=np.float64)
    w = np.ascontiguousarray(w, dtype=np.float64)
    m, n = y.shape
    lights = np.asarray(lights, dtype=np.float64)
    per_pixel = lights.ndim == 3
    lights = np.ascontiguousarray(lights if per_pixel else lights[None])
    # writable: a read-only view (broadcast_to) would make numba compile a second version
    lam_obs = np.require(np.broadcast_to(np.asarray(lam, dtype=np.float64), (m, n)), None, "CW")
    lam_pl = lam_obs if lam_pl is None else np.require(
        np.broadcast_to(np.asarray(lam_pl, dtype=np.float64), (m, n)), None, "CW")
    gate = choose and lam_test is not None
    lam_t = (np.require(np.broadcast_to(np.asarray(lam_test, dtype=np.float64), (m, n)), None, "CW")
             if gate else np.ones((1, 1)))
    q_table = chi2_quantiles(n, false_alarm) if gate else np.zeros(1)
    if sbl_fit is not None:  # stage "pl": SBL's fit of the "sbl" stage, updated in place
        x, outliers, iters, segs = (np.array(sbl_fit.x), np.array(sbl_fit.outliers),
                                    np.array(sbl_fit.iterations), np.array(sbl_fit.segments))
        v_io = np.require(sbl_fit.sbl_weights, np.float64, "CW")
        known = gate and sbl_fit.gate_breaks is not None
    else:
        x = np.zeros((m, 3))
        outliers = np.zeros((m, n), np.bool_)
        iters = np.zeros(m, np.int64)
        segs = np.zeros(m, np.int64)
        v_io = np.zeros((m, n) if choose else (1, 1))
        known = False
    breaks = (np.require(sbl_fit.gate_breaks, np.float64, "CW") if known else
              np.zeros((m, max(int(segments) - 1, 1)) if gate else (m, 1)))
    evidence = np.full(m, -np.inf)
    stat = np.full(m, -np.inf)
    resid = np.zeros((m, n) if residuals else (1, 1))
    if m:
        _pl_kernel(y, w, lights, per_pixel, lam_obs, lam_pl, int(segments), bool(choose), bool(sbl),
                   1.0 / float(sigma_x2), bool(learn_tau), int(max_iter), int(sbl_max_iter),
                   float(tol),
                   float(gamma_floor), float(gamma_start), float(outlier_threshold), x, outliers,
                   iters, segs, evidence, bool(residuals), resid, float(choice_z), gate, lam_t,
                   q_table, stage != "pl", stage != "sbl", v_io, stat, breaks, known,
                   bool(sbl_start))
    return PLTileResult(x, outliers, iters, segs, evidence, resid if residuals else None,
                        stat if gate else None, v_io if stage == "sbl" else None,
                        breaks if gate and stage == "sbl" else None)

