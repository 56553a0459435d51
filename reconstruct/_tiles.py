"""Tiles of the per-pixel solvers: scaled observations in, unit normals and albedo out.

Shared by :mod:`._solve` and the default's two passes (:mod:`._auto`).
"""

from __future__ import annotations

import numpy as np

from ._linalg import SOLVABLE_REL_DET, inverse6, outer6, pixel_scale
from ._solution import ALBEDO_DEFINITION, Solution, _albedo_rows

# Noise level floor (relative to the pixel scale): the paper's lambda for noise-free data.
LAMBDA_FLOOR = 1e-6


def sbl_lambda(scale: np.ndarray, noise_sigma: float, noise_floor: float,
               light_noise: np.ndarray | None = None) -> np.ndarray:
    """SBL's default noise variance per observation, in units of the pixel's scale squared.

    Parameters
    ----------
    scale : ndarray of shape (m,)
        The pixels' robust scales (:func:`pixel_scale`), in the observations' units.
    noise_sigma : float
        Noise proportional to the signal, relative to the pixel scale (:func:`estimate_noise`).
    noise_floor : float
        Noise constant in the observations' units (:func:`estimate_noise_model`).
    light_noise : ndarray of shape (n,), optional
        Relative size of the noise floor under each light (mean square 1; default all 1): a floor
        constant in the *image* units becomes ``floor / intensity`` once each image is divided by
        its light's intensity (:func:`light_noise_factors`).

    Returns
    -------
    ndarray of shape (m, 1), or (m, n) with ``light_noise``
        ``max(noise_sigma^2 + (noise_floor * light_noise_i / scale)^2, LAMBDA_FLOOR)`` (the floor
        where ``scale`` is 0: unsolvable pixels).
    """
    s = np.asarray(scale, dtype=np.float64)[:, None]
    f2 = np.ones(1) if light_noise is None else np.asarray(light_noise, dtype=np.float64) ** 2
    with np.errstate(divide="ignore"):
        inv = np.where(s > 0, 1.0 / np.where(s > 0, s, 1.0) ** 2, 0.0)
    return np.maximum(noise_sigma * noise_sigma + noise_floor**2 * inv * f2[None, :],
                      LAMBDA_FLOOR)


def _prepare_tile(obs, usable, lights, a, b):
    """Pixel-major scaled observations of pixels a:b and the solvable-pixel mask."""
    y = np.array(obs[:, a:b].T, dtype=np.float64, order="C")  # a copy: scaled in place below
    w = np.ascontiguousarray(usable[:, a:b].T)
    scale = pixel_scale(y, w)
    _, ok = inverse6(w.astype(np.float64) @ outer6(lights), SOLVABLE_REL_DET)
    ok &= (scale > 0) & (w.sum(axis=1) >= 3)
    w &= ok[:, None]
    y /= np.where(ok, scale, 1.0)[:, None]
    y[~w] = 0.0  # dropped observations may hold NaN or garbage: weight 0 must not see it
    return y, w.astype(np.float64), scale, ok


def _store_tile(a, b, y, w, scale, ok, res, lights, normals, albedo, outliers, iterations,
                segments):
    """Unit normals, the Lambertian-equivalent albedo and flags of pixels a:b into the outputs."""
    x = res.x.astype(np.float64) * scale[:, None]
    length = np.linalg.norm(x, axis=1)
    good = ok & (length > 0) & np.isfinite(length)
    unit = np.where(good[:, None], x / np.where(good, length, 1.0)[:, None], 0.0)
    normals[a:b] = unit
    # one albedo for every method: the Lambertian-equivalent reflectance on the inliers
    rho = _albedo_rows(unit @ lights.T, (w > 0) & ~res.outliers, y) * scale
    albedo[a:b] = np.where(good, np.where(np.isnan(rho), length, rho), 0.0)
    outliers[:, a:b] = (res.outliers & good[:, None]).T
    iterations[a:b] = np.where(ok, res.iterations, 0)
    if segments is not None:
        segments[a:b] = np.where(ok, res.segments, 0)


def _finish_solution(used, normals, albedo, outliers, iterations, segments):
    if segments is not None:
        solved = segments > 0
        used["pixels_per_segments"] = {int(k): int(c) for k, c in
                                       zip(*np.unique(segments[solved], return_counts=True),
                                           strict=True)}
    used["albedo"] = ALBEDO_DEFINITION
    return Solution(normals, albedo, outliers, iterations, used)
