"""Tile kernels of the per-pixel solvers (LS, L1-IRLS, SBL), vectorised over the pixels of a tile.

Every kernel works on one tile in pixel-major layout:

- ``y`` : (m, n) observations of m pixels, already divided by each pixel's robust scale;
- ``w`` : (m, n) 1.0 for usable observations, 0.0 for dropped ones (saturated, shadow-thresholded);
- ``lights`` : (n, 3) light directions (times intensities when those are known).

and returns ``x`` (m, 3) albedo-normal vectors in the scaled units, the per-observation outlier
flags, and the iterations per pixel. All per-pixel 3x3 algebra is written out (``_linalg``), so a
pixel costs O(n) per iteration and no n x n matrix is ever formed.

Per-pixel convergence and the active set: a pixel whose update falls under ``tol`` is recorded at
that iteration (exactly where the one-pixel-at-a-time oracle stops) and leaves the working arrays
at the next compaction, so converged pixels cost nothing afterwards.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._linalg import apply6, inverse6, outer6, quad6

# A working set is compacted once this share of it has converged: compaction copies the arrays,
# so doing it every iteration costs more than carrying a few finished pixels along.
_COMPACT_SHARE = 0.2


@dataclass
class TileResult:
    """Output of a tile kernel (see module docstring)."""

    x: np.ndarray  # (m, 3)
    outliers: np.ndarray  # (m, n) bool
    iterations: np.ndarray  # (m,) int


def weighted_fit(y: np.ndarray, w: np.ndarray, lights: np.ndarray, aa: np.ndarray) -> np.ndarray:
    """Weighted least squares ``argmin sum_i w_i (y_i - a_i.x)^2`` for every pixel: (m, 3)."""
    m6 = w @ aa
    inv, _ = inverse6(m6, 0.0)
    return apply6(inv, (w * y) @ lights)


def ls_tile(y, w, lights, *, outlier_threshold: float) -> TileResult:
    """Woodham's least squares; it trusts every usable observation (no outliers)."""
    x = weighted_fit(y, w, lights, outer6(lights))
    return TileResult(x, np.zeros(y.shape, bool), np.ones(y.shape[0], np.int64))


def l1_tile(y, w, lights, *, max_iter: int, tol: float, delta: float,
            outlier_threshold: float) -> TileResult:
    """IRLS for ``min_x sum_i w_i |y_i - a_i.x|``.

    Starts from least squares; each iteration re-weights by ``1 / max(|r_i|, delta)`` and solves
    the weighted normal equations; a pixel converges when ``max_k |x_k - x_k_old| < tol``.
    Outliers: usable observations whose final residual exceeds ``outlier_threshold``.
    """
    m = y.shape[0]
    aa = outer6(lights)
    x_all = weighted_fit(y, w, lights, aa)
    iters = np.full(m, max_iter, np.int64)
    idx = np.arange(m)
    ya, wa, x = y, w, x_all.copy()
    done = np.zeros(m, bool)
    for it in range(1, max_iter + 1):
        r = ya - x @ lights.T
        np.abs(r, out=r)
        np.maximum(r, delta, out=r)
        np.divide(wa, r, out=r)
        x_new = weighted_fit(ya, r, lights, aa)
        step = np.abs(x_new - x).max(axis=1)
        x = x_new
        newly = (step < tol) & ~done
        if newly.any():
            x_all[idx[newly]] = x[newly]
            iters[idx[newly]] = it
            done |= newly
        if done.all():
            break
        if done.sum() >= _COMPACT_SHARE * done.size:
            keep = ~done
            idx, ya, wa, x, done = idx[keep], ya[keep], wa[keep], x[keep], done[keep]
    else:
        x_all[idx[~done]] = x[~done]
    r = np.abs(y - x_all @ lights.T)
    return TileResult(x_all, (w > 0) & (r > outlier_threshold), iters)


def sbl_tile(y, w, lights, *, lam: float, sigma_x2: float, max_iter: int, tol: float,
             gamma_floor: float, outlier_threshold: float) -> TileResult:
    """Sparse Bayesian learning of Ikehata et al. (CVPR 2012), Eqs. 12-13, per pixel.

    With ``D = (Gamma + lam I)^-1`` (zero for dropped observations) and
    ``M = sigma_x^-2 I + A^T D A`` (3x3), ``S = D - D A M^-1 A^T D`` is ``Sigma_y^-1``:

    - ``S y = D (y - A x)`` with ``x = M^-1 A^T D y``,
    - ``diag(S)_i = d_i - d_i^2 a_i^T M^-1 a_i``,

    so ``z = Gamma S y`` and ``u = diag(Gamma - Gamma S Gamma)`` cost O(n) per pixel;
    ``gamma <- max(z^2 + u, gamma_floor)``. A pixel converges when ``max_i |z_i - z_i_old| < tol``.
    The normal comes from ``x`` of the final ``gamma``; outliers are usable observations whose
    corruption estimate ``|z_i|`` (from the final ``gamma``) exceeds ``outlier_threshold``.
    """
    m, n = y.shape
    dtype = y.dtype
    aa = outer6(lights)
    q6 = quad6(lights).T.copy()
    lights_t = lights.T.copy()
    ridge = dtype.type(1.0 / sigma_x2)
    lam = dtype.type(lam)
    floor = dtype.type(gamma_floor)
    gamma_all = np.ones((m, n), dtype)
    iters = np.full(m, max_iter, np.int64)
    idx = np.arange(m)
    ya, wa, g = y, w, gamma_all.copy()
    z_old = np.zeros_like(y)
    done = np.zeros(m, bool)
    for it in range(1, max_iter + 1):
        d = wa / (g + lam)
        mm = d @ aa
        mm[:, :3] += ridge
        inv, _ = inverse6(mm, 0.0)
        x = apply6(inv, (d * ya) @ lights)
        r = ya - x @ lights_t
        gd = g * d
        z = gd * r
        # u = g - g^2 diag(S) = g - g*gd*(1 - d*q), q_i = a_i^T M^-1 a_i
        q = inv @ q6
        q *= d
        np.subtract(1.0, q, out=q)
        q *= gd
        q *= g
        u = np.subtract(g, q, out=q)
        g = z * z
        g += u
        np.maximum(g, floor, out=g)
        step = np.abs(z - z_old).max(axis=1)
        z_old = z
        newly = (step < tol) & ~done
        if newly.any():
            gamma_all[idx[newly]] = g[newly]
            iters[idx[newly]] = it
            done |= newly
        if done.all():
            break
        if done.sum() >= _COMPACT_SHARE * done.size:
            keep = ~done
            idx, ya, wa, g, z_old, done = idx[keep], ya[keep], wa[keep], g[keep], z_old[keep], done[keep]
    else:
        gamma_all[idx[~done]] = g[~done]
    x, z = sbl_estimate(y, w, lights, aa, gamma_all, lam, ridge)
    return TileResult(x, (w > 0) & (np.abs(z) > outlier_threshold), iters)


def sbl_estimate(y, w, lights, aa, gamma, lam, ridge):
    """Posterior mean ``x = M^-1 A^T D y`` and corruption ``e = Gamma D (y - A x)`` for given gamma."""
    d = w / (gamma + lam)
    mm = d @ aa
    mm[:, :3] += ridge
    inv, _ = inverse6(mm, 0.0)
    x = apply6(inv, (d * y) @ lights)
    z = gamma * d * (y - x @ lights.T)
    return x, z
