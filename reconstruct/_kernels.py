"""Tile kernels of the per-pixel solvers: LS (numpy), L1-IRLS and SBL (numba).

Every kernel works on one tile in pixel-major layout:

- ``y`` : (m, n) float64 observations of m pixels, divided by each pixel's robust scale;
- ``w`` : (m, n) float64, 1.0 for usable observations, 0.0 for dropped ones;
- ``lights`` : (n, 3) float64 light vectors.

and returns ``x`` (m, 3) albedo-normal vectors in the scaled units, per-observation outlier flags
and the iterations per pixel. The per-pixel 3x3 algebra is written out, so an iteration costs O(n)
per pixel and no n x n matrix is ever formed.

L1 and SBL iterate per pixel until that pixel converges (the active set is the pixel loop
itself: a converged pixel leaves at once). They are compiled with numba: fused loops over the
lights cost 3-4x less than the same algebra as whole-tile numpy array operations (which stream
~15 (m, n) temporaries per iteration through memory), and ``nogil`` lets the tile threads run
in parallel. See docs/solvers.md for the measurements.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ps_lab.jit import INLINE, VECTOR

from ._linalg import apply6, inverse6, outer6, solve3, weighted_sums3


@dataclass
class TileResult:
    """Output of a tile kernel (see module docstring)."""

    x: np.ndarray  # (m, 3)
    outliers: np.ndarray  # (m, n) bool
    iterations: np.ndarray  # (m,) int


def ls_tile(y, w, lights, *, outlier_threshold: float) -> TileResult:
    """Woodham's least squares on the usable observations; it flags no outliers."""
    inv, _ = inverse6(w @ outer6(lights))
    x = apply6(inv, (w * y) @ lights)
    return TileResult(x, np.zeros(y.shape, bool), np.ones(y.shape[0], np.int64))


# Rows of the per-pixel state arrays.
# observations, usable (1/0), SBL's noise variance and gamma, weights (L1) or d = w / (gamma + lam)
# (SBL), SBL's corruption estimate of the last iteration
_Y, _W, _LAM, _G, _V, _Z = 0, 1, 2, 3, 4, 5
STATE_ROWS = 6


def light_table(lights: np.ndarray) -> np.ndarray:
    """Light table (9, n) of the kernels: ``outer6(lights).T`` on rows 0-5, ``lights.T`` on 6-8."""
    return np.ascontiguousarray(np.concatenate([outer6(lights).T, lights.T]), dtype=np.float64)


@njit(**INLINE)
def _light_table(lights, tab):
    """``tab`` (9, n): ``a_i a_i^T`` (rows 0-5, as ``outer6``) and ``a_i`` (6-8) of (n, 3)."""
    for i in range(lights.shape[0]):
        a0, a1, a2 = lights[i, 0], lights[i, 1], lights[i, 2]
        tab[0, i] = a0 * a0
        tab[1, i] = a1 * a1
        tab[2, i] = a2 * a2
        tab[3, i] = a0 * a1
        tab[4, i] = a0 * a2
        tab[5, i] = a1 * a2
        tab[6, i] = a0
        tab[7, i] = a1
        tab[8, i] = a2


@njit(**INLINE)
def _weighted_fit(st, tab, n):
    """Return x minimising ``sum_i v_i (y_i - a_i.x)^2`` (v = st[_V], y = st[_Y])."""
    xx, yy, zz, xy, xz, yz, t0, t1, t2 = weighted_sums3(st[_V], st[_Y], tab, n)
    s = solve3(xx, yy, zz, xy, xz, yz, t0, t1, t2)
    return s[0], s[1], s[2]


@njit(**INLINE)
def _load_pixel(st, y, w, p, n):
    for i in range(n):
        st[_Y, i] = y[p, i]
        st[_W, i] = w[p, i]


@njit(**INLINE)
def _flag_outliers(st, tab, n, x0, x1, x2, threshold, factor_row, outliers, p):
    """``outliers[p, i]``: usable and ``|factor_i r_i| > threshold`` (factor 1 for row -1)."""
    for i in range(n):
        r = st[_Y, i] - (x0 * tab[6, i] + x1 * tab[7, i] + x2 * tab[8, i])
        if factor_row >= 0:
            r *= st[factor_row, i]
        outliers[p, i] = st[_W, i] > 0.0 and abs(r) > threshold


