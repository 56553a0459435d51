"""Tile kernels of the piecewise-linear models: PL-LS, PL-SBL and the per-pixel choice (numba).

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
  ``gamma``, ``tau^2``, plus the log Jacobian ``sum_i log s_{k(i)}`` of ``y -> f(y)``), so that
  models with different ``K`` compare: the ``auto`` kernel solves every pixel with ``K = 1``
  (SBL) and with ``K`` segments and keeps the one with the larger evidence.

Inputs are those of :mod:`._kernels` (``y`` (m, n) scaled, ``w`` (m, n) 1/0, lights (n, 3) or,
for near lights, (m, n, 3)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from ._kernels import INLINE, VECTOR, TileResult

# Rows of the per-pixel state: usable (1/0), observation noise in y units, in f units, gamma,
# d = w / (gamma + lambda), corruption estimate of the last iteration, residual, a^T M^-1 a,
# segment of the observation, target t.
_W, _LAM0, _LAM, _G, _D, _Z, _R, _Q, _SEG, _T = range(10)
STATE_ROWS = 10
MAX_SEGMENTS = 8
# Smallest slope (times 1/K) used for an observation's noise and the Jacobian.
SLOPE_FLOOR = 1e-3
TAU_FLOOR = 1e-10


@njit(**INLINE)
def _design(y, w, lights, p, k, st, tab, breaks, vals):
    """Break points, design rows and products of pixel p for ``k`` segments; usable count."""
    n = y.shape[1]
    cnt = 0
    for i in range(n):
        if w[p, i] > 0.0:
            vals[cnt] = y[p, i]
            cnt += 1
    srt = np.sort(vals[:cnt])
    breaks[0] = 0.0
    for j in range(1, k):
        breaks[j] = srt[(j * cnt) // k]
    breaks[k] = srt[cnt - 1]
    u = k + 2
    ns = k - 1
    for i in range(n):
        yi = y[p, i]
        wi = w[p, i]
        last = 0.0
        seg = 0
        for j in range(k):
            lo = breaks[j]
            width = breaks[j + 1] - lo
            ph = yi - lo
            ph = ph if ph > 0.0 else 0.0
            ph = ph if ph < width else width
            if j < ns:
                tab[j, i] = ph
            else:
                last = ph
            if j > 0 and yi > breaks[j]:
                seg = j
        for j in range(ns):
            tab[j, i] = (tab[j, i] - last) * wi
        tab[ns, i] = -lights[i, 0] * wi
        tab[ns + 1, i] = -lights[i, 1] * wi
        tab[ns + 2, i] = -lights[i, 2] * wi
        st[_T, i] = -last * wi
        st[_SEG, i] = seg
        st[_W, i] = wi
    # products a_a^T (upper triangle, row-major) on rows u .. u + u(u+1)/2
    e = u
    for r in range(u):
        for c in range(r, u):
            for i in range(n):
                tab[e, i] = tab[r, i] * tab[c, i]
            e += 1
    return cnt


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
def _pl_pixel(y, w, lights, p, k_max, lam_row, ridge, learn_tau, max_iter, tol, floor, start,
              sbl, st, tab, mat, inv, low, x, rhs, prior, prior_rhs, breaks, vals, slopes):
    """One pixel with up to ``k_max`` segments (fewer when it has few observations).

    Leaves ``x`` (U), ``slopes`` (K) and the state rows of the final iteration; returns
    (segments used, iterations, log evidence). ``sbl`` False: one weighted least-squares solve
    (PL-LS: every observation weight 1, no noise model).
    """
    n = y.shape[1]
    cnt = 0
    for i in range(n):
        cnt += w[p, i] > 0.0
    k = k_max if k_max < cnt - 3 else cnt - 3
    k = k if k > 1 else 1
    u = k + 2
    _design(y, w, lights, p, k, st, tab, breaks, vals)
    tau2 = 1.0
    scale2 = 1.0 / (k * k)
    for i in range(n):
        st[_LAM0, i] = lam_row[i]
        st[_LAM, i] = lam_row[i] * scale2
        st[_G, i] = start * scale2
        st[_D, i] = st[_W, i] / ((st[_G, i] if sbl else 0.0) + st[_LAM, i])
        st[_Z, i] = 0.0
    for j in range(k):
        slopes[j] = 1.0 / k
    ftol = tol / k
    iters = max_iter if sbl else 1
    logdet = math.nan
    it = 0
    done = not sbl
    while True:
        _prior(k, tau2, ridge, prior, prior_rhs)
        _normal_equations(st, tab, n, u, mat, rhs, prior, prior_rhs)
        logdet = _cholesky_inverse(mat, inv, low, u)
        if not logdet == logdet:
            for r in range(u):
                x[r] = 0.0
            return k, iters, -math.inf
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
        return k, 1, 0.0
    # log evidence of y: -1/2 [sum log c + log|M| - log|P| + sum d r^2 + dx^T P dx] + log Jacobian
    quad = 0.0
    logc = 0.0
    jac = 0.0
    for i in range(n):
        if st[_W, i] > 0.0:
            quad += st[_D, i] * st[_R, i] * st[_R, i]
            logc += math.log(st[_G, i] + st[_LAM, i])
            sl = slopes[int(st[_SEG, i])]
            jac += math.log(sl) if sl > 0.0 else -math.inf
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
    evidence = -0.5 * (logc + logdet - logdet_p + quad) + jac
    return k, iters, evidence


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
def _pl_kernel(y, w, lights, per_pixel, lam, k_max, choose, sbl, ridge, learn_tau, max_iter,
               sbl_max_iter, tol, floor, start, threshold, x_out, outliers, iters, segments_out,
               evidence_out):
    m, n = y.shape
    umax = k_max + 2
    st = np.zeros((STATE_ROWS, n))
    tab = np.zeros((umax + umax * (umax + 1) // 2, n))
    mat = np.zeros((umax, umax))
    inv = np.zeros((umax, umax))
    low = np.zeros((umax, umax))
    prior = np.zeros((umax, umax))
    x = np.zeros(umax)
    x1 = np.zeros(umax)
    rhs = np.zeros(umax)
    prior_rhs = np.zeros(umax)
    breaks = np.zeros(k_max + 1)
    vals = np.zeros(n)
    slopes = np.zeros(k_max)
    ones = np.ones(1)
    for p in range(m):
        lp = lights[p] if per_pixel else lights[0]
        lam_row = lam[p]
        if choose:
            # the Lambertian model (K = 1, SBL) first; kept unless K segments have more evidence
            k1, it1, ev1 = _pl_pixel(y, w, lp, p, 1, lam_row, ridge, learn_tau, sbl_max_iter, tol,
                                     floor, start, True, st, tab, mat, inv, low, x1, rhs, prior,
                                     prior_rhs, breaks, vals, slopes)
            _finish(p, 1, x1, ones, breaks, st, n, threshold, x_out, outliers, segments_out)
            iters[p] = it1
            evidence_out[p] = ev1
            if k_max == 1:
                continue
        k, it, ev = _pl_pixel(y, w, lp, p, k_max, lam_row, ridge, learn_tau, max_iter, tol,
                              floor, start, sbl, st, tab, mat, inv, low, x, rhs, prior,
                              prior_rhs, breaks, vals, slopes)
        if choose:
            iters[p] += it
            if not ev > evidence_out[p]:
                continue
        evidence_out[p] = ev
        _finish(p, k, x, slopes, breaks, st, n, threshold, x_out, outliers, segments_out)
        if not choose:
            iters[p] = it


@dataclass
class PLTileResult(TileResult):
    """:class:`._kernels.TileResult` plus the segments each pixel used and its log evidence."""

    segments: np.ndarray | None = None  # (m,) int: 1 = the Lambertian model
    evidence: np.ndarray | None = None  # (m,) float


def pl_tile(y, w, lights, *, segments: int, lam, sigma_x2: float = 1e6, max_iter: int = 100,
            tol: float = 1e-4, gamma_floor: float = 1e-10, gamma_start: float = 1e3,
            outlier_threshold: float = np.inf, learn_tau: bool = True, sbl: bool = True,
            choose: bool = False, sbl_max_iter: int = 100) -> PLTileResult:
    """Piecewise-linear model of ``segments`` segments on one tile (module docstring).

    Parameters
    ----------
    y, w : ndarray of shape (m, n)
        Scaled observations and their usable mask (1/0).
    lights : ndarray of shape (n, 3) or (m, n, 3)
        Light vectors: the same for every pixel, or each pixel's own (near lights).
    segments : int
        ``K`` (1 to ``MAX_SEGMENTS``); a pixel with ``u`` usable observations uses at most
        ``u - 3`` (at least 1).
    lam : float or ndarray of shape (m, 1) or (m, n)
        Each observation's noise variance in the pixel's relative units.
    sbl : bool
        False: PL-LS (one least-squares solve of the same design, no sparse errors).
    choose : bool
        Solve each pixel with ``K = 1`` (SBL, at most ``sbl_max_iter`` iterations) too and keep
        the model with the larger evidence.

    Other parameters are SBL's (:func:`._kernels.sbl_tile`); ``gamma_start`` and ``tol`` are in
    the units of ``y`` (divided by ``K`` in ``f``'s units).
    """
    y = np.ascontiguousarray(y, dtype=np.float64)
    w = np.ascontiguousarray(w, dtype=np.float64)
    m, n = y.shape
    lights = np.asarray(lights, dtype=np.float64)
    per_pixel = lights.ndim == 3
    lights = np.ascontiguousarray(lights if per_pixel else lights[None])
    lam_obs = np.ascontiguousarray(np.broadcast_to(np.asarray(lam, dtype=np.float64), (m, n)))
    x = np.zeros((m, 3))
    outliers = np.zeros((m, n), np.bool_)
    iters = np.zeros(m, np.int64)
    segs = np.zeros(m, np.int64)
    evidence = np.full(m, -np.inf)
    if m:
        _pl_kernel(y, w, lights, per_pixel, lam_obs, int(segments), bool(choose), bool(sbl),
                   1.0 / float(sigma_x2), bool(learn_tau), int(max_iter), int(sbl_max_iter),
                   float(tol),
                   float(gamma_floor), float(gamma_start), float(outlier_threshold), x, outliers,
                   iters, segs, evidence)
    return PLTileResult(x, outliers, iters, segs, evidence)
