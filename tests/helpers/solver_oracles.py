"""Straightforward per-pixel references of the solvers: test oracle and benchmark baseline.

Each oracle handles ONE pixel with plain numpy, exactly as the method is written in its paper
(for SBL the n x n matrices of Ikehata et al. Eq. 13 are formed explicitly). Dropped
observations are removed from the pixel's problem. The update and stopping rules are the ones
the vectorised solvers document, so results agree as far as ``tolerances.py`` derives.

Each pixel oracle returns ``(x, statistic, iterations)``: ``statistic`` is what the method compares
with ``outlier_threshold`` to flag an observation (``|residual|`` for L1, the corruption estimate
``|e|`` for SBL, 0 for least squares).
"""

from __future__ import annotations

import numpy as np


def pixel_scale(y: np.ndarray) -> float:
    """Median of |y| over a pixel's usable observations (mean if the median is 0)."""
    if y.size == 0:
        return 0.0
    med = float(np.median(np.abs(y)))
    return med if med > 0 else float(np.mean(np.abs(y)))


def solvable(a: np.ndarray, scale: float, rel_det: float = 1e-6) -> bool:
    m = a.T @ a
    tr = np.trace(m) / 3.0
    return a.shape[0] >= 3 and scale > 0 and tr > 0 and np.linalg.det(m) > rel_det * tr**3


def ls_pixel(y, a):
    return np.linalg.lstsq(a, y, rcond=None)[0], np.zeros(y.size), 1


def l1_pixel(y, a, *, max_iter=100, tol=1e-6, delta=1e-6):
    x = np.linalg.lstsq(a, y, rcond=None)[0]
    it = max_iter
    for k in range(1, max_iter + 1):
        wts = 1.0 / np.maximum(np.abs(y - a @ x), delta)
        x_new = np.linalg.solve(a.T @ (wts[:, None] * a), a.T @ (wts * y))
        step = np.abs(x_new - x).max()
        x = x_new
        if step < tol:
            it = k
            break
    return x, np.abs(y - a @ x), it


def sbl_pixel(y, a, *, lam, sigma_x2=1e6, max_iter=100, tol=1e-4, gamma_floor=1e-10,
              gamma_start=1e3):
    n = y.size
    gamma = np.full(n, float(gamma_start))
    z_old = np.zeros(n)
    it = max_iter
    for k in range(1, max_iter + 1):
        big_d = np.diag(1.0 / (gamma + lam))
        m = np.eye(3) / sigma_x2 + a.T @ big_d @ a
        s = big_d - big_d @ a @ np.linalg.inv(m) @ a.T @ big_d  # Sigma_y^-1 (Eq. 13's "S")
        g = np.diag(gamma)
        z = g @ s @ y
        u = np.diag(g - g @ s @ g)
        gamma = np.maximum(z**2 + u, gamma_floor)
        step = np.abs(z - z_old).max()
        z_old = z
        if step < tol:
            it = k
            break
    big_d = np.diag(1.0 / (gamma + lam))
    m = np.eye(3) / sigma_x2 + a.T @ big_d @ a
    x = np.linalg.solve(m, a.T @ big_d @ y)
    e = gamma * np.diag(big_d) * (y - a @ x)
    return x, np.abs(e), it


PIXEL_ORACLES = {"ls": ls_pixel, "l1": l1_pixel, "sbl": sbl_pixel}