@njit(**INLINE)
def _l1_weights(st, tab, n, x0, x1, x2, delta):
    for i in range(n):
        r = abs(st[_Y, i] - (x0 * tab[6, i] + x1 * tab[7, i] + x2 * tab[8, i]))
        st[_V, i] = st[_W, i] / (r if r > delta else delta)


@njit(**INLINE)
def _l1_pixel(st, tab, n, max_iter, tol, delta, threshold, x_out, outliers, iters, p):
    """IRLS on pixel p: its rows ``_Y``, ``_W`` of ``st`` and its light table ``tab`` loaded."""
    for i in range(n):
        st[_V, i] = st[_W, i]
    x0, x1, x2 = _weighted_fit(st, tab, n)
    iters[p] = max_iter
    for it in range(1, max_iter + 1):
        _l1_weights(st, tab, n, x0, x1, x2, delta)
        n0, n1, n2 = _weighted_fit(st, tab, n)
        step = max(abs(n0 - x0), abs(n1 - x1), abs(n2 - x2))
        x0, x1, x2 = n0, n1, n2
        if step < tol:
            iters[p] = it
            break
    x_out[p, 0], x_out[p, 1], x_out[p, 2] = x0, x1, x2
    _flag_outliers(st, tab, n, x0, x1, x2, threshold, -1, outliers, p)


@njit(nogil=True, cache=True, **VECTOR)
def _l1_kernel(y, w, tab, max_iter, tol, delta, threshold, x_out, outliers, iters):
    m, n = y.shape
    st = np.zeros((STATE_ROWS, n))
    for p in range(m):
        _load_pixel(st, y, w, p, n)
        _l1_pixel(st, tab, n, max_iter, tol, delta, threshold, x_out, outliers, iters, p)


def l1_tile(y, w, lights, *, max_iter: int, tol: float, delta: float,
            outlier_threshold: float) -> TileResult:
    """IRLS for ``min_x sum_i w_i |y_i - a_i.x|``.

    Starts from least squares; each iteration re-weights by ``1 / max(|r_i|, delta)`` and solves
    the weighted normal equations; a pixel converges when ``max_k |x_k - x_k_old| < tol``.
    Outliers: usable observations whose final residual exceeds ``outlier_threshold``.
    """
    m = y.shape[0]
    x = np.zeros((m, 3))
    outliers = np.zeros(y.shape, np.bool_)
    iters = np.zeros(m, np.int64)
    y, w = np.require(y, np.float64, "CW"), np.require(w, np.float64, "CW")  # numba: one version
    _l1_kernel(y, w, light_table(lights), int(max_iter), float(tol), float(delta),
               float(outlier_threshold), x, outliers, iters)
    return TileResult(x, outliers, iters)


@njit(**INLINE)
def _sbl_update(st, tab, n, x0, x1, x2, i00, i11, i22, j01, j02, j12, floor, tol):
    """One gamma update of a pixel (st holds its state); the count of ``|z_i - z_i_old| >= tol``.

    Counting instead of taking the maximum keeps the loop vectorised; ``max < tol`` is
    ``count == 0`` (NaN counts in neither).
    """
    moved = 0
    for i in range(n):
        gi = st[_G, i]
        di = st[_V, i]
        r = st[_Y, i] - (x0 * tab[6, i] + x1 * tab[7, i] + x2 * tab[8, i])
        gd = gi * di
        z = gd * r  # (Gamma S y)_i with S y = D (y - A x)
        q = (i00 * tab[0, i] + i11 * tab[1, i] + i22 * tab[2, i]
             + j01 * tab[3, i] + j02 * tab[4, i] + j12 * tab[5, i])
        # u_i = gamma_i - gamma_i^2 S_ii, S_ii = d_i - d_i^2 a_i^T M^-1 a_i
        gn = z * z + (gi - gi * gd * (1.0 - di * q))
        gn = gn if gn > floor else floor
        st[_G, i] = gn
        st[_V, i] = st[_W, i] / (gn + st[_LAM, i])
        moved += abs(z - st[_Z, i]) >= tol
        st[_Z, i] = z
    return moved


