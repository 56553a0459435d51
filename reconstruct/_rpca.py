"""R-PCA photometric stereo (Wu et al., ACCV 2010): low-rank + sparse split by inexact ALM, then LS.

The observation matrix of the masked pixels (n lights x P pixels, each pixel's column divided by
its robust scale, which keeps the Lambertian part at rank 3) is split as ``D = L + E`` minimising
``||L||_* + lam_sparse ||E||_1`` over the usable entries; dropped entries are missing data (E is
free there, so L fills them in). Inexact augmented Lagrange multipliers (Lin, Chen & Ma 2010):
singular-value thresholding of L, soft thresholding of E, multiplier update, ``mu *= rho``.
The SVD of the wide n x P matrix goes through the n x n Gram matrix, so one iteration costs
O(n^2 P). Normals are then the least-squares fit of each column of L with all n lights.
"""

from __future__ import annotations

import numpy as np

from ._linalg import SOLVABLE_REL_DET, apply6, inverse6, outer6, pixel_scale
from ._solution import Solution


def _svt(x: np.ndarray, tau: float) -> np.ndarray:
    """Singular-value thresholding of a wide (n, P) matrix through its Gram matrix."""
    s2, u = np.linalg.eigh(x @ x.T)
    s = np.sqrt(np.clip(s2, 0.0, None))
    keep = s > tau
    if not keep.any():
        return np.zeros_like(x)
    uk = u[:, keep]
    shrink = 1.0 - tau / s[keep]
    return (uk * shrink) @ (uk.T @ x)


def solve_rpca(obs, lights, usable, params, used, progress) -> Solution:
    """Run R-PCA + LS on all pixels at once (called by :func:`solve`)."""
    n, p = obs.shape
    y = np.ascontiguousarray(obs.T, dtype=np.float64)
    w = usable.T.copy()
    scale = pixel_scale(y, w)
    _, ok = inverse6(w.astype(np.float64) @ outer6(lights), SOLVABLE_REL_DET)
    ok &= (scale > 0) & (w.sum(axis=1) >= 3)
    cols = np.flatnonzero(ok)
    d = np.where(w[cols], y[cols] / scale[cols, None], 0.0).T.copy()  # (n, p_ok)
    omega = w[cols].T.copy()
    lam_sparse = params["lam_sparse"]
    if lam_sparse is None:
        lam_sparse = 1.0 / np.sqrt(max(n, max(cols.size, 1)))
    used["lam_sparse"] = float(lam_sparse)
    low = np.zeros_like(d)
    sparse = np.zeros_like(d)
    iterations = 0
    if cols.size:
        norm2 = np.sqrt(max(np.linalg.eigvalsh(d @ d.T).max(), 0.0))
        dnorm = np.linalg.norm(d)
        if norm2 > 0:
            mult = d / max(norm2, np.abs(d).max() / lam_sparse)
            mu = 1.25 / norm2
            mu_max = mu * 1e7
            for iterations in range(1, params["max_iter"] + 1):
                low = _svt(d - sparse + mult / mu, 1.0 / mu)
                t = d - low + mult / mu
                shrunk = np.sign(t) * np.maximum(np.abs(t) - lam_sparse / mu, 0.0)
                sparse = np.where(omega, shrunk, t)
                resid = np.where(omega, d - low - sparse, 0.0)
                mult += mu * resid
                mu = min(mu * params["rho"], mu_max)
                if np.linalg.norm(resid) <= params["tol"] * dnorm:
                    break
    used["alm_iterations"] = iterations
    x = np.zeros((p, 3))
    if cols.size:
        m6 = np.broadcast_to(outer6(lights).sum(axis=0), (cols.size, 6)).copy()
        inv, _ = inverse6(m6)
        x[cols] = apply6(inv, low.T @ lights) * scale[cols, None]
    length = np.linalg.norm(x, axis=1)
    good = ok & (length > 0)
    normals = np.where(good[:, None], x / np.where(good, length, 1.0)[:, None], 0.0)
    outliers = np.zeros((n, p), bool)
    outliers[:, cols] = omega & (np.abs(sparse) > params["outlier_threshold"])
    outliers[:, ~good] = False
    if progress is not None and p:
        progress(p)
    return Solution(normals, np.where(good, length, 0.0), outliers,
                    np.where(ok, iterations, 0).astype(np.int64), used)