def solve_oracle(observations, lights, method, valid=None, *, statistic=False, **params):
    """One pixel at a time; returns (normals (P,3), albedo (P,), outliers (n,P), iterations (P,)).

    With ``statistic``, also the (n, P) statistic each flag compares with the outlier threshold
    (scaled units; NaN for unused observations).
    """
    obs = np.asarray(observations, float)
    n, p = obs.shape
    valid = np.ones((n, p), bool) if valid is None else np.asarray(valid, bool)
    valid = valid & np.isfinite(obs)
    if method == "rpca":
        result = rpca_oracle(obs, lights, valid, **params)
        return result if statistic else result[:4]
    threshold = params.get("outlier_threshold", np.inf)
    params = {k: v for k, v in params.items() if k != "outlier_threshold"}
    normals, albedo = np.zeros((p, 3)), np.zeros(p)
    outliers, iterations = np.zeros((n, p), bool), np.zeros(p, int)
    statistics = np.full((n, p), np.nan)
    for j in range(p):
        v = valid[:, j]
        y, a = obs[v, j], lights[v]
        scale = pixel_scale(y)
        if not solvable(a, scale):
            continue
        pixel_params = params
        if method == "sbl" and params.get("lam") is None:
            # SBL's default: sigma^2 relative plus the noise floor (observation units, times each
            # light's factor) / scale, per observation
            sigma, floor = params["noise_sigma"], params["noise_floor"]
            factor = params.get("light_noise")
            factor = np.ones(n) if factor is None else np.asarray(factor)
            rest = {k: v for k, v in params.items()
                    if k not in ("noise_sigma", "noise_floor", "light_noise")}
            lam = np.maximum(sigma**2 + (floor * factor[v] / scale) ** 2, 1e-6)
            pixel_params = {**rest, "lam": lam}
        x, stat, it = PIXEL_ORACLES[method](y / scale, a, **pixel_params)
        x = x * scale
        albedo[j] = np.linalg.norm(x)
        if albedo[j] > 0:
            normals[j] = x / albedo[j]
            outliers[np.flatnonzero(v), j] = stat > threshold
            statistics[np.flatnonzero(v), j] = stat
        iterations[j] = it
    if statistic:
        return normals, albedo, outliers, iterations, statistics
    return normals, albedo, outliers, iterations


def rpca_oracle(obs, lights, valid, *, lam_sparse=None, max_iter=500, tol=1e-7, rho=1.5,
                outlier_threshold=0.05):
    """Inexact ALM with a full SVD per iteration (Lin, Chen & Ma 2010; Wu et al. 2010)."""
    n, p = obs.shape
    scales = np.array([pixel_scale(obs[valid[:, j], j]) for j in range(p)])
    ok = np.array([solvable(lights[valid[:, j]], scales[j]) for j in range(p)])
    cols = np.flatnonzero(ok)
    d = np.where(valid[:, cols], obs[:, cols] / scales[cols], 0.0)
    omega = valid[:, cols]
    lam = 1.0 / np.sqrt(max(n, cols.size)) if lam_sparse is None else lam_sparse
    norm2 = np.linalg.norm(d, 2)
    mult = d / max(norm2, np.abs(d).max() / lam)
    mu, mu_max = 1.25 / norm2, 1.25e7 / norm2
    e = np.zeros_like(d)
    it = 0
    for it in range(1, max_iter + 1):
        u, s, vt = np.linalg.svd(d - e + mult / mu, full_matrices=False)
        low = (u * np.maximum(s - 1.0 / mu, 0.0)) @ vt
        t = d - low + mult / mu
        e = np.where(omega, np.sign(t) * np.maximum(np.abs(t) - lam / mu, 0.0), t)
        r = np.where(omega, d - low - e, 0.0)
        mult = mult + mu * r
        mu = min(mu * rho, mu_max)
        if np.linalg.norm(r) <= tol * np.linalg.norm(d):
            break
    normals, albedo = np.zeros((p, 3)), np.zeros(p)
    outliers = np.zeros((n, p), bool)
    x = np.linalg.lstsq(lights, low, rcond=None)[0] * scales[cols]
    albedo[cols] = np.linalg.norm(x, axis=0)
    normals[cols] = (x / albedo[cols]).T
    outliers[:, cols] = omega & (np.abs(e) > outlier_threshold)
    statistics = np.full((n, p), np.nan)
    statistics[:, cols] = np.where(omega, np.abs(e), np.nan)
    return normals, albedo, outliers, np.where(ok, it, 0), statistics
