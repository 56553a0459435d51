"""`solve`: input checks, each method's parameters and their data-driven defaults, and the threads
that run its tiles (``_tiles.py``), the default's two passes (``_auto.py``) or R-PCA; the noise
estimates are ``_noise.py``'s."""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext

import numpy as np

from . import _pl_model
from ._auto import auto_tiles
from ._rpca import solve_rpca
from ._noise import _noise_floor, _noise_level, _noise_residuals, pl_noise_level
from ._solution import ALBEDO_DEFINITION, Solution, SolverInputError, _albedo_rows
from ._solution import check_inputs as _check_inputs
from ._tiles import DEFAULT_TILE_SIZE, solve_tiles, tile_pixels
from .methods import SBL_MAX_ITER, solver

# Smallest outlier threshold (relative to the pixel scale); _pl_model.GATE_NOISE is its third.
MIN_OUTLIER_THRESHOLD = 0.05
# SBL's default tolerance: a change of the corruption estimate this small against the noise level
# moves no normal (docs/solvers.md), and never tighter than SBL_TOL_MIN (noise-free data).
SBL_TOL_NOISE_SHARE = 1.0 / 200.0
SBL_TOL_MIN = 1e-4


def _method_params(method: str, given: dict) -> dict:
    defaults = solver(method).defaults  # the solver table's (pixel-scale units, `pixel_scale`)
    unknown = sorted(set(given) - set(defaults))
    if unknown:
        raise SolverInputError(f"method {method!r} has no parameter(s) {', '.join(unknown)}; "
                               f"it takes {', '.join(sorted(defaults))}")
    params = dict(defaults)
    params.update(given)
    if "segments" in params:
        k = params["segments"]
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not (
                1 <= k <= _pl_model.MAX_SEGMENTS):
            raise SolverInputError(f"segments must be a whole number from 1 to "
                                   f"{_pl_model.MAX_SEGMENTS}, got {k!r}")
        params["segments"] = int(k)
    return params


def solve(
    observations: np.ndarray,
    light_directions: np.ndarray,
    *,
    method: str = "auto",
    valid: np.ndarray | None = None,
    threads: int | None = None,
    tile_size: int | None = None,
    progress: Callable[[int], None] | None = None,
    **method_params,
) -> Solution:
    """Per-pixel surface normals and albedo from photometric-stereo observations.

    Parameters
    ----------
    observations : ndarray of shape (n, P)
        Linear intensities of P pixels under n lights (already divided by the light
        intensities, or pass light vectors scaled by intensity as ``light_directions``).
    light_directions : ndarray of shape (n, 3)
        Unit vectors from the surface toward each light (camera frame, x right, y up, z to
        the camera), optionally scaled by the light's intensity.
    method : str
        One of ``METHODS``: the solver table (:mod:`ps_lab.reconstruct.methods`, docs/solvers.md:
        ``auto``, Woodham least squares, L1 (IRLS), sparse Bayesian learning, the
        piecewise-linear models, R-PCA + least squares).
    valid : ndarray of shape (n, P), bool, optional
        False for observations to drop (saturated, under the shadow threshold). Non-finite
        observations are always dropped.
    threads : int, optional
        Worker threads over tiles and over the noise fit's pieces (default: all cores).
    tile_size : int, optional
        Pixels per tile, at most (default 4096; with several threads a small input is cut into
        smaller tiles, down to 512 pixels, so that each thread gets four). Results do not depend
        on it.
    progress : callable, optional
        Called as ``progress(k)`` with the number of pixels just finished (increments summing
        to P).
    **method_params
        The method's parameters, all in units of the pixel's robust scale (median of its usable
        observations):

        - ``sbl``: ``lam`` (noise variance; default per pixel from the data, below),
          ``sigma_x2`` (1e6), ``max_iter`` (100), ``tol`` (``max(1e-4, sigma / 200)``),
          ``gamma_floor`` (1e-10),
          ``gamma_start`` (1e3), ``outlier_threshold``;
        - ``l1``: ``max_iter`` (100), ``tol`` (1e-6), ``delta`` (1e-6), ``outlier_threshold``;
        - ``rpca``: ``lam_sparse`` (1/sqrt(max(n, P))), ``max_iter`` (500), ``tol`` (1e-7),
          ``rho`` (1.5), ``outlier_threshold``.

        ``outlier_threshold`` defaults to ``max(3 sigma, 0.05)`` with sigma the noise level;
        ``noise_sigma`` (l1, sbl, rpca) gives sigma instead of estimating it from these
        observations (for solving a capture in bands with whole-image parameters); SBL's
        default ``lam`` is, per pixel of scale ``s``, ``max(sigma^2 + (noise_floor / s)^2, 1e-6)``
        with ``noise_floor`` (sbl; in the observations' units) given or estimated
        (:func:`estimate_noise_model`).

    Returns
    -------
    Solution

    Raises
    ------
    SolverInputError
        Wrong shapes, non-finite or coplanar lights, unknown method or parameter.
    """
    obs, lights, usable = _check_inputs(observations, light_directions, valid)
    params = _method_params(method, method_params)
    row = solver(method)
    if row.chooses:
        # the SBL candidate runs SBL's own iterations, unless a cap is given for both models
        params["sbl_max_iter"] = int(method_params.get("max_iter", SBL_MAX_ITER))
    n, p = obs.shape
    workers = int(threads) if threads else (os.cpu_count() or 1)
    if workers < 1:
        raise SolverInputError(f"threads must be positive, got {threads}")
    bound = int(tile_size) if tile_size else DEFAULT_TILE_SIZE
    if bound < 1:
        raise SolverInputError(f"tile_size must be positive, got {tile_size}")
    tile = tile_pixels(p, workers, bound)
    starts = range(0, p, tile)
    parallel = workers > 1 and (len(starts) > 1 or row.estimates_noise)
    with ThreadPoolExecutor(max_workers=workers) if parallel else nullcontext() as pool:
        mapper = pool.map if pool is not None else map

        def residuals():
            return _noise_residuals(obs, lights, usable, mapper=mapper, workers=workers)

        def pl_noise(segments, noise_sigma):
            return pl_noise_level(obs, lights, usable, segments=segments,
                                  noise_sigma=noise_sigma, mapper=mapper, workers=workers)

        used = _solve_params(n, method, params, residuals, pl_noise)
        if row.one_light_matrix:
            sol = solve_rpca(obs, lights, usable, params, used, progress)
            rho = _albedo_rows(sol.normals @ lights.T, (usable & ~sol.outliers).T,
                               np.where(usable, obs, 0.0).T)
            sol.params["albedo"] = ALBEDO_DEFINITION
            return Solution(sol.normals, np.where(np.isnan(rho), sol.albedo, rho), sol.outliers,
                            sol.iterations, sol.params)
        used.update({"tile_size": bound, "threads": workers})
        if row.chooses:
            def pl_noise_of(columns):  # the PL noise on some pixels (the gate's failures)
                return pl_noise_level(obs[:, columns], lights, usable[:, columns],
                                      segments=params["segments"],
                                      noise_sigma=used["noise_sigma"], mapper=mapper,
                                      workers=workers)

            return auto_tiles(obs, lights, usable, params, used, starts, tile, mapper, progress,
                              pl_noise_of)
        return solve_tiles(obs, lights, usable, row, params, used, starts, tile, mapper,
                           progress)


