"""Result types and the input error of the solvers."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ps_lab.errors import DatasetError

# What every method's ``albedo`` is (``Solution.params["albedo"]``, metrics.json).
ALBEDO_DEFINITION = "lambertian-equivalent"


class SolverInputError(DatasetError, ValueError):
    """Observations, lights or parameters a solver cannot use (shape, NaN, rank, unknown option).

    A :class:`~ps_lab.errors.DatasetError` (the CLI prints one line) and a ``ValueError`` (for
    library callers).
    """


@dataclass(frozen=True)
class Solution:
    """Per-pixel result of a photometric-stereo solver.

    Attributes
    ----------
    normals : ndarray of shape (P, 3)
        Unit normals, camera frame of the lights; zeros where a pixel is unsolvable (fewer than
        three usable observations, or degenerate lights).
    albedo : ndarray of shape (P,)
        The Lambertian-equivalent reflectance (:func:`lambertian_albedo`), in the units of the
        observations, for every method.
    outliers : ndarray of shape (n, P), bool
        Observations the method treated as corrupted (invalid observations are never flagged).
    iterations : ndarray of shape (P,), int
        Iterations each pixel ran (1 for ``ls``; the global ALM count for ``rpca``).
    params : dict
        The method and every parameter actually used (``lambda`` after auto-estimation, ...).
    """

    normals: np.ndarray
    albedo: np.ndarray
    outliers: np.ndarray
    iterations: np.ndarray
    params: dict = field(default_factory=dict)


@dataclass(frozen=True)
class RefinementResult:
    """Result of :func:`refine_lights`.

    Attributes
    ----------
    solution : Solution
        The solver's result with the final (refined) lights.
    light_directions : ndarray of shape (n, 3)
        Refined unit light directions.
    light_intensities : ndarray of shape (n,)
        Refined relative intensities (the input ones when ``fixed_intensities``).
    history : list of dict
        One entry per refinement iteration: ``iteration``, ``mean_direction_change_deg``,
        ``max_direction_change_deg``, ``mean_intensity_change`` and, when a ground truth was
        given, ``normal_error_deg`` (mean error of the normals solved with the lights *before* that
        iteration's update) plus ``light_error_deg`` when true lights were given. A final entry
        with ``iteration = iterations`` reports the error after the last update.
    """

    solution: Solution
    light_directions: np.ndarray
    light_intensities: np.ndarray
    history: list = field(default_factory=list)


def lambertian_albedo(normals: np.ndarray, inliers: np.ndarray, observations: np.ndarray,
                      lights: np.ndarray) -> np.ndarray:
    """Lambertian-equivalent reflectance of each pixel, given its normal and inliers.

    The least-squares scale ``rho`` of the Lambertian image ``rho max(n.l_i, 0)`` on the pixel's
    inlier observations (usable, not flagged as corrupted) that its normal sees lit:
    ``rho = max(sum_i y_i (n.l_i) / sum_i (n.l_i)^2, 0)`` over ``i`` with ``n.l_i > 0``. It is
    the same quantity whatever model gave the normal (on Lambertian data every method's albedo is
    the true one), and it applies to one colour channel's observations as well as to their mean.

    Parameters
    ----------
    normals : ndarray of shape (P, 3)
        Unit normals (zeros for unsolved pixels).
    inliers : ndarray of shape (n, P), bool
        The observations to fit.
    observations : ndarray of shape (n, P)
        Intensities (divided by the light intensities, as solved).
    lights : ndarray of shape (n, 3) or (P, n, 3)
        Light vectors (the same for every pixel, or each pixel's own).

    Returns
    -------
    ndarray of shape (P,)
        ``rho``; 0 where no inlier is lit (or the normal is 0).
    """
    normals = np.asarray(normals, dtype=np.float64)
    lights = np.asarray(lights, dtype=np.float64)
    if lights.ndim == 2:
        shading = normals @ lights.T
    else:
        shading = np.einsum("pk,pnk->pn", normals, lights)
    rho = _albedo_rows(shading, np.asarray(inliers, bool).T,
                       np.asarray(observations, np.float64).T)
    return np.nan_to_num(rho, nan=0.0)


def _albedo_rows(shading: np.ndarray, inliers: np.ndarray, y: np.ndarray) -> np.ndarray:
    """:func:`lambertian_albedo` in pixel-major layout ((m, n) ``n.l``, inliers and ``y``); NaN
    where no inlier is lit (the caller's fallback)."""
    use = inliers & (shading > 0.0)
    s = np.where(use, shading, 0.0)
    num = np.einsum("pn,pn->p", s, np.where(use, y, 0.0))
    den = np.einsum("pn,pn->p", s, s)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0.0, np.maximum(num / np.where(den > 0.0, den, 1.0), 0.0), np.nan)


def check_inputs(observations, light_directions, valid):
    """``solve``'s inputs as arrays: observations (n, P), lights (n, 3) float64 and the usable
    mask (finite and ``valid``); :class:`SolverInputError` for wrong shapes or lights."""
    obs = np.asarray(observations)
    if obs.ndim != 2:
        raise SolverInputError(f"observations must be (n_lights, n_pixels), got shape {obs.shape}")
    if not np.issubdtype(obs.dtype, np.number):
        raise SolverInputError(f"observations must be numeric, got {obs.dtype}")
    # the tile kernels take C-ordered float32 (the store's) or float64 (one compiled version each)
    obs = np.ascontiguousarray(obs, dtype=obs.dtype if obs.dtype == np.float32 else np.float64)
    lights = np.asarray(light_directions, dtype=np.float64)
    n = obs.shape[0]
    if lights.shape != (n, 3):
        raise SolverInputError(f"light_directions must be ({n}, 3) for {n} observations per "
                               f"pixel, got {lights.shape}")
    if not np.all(np.isfinite(lights)):
        raise SolverInputError("light_directions contain NaN or infinite values")
    if n < 3 or np.linalg.matrix_rank(lights) < 3:
        raise SolverInputError("the light directions do not span 3-D space "
                               "(need >= 3 non-coplanar lights)")
    usable = np.isfinite(obs)
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != obs.shape:
            raise SolverInputError(f"valid must have the observations' shape {obs.shape}, "
                               f"got {valid.shape}")
        usable &= valid
    return obs, lights, np.ascontiguousarray(usable)