@njit(**INLINE)
def _sbl_pixel(st, tab, n, ridge, max_iter, tol, floor, start, threshold, x_out, outliers,
               iters, p):
    """SBL on pixel p: its rows ``_Y``, ``_W``, ``_LAM`` of ``st`` and its ``tab`` loaded."""
    for i in range(n):
        st[_G, i] = start
        st[_V, i] = st[_W, i] / (start + st[_LAM, i])
        st[_Z, i] = 0.0
    iters[p] = max_iter
    done = False
    it = 0
    while True:
        # M = ridge I + A^T D A with D = (Gamma + lam I)^-1 (0 for dropped observations)
        xx, yy, zz, xy, xz, yz, t0, t1, t2 = weighted_sums3(st[_V], st[_Y], tab, n)
        x0, x1, x2, i00, i11, i22, i01, i02, i12 = solve3(
            xx + ridge, yy + ridge, zz + ridge, xy, xz, yz, t0, t1, t2)
        if done or it == max_iter:
            # posterior mean for the final gamma; corruption e = Gamma S y
            x_out[p, 0], x_out[p, 1], x_out[p, 2] = x0, x1, x2
            for i in range(n):
                st[_Z, i] = st[_G, i] * st[_V, i]
            _flag_outliers(st, tab, n, x0, x1, x2, threshold, _Z, outliers, p)
            return
        moved = _sbl_update(st, tab, n, x0, x1, x2, i00, i11, i22,
                            2.0 * i01, 2.0 * i02, 2.0 * i12, floor, tol)
        it += 1
        if moved == 0:
            iters[p] = it
            done = True


@njit(nogil=True, cache=True, **VECTOR)
def _sbl_kernel(y, w, tab, lam, ridge, max_iter, tol, floor, start, threshold, x_out,
                outliers, iters):
    m, n = y.shape
    st = np.zeros((STATE_ROWS, n))
    for p in range(m):
        _load_pixel(st, y, w, p, n)
        for i in range(n):
            st[_LAM, i] = lam[p, i]
        _sbl_pixel(st, tab, n, ridge, max_iter, tol, floor, start, threshold, x_out, outliers,
                   iters, p)


def sbl_tile(y, w, lights, *, lam, sigma_x2: float, max_iter: int, tol: float,
             gamma_floor: float, gamma_start: float, outlier_threshold: float) -> TileResult:
    """Sparse Bayesian learning of Ikehata et al. (CVPR 2012), Eqs. 12-13, per pixel.

    With ``D = (Gamma + lam I)^-1`` (zero for dropped observations) and
    ``M = sigma_x^-2 I + A^T D A`` (3x3), ``S = D - D A M^-1 A^T D`` is ``Sigma_y^-1``:

    - ``S y = D (y - A x)`` with ``x = M^-1 A^T D y``,
    - ``diag(S)_i = d_i - d_i^2 a_i^T M^-1 a_i``,

    so ``z = Gamma S y`` and ``u = diag(Gamma - Gamma S Gamma)`` cost O(n) per pixel;
    ``gamma <- max(z^2 + u, gamma_floor)``, starting from ``gamma = gamma_start``. ``lam`` is the
    noise variance: one for the tile, one per pixel (m, 1) or one per observation (m, n). A pixel
    converges when ``max_i |z_i - z_i_old| < tol``. The normal comes from ``x`` of the final
    ``gamma``; outliers are usable observations whose corruption estimate ``|z_i|`` (final
    gamma) exceeds ``outlier_threshold``.
    """
    m = y.shape[0]
    x = np.zeros((m, 3))
    outliers = np.zeros(y.shape, np.bool_)
    iters = np.zeros(m, np.int64)
    # writable: a read-only view (broadcast_to) would make numba compile a second version
    lam_obs = np.require(np.broadcast_to(np.asarray(lam, dtype=np.float64), y.shape), None, "CW")
    y, w = np.require(y, np.float64, "CW"), np.require(w, np.float64, "CW")
    _sbl_kernel(y, w, light_table(lights), lam_obs, 1.0 / float(sigma_x2),
                int(max_iter), float(tol), float(gamma_floor), float(gamma_start),
                float(outlier_threshold), x, outliers, iters)
    return TileResult(x, outliers, iters)