def _solve_params(n, method, params, residuals, pl_noise=None) -> dict:
    """Fill in the data-driven defaults of ``params`` (in place); the parameters as used.

    ``n`` lights; ``residuals()`` returns the noise fit's residuals (:func:`_noise_residuals`),
    ``pl_noise(segments, noise_sigma)`` the PL models' noise level (:func:`pl_noise_level`).
    """
    used: dict = {"method": method}
    row = solver(method)
    sigma_pl = params.pop("noise_sigma_pl", None)
    if row.estimates_noise:
        noise = params.pop("noise_sigma")
        if row.sbl_noise:
            noise_floor = params.pop("noise_floor")
            light_noise = params.pop("light_noise")
            if light_noise is not None:
                light_noise = np.asarray(light_noise, dtype=np.float64)
                good = np.isfinite(light_noise) & (light_noise > 0)
                if light_noise.shape != (n,) or not np.all(good):
                    raise SolverInputError(f"light_noise must be {n} finite positive factors")
            params["light_noise"] = light_noise
            if params["lam"] is None and (noise is None or noise_floor is None):
                fit = residuals()
                if noise is None:
                    noise = _noise_level(*fit)
                if noise_floor is None:
                    noise_floor = _noise_floor(*fit, light_noise)
            params["noise_floor"] = noise_floor
            if params["lam"] is None:
                # per observation: max(noise_sigma^2 + (noise_floor light_noise_i / s)^2, 1e-6)
                used["lambda"] = None
                used["noise_floor"] = float(noise_floor)
                used["light_noise"] = None if light_noise is None else light_noise.tolist()
            else:
                used["lambda"] = float(params["lam"])
                if noise is None:
                    noise = math.sqrt(params["lam"])
        if params["outlier_threshold"] is None and noise is None:
            noise = _noise_level(*residuals())
        if noise is not None:
            used["noise_sigma"] = float(noise)
        if row.pl_noise and params["lam"] is None:
            if sigma_pl is None and row.chooses:
                # measured after SBL, on the pixels whose Lambertian fit fails (_auto_tiles)
                params["noise_sigma_pl"] = None
            elif sigma_pl is None:
                sigma_pl = pl_noise(params["segments"], noise)
            if sigma_pl is not None:
                used["noise_sigma_pl"] = params["noise_sigma_pl"] = float(sigma_pl)
        noise_defaults(row, params, noise)
    used.update({k: v for k, v in params.items()
                 if k not in ("lam", "noise_floor", "light_noise", "noise_sigma_pl")})
    return used


def noise_defaults(row, params: dict, noise: float | None) -> None:
    """Fill in, from the noise level, the outlier threshold and SBL's tolerance (in place).

    ``max(3 noise, MIN_OUTLIER_THRESHOLD)`` and, for SBL's methods (``row.sbl_noise``),
    ``max(SBL_TOL_MIN, SBL_TOL_NOISE_SHARE noise)``; those given are kept (``noise`` may be None
    only when neither is needed).
    """
    if params["outlier_threshold"] is None:
        params["outlier_threshold"] = max(3.0 * noise, MIN_OUTLIER_THRESHOLD)
    if row.sbl_noise and params["tol"] is None:
        params["tol"] = max(SBL_TOL_MIN, SBL_TOL_NOISE_SHARE * noise)


def tile_kernel(method: str):
    """The tile kernel of ``method`` (directional lights (n, 3); the PL kernels also (m, n, 3))."""
    return solver(method).tile
