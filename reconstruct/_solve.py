"""`solve`: input checks, per-pixel intensity scaling, the noise level, tiles and threads."""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext

import numpy as np

from . import _kernels, _pl_kernels
from ._linalg import SOLVABLE_REL_DET, pixel_scale  # noqa: F401 (near.py imports it from here)
from ._auto import auto_tiles
from ._rpca import solve_rpca
from ._solution import ALBEDO_DEFINITION, Solution, SolverInputError, _albedo_rows
from ._tiles import (DEFAULT_TILE_SIZE, LAMBDA_FLOOR, _prepare_tile, sbl_lambda, solve_tiles,
                     tile_pixels)
from .methods import SBL_MAX_ITER, SOLVERS, solver

# Defaults of each method's parameters (in units of the pixel's robust scale, see `pixel_scale`):
# the solver table's (methods.py).
DEFAULTS: dict[str, dict] = {row.name: dict(row.defaults) for row in SOLVERS}
# The noise fit's pixel sample is cut into pieces of at least this many pixels for the threads.
NOISE_PIECE_PIXELS = 1000
# Smallest outlier threshold (relative to the pixel scale); _pl_algebra.GATE_NOISE is its third.
MIN_OUTLIER_THRESHOLD = 0.05
NOISE_SAMPLE_PIXELS = 4000
# Observations below this share of the pixel scale are not used to estimate the noise.
SHADOW_FRACTION = 0.1
# The noise is read from a low quantile of the residual magnitudes, which stays clean while
# up to 75% of the residuals are corrupted (speculars, inter-reflections): for Gaussian noise
# the 25% quantile of abs(r) is 0.3186 sigma.
NOISE_QUANTILE = 0.25
NOISE_QUANTILE_Z = 0.31864
# The noise floor (noise constant in the observations' own units: quantisation, read noise) is
# fitted on this many equal-count bins of pixel scale, each needing this many residuals.
NOISE_FLOOR_BINS = 8
# Seed of the PL noise estimate's parametric bootstrap (pl_noise_level): the estimate is
# a function of the data.
PL_NOISE_SEED = 20140601
# It looks for the noise whose simulated estimate is the measured one, by at most this many
# rescalings, stopping once they change it by less than PL_NOISE_RTOL.
PL_NOISE_ROUNDS = 6
PL_NOISE_RTOL = 0.01
NOISE_FLOOR_MIN_COUNT = 50
# SBL's default tolerance: a change of the corruption estimate this small against the noise level
# moves no normal (docs/solvers.md), and never tighter than SBL_TOL_MIN (noise-free data).
SBL_TOL_NOISE_SHARE = 1.0 / 200.0
SBL_TOL_MIN = 1e-4



def light_noise_factors(light_intensities: np.ndarray, channel: str = "mean") -> np.ndarray:
    """Relative noise floor of each light's observations after the intensity division.

    Parameters
    ----------
    light_intensities : ndarray of shape (n, 3)
        RGB intensity of each light, as the observations were divided by.
    channel : {"mean", "r", "g", "b"}
        The colour rule (``mean``: the channels divided by their intensities are averaged).

    Returns
    -------
    ndarray of shape (n,)
        ``sqrt(sum_c 1 / I_ic^2)`` (mean) or ``1 / I_ik`` (one channel), scaled to mean square 1:
        noise that is the same in every raw image (quantisation, read noise) is this much larger,
        relative to the others, in light i's observations.
    """
    intensity = np.asarray(light_intensities, dtype=np.float64)
    pick = {"r": 0, "g": 1, "b": 2}
    if channel == "mean":
        f2 = (1.0 / intensity**2).sum(axis=1)
    else:
        f2 = 1.0 / intensity[:, pick[channel]] ** 2
    if not np.all(np.isfinite(f2)) or not np.all(f2 > 0):
        raise SolverInputError("light intensities must be finite and positive")
    return np.sqrt(f2 / f2.mean())


def _check_inputs(observations, light_directions, valid):
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


def _method_params(method: str, given: dict) -> dict:
    allowed = set(solver(method).defaults)
    unknown = sorted(set(given) - allowed)
    if unknown:
        raise SolverInputError(f"method {method!r} has no parameter(s) {', '.join(unknown)}; "
                               f"it takes {', '.join(sorted(allowed))}")
    params = dict(DEFAULTS[method])
    params.update(given)
    if "segments" in params:
        k = params["segments"]
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not (
                1 <= k <= _pl_kernels.MAX_SEGMENTS):
            raise SolverInputError(f"segments must be a whole number from 1 to "
                                   f"{_pl_kernels.MAX_SEGMENTS}, got {k!r}")
        params["segments"] = int(k)
    return params



def estimate_noise(observations, light_directions, valid=None, *,
                   max_pixels: int = NOISE_SAMPLE_PIXELS) -> float:
    """Noise level of the scaled observations, from residuals of a robust (L1) fit.

    Parameters
    ----------
    observations : ndarray of shape (n, P)
    light_directions : ndarray of shape (n, 3)
    valid : ndarray of shape (n, P), bool, optional
    max_pixels : int
        At most this many pixels (evenly spaced) are used.

    Returns
    -------
    float
        A standard deviation relative to a pixel's typical observation: the residuals ``r``
        of the per-pixel L1 fit on observations divided by the pixel's robust scale, kept
        where the observation and the fit both exceed ``SHADOW_FRACTION`` (shadows are not
        noise) and ``r`` is not one of the pixel's 3 smallest (the fit's interpolations); then ``quantile(|r|, 0.25) / 0.31864``
        (the Gaussian ratio), which ignores up to 75 % corrupted residuals.
    """
    obs, lights, usable = _check_inputs(observations, light_directions, valid)
    return _noise_level(*_noise_residuals(obs, lights, usable, max_pixels))


def estimate_noise_model(observations, light_directions, valid=None, *,
                         max_pixels: int = NOISE_SAMPLE_PIXELS,
                         light_noise: np.ndarray | None = None, mapper=map,
                         workers: int = 1) -> tuple[float, float]:
    """Both noise terms of SBL's default lambda, from one L1 fit (see :func:`sbl_lambda`).

    Parameters are those of :func:`estimate_noise`, and ``light_noise`` (n,), the relative noise
    floor of each light (:func:`sbl_lambda`; default all 1).

    Returns
    -------
    noise_sigma : float
        As :func:`estimate_noise`.
    noise_floor : float
        Noise constant in the observations' units (quantisation, read noise): the same residuals
        as :func:`estimate_noise`, cut into ``NOISE_FLOOR_BINS`` equal-count bins of
        ``x = light_noise_i^2 / s^2`` (``s`` the pixel scale); each bin's Gaussian-equivalent
        variance (25 % quantile) is fitted by ``sigma_abs^2 x + sigma_rel^2`` (both >= 0, relative
        least squares), and ``noise_floor = sigma_abs``. Zero for float renders and when dark
        pixels are no noisier (relative to their scale) than bright ones.

    The sample is fitted in up to ``workers`` pieces through ``mapper`` (as
    :func:`_noise_residuals`); the result does not depend on them.
    """
    obs, lights, usable = _check_inputs(observations, light_directions, valid)
    residuals = _noise_residuals(obs, lights, usable, max_pixels, mapper=mapper, workers=workers)
    return _noise_level(*residuals), _noise_floor(*residuals, light_noise)


def _noise_residuals(obs, lights, usable, max_pixels=NOISE_SAMPLE_PIXELS, mapper=map,
                     workers=1):
    """Relative residuals of an L1 fit on a pixel sample, each residual's pixel scale and light.

    The sample is fitted in up to ``workers`` pieces through ``mapper`` (``map``, or a thread
    pool's ``map``); the pixels are independent, so the result does not depend on the pieces.
    """
    n, p = obs.shape
    empty = np.zeros(0), np.zeros(0), np.zeros(0, np.int64)
    if p == 0:
        return empty
    take = np.unique(np.linspace(0, p - 1, min(p, max_pixels)).round().astype(np.int64))
    pieces = max(1, min(workers, take.size // NOISE_PIECE_PIXELS))

    def fit(part):
        y, w, scale, ok = _prepare_tile(obs[:, part], usable[:, part], lights, 0, part.size)
        y, w, scale = y[ok], w[ok], scale[ok]
        res = _kernels.l1_tile(y, w, lights, max_iter=30, tol=1e-6, delta=1e-6,
                               outlier_threshold=np.inf)
        r, keep = _kept_residuals(y, w, res.x @ lights.T)
        keep &= ~_interpolated(r, w)
        light = np.broadcast_to(np.arange(n)[None, :], r.shape)[keep]
        return r[keep], np.broadcast_to(scale[:, None], r.shape)[keep], light

    parts = list(mapper(fit, np.array_split(take, pieces)))
    return tuple(np.concatenate([part[k] for part in parts]) for k in range(3))


def pl_noise_level(observations, light_directions, valid=None, *, segments: int = 3,
                   noise_sigma: float, max_pixels: int = NOISE_SAMPLE_PIXELS, mapper=map,
                   workers: int = 1) -> float:
    """Noise level left by the piecewise-linear model on a pixel sample, relative.

    :func:`estimate_noise`'s estimate for the PL models: SBL's (from a robust Lambertian fit,
    L1) holds the dense misfit of the Lambertian model (non-Lambertian shading), which the PL
    model explains. Each sampled pixel is fitted robustly by PL-SBL (``segments`` segments, 20
    EM steps, noise variance ``noise_sigma^2``: the Lambertian estimate, an upper bound); a
    residual in the pixel's relative units is ``(f(y_i) - n.l_i) / s_k(i)`` (the equation's
    error over its segment's slope); the kept residuals and the quantile are
    :func:`estimate_noise`'s.

    The PL fit has ``2 segments + 1`` unknowns against the L1 fit's 3, and its residuals are
    smaller than the noise by a share that grows as the lights get fewer (12 lights: 1.5x,
    96: 1.04-1.07x on DiLiGenT). The estimate is made consistent on the same pixels, lights and
    usable observations by a parametric bootstrap: the sample's robust Lambertian fit (L1) plus
    Gaussian noise ``sigma`` (seeded: ``PL_NOISE_SEED``) is fitted and measured the same way, and
    ``sigma`` is rescaled until that estimate is the measured one (at most ``PL_NOISE_ROUNDS``;
    on Lambertian data with known noise it returns it within 2 % at 12 lights). The
    sample is fitted in up to ``workers`` pieces through ``mapper`` (as :func:`_noise_residuals`);
    the result does not depend on the pieces.
    """
    obs, lights, usable = _check_inputs(observations, light_directions, valid)
    n, p = obs.shape
    if p == 0:
        return 0.0
    take = np.unique(np.linspace(0, p - 1, min(p, max_pixels)).round().astype(np.int64))
    y, w, _, ok = _prepare_tile(obs[:, take], usable[:, take], lights, 0, take.size)
    y, w = y[ok], w[ok]
    if y.shape[0] == 0:
        return 0.0
    count = max(1, min(workers, take.size // NOISE_PIECE_PIXELS))
    pieces = np.array_split(np.arange(y.shape[0]), count)
    lam = max(noise_sigma * noise_sigma, LAMBDA_FLOOR)

    def level(data, use):
        def fit(rows):
            res = _pl_kernels.pl_tile(data[rows], use[rows], lights, segments=segments, lam=lam,
                                      max_iter=20, tol=0.0, residuals=True,
                                      sbl_start=False)  # the noise: one flat-start fit
            r, keep = _kept_residuals(data[rows], use[rows], data[rows] - res.residuals)
            return r[keep]

        return _noise_level(np.concatenate(list(mapper(fit, pieces))))

    raw = level(y, w)
    if raw <= 0.0 or 2.0 * raw <= math.sqrt(LAMBDA_FLOOR):
        return raw  # the consistency factor (< 2) cannot lift it over the noise variance's floor

    def lambertian(rows):
        res = _kernels.l1_tile(y[rows], w[rows], lights, max_iter=30, tol=1e-6, delta=1e-6,
                               outlier_threshold=np.inf)
        return res.x @ lights.T

    model = np.concatenate(list(mapper(lambertian, pieces)))
    noise = np.random.default_rng(PL_NOISE_SEED).standard_normal(y.shape)
    lit = np.where((w > 0) & (model > 0.0), 1.0, 0.0)  # the model's shadows are dropped
    sigma = raw
    for _ in range(PL_NOISE_ROUNDS):
        measured = level(np.where(lit > 0, model + sigma * noise, 0.0), lit)
        if measured <= 0.0:
            break
        sigma *= raw / measured
        if abs(raw / measured - 1.0) < PL_NOISE_RTOL:
            break
    return sigma


def _kept_residuals(y, w, model):
    """``|y - model|`` (m, n) and the mask of residuals that are noise samples.

    Attached and cast shadows are the bulk of the corruptions (often half the observations of a
    pixel), so only observations that are lit and predicted lit count; the L1 fit interpolates
    three observations per pixel exactly, which are not residual samples either.
    """
    r = np.abs(y - model)
    return r, (w > 0) & (y > SHADOW_FRACTION) & (model > SHADOW_FRACTION) & (r > 1e-12)


def _interpolated(r, w, unknowns=3):
    """(m, n) mask of each pixel's ``unknowns`` smallest usable residuals ``r``.

    An L1 fit interpolates as many observations as it has unknowns; IRLS reaches them only to
    ~1e-7 (not 0), and with few lights they are a quarter of the kept residuals, which pulled the
    25 % quantile to ~0 (12 of DiLiGenT's lights: 0.001-0.008 against 0.03-0.10 from all 96).
    """
    ru = np.where(w > 0, r, np.inf)
    k = min(unknowns, r.shape[1]) - 1
    if k < 0 or r.shape[0] == 0:
        return np.zeros(r.shape, bool)
    third = np.partition(ru, k, axis=1)[:, k:k + 1]
    return ru <= third


def residual_noise(y: np.ndarray, w: np.ndarray, model: np.ndarray) -> float:
    """Noise level from the residuals of scaled observations ``y`` (m, n) against a robust fit."""
    r, keep = _kept_residuals(y, w, model)
    return _noise_level(r[keep])


def _quantile(a, q):
    """``np.quantile(a, q)`` (linear interpolation, same rounding) by one partition."""
    where = q * (a.size - 1)
    lo = int(math.floor(where))
    t = where - lo
    hi = min(lo + 1, a.size - 1)
    part = np.partition(a, [lo, hi] if hi > lo else [lo])
    low, high = float(part[lo]), float(part[hi])
    diff = high - low
    return high - diff * (1.0 - t) if t >= 0.5 else low + diff * t


def _noise_level(r, s=None, light=None):
    return _quantile(r, NOISE_QUANTILE) / NOISE_QUANTILE_Z if r.size else 0.0


def _noise_floor(r, s, light, light_noise=None):
    """``sigma_abs`` of ``var(r) = sigma_abs^2 x + sigma_rel^2`` fitted over bins of ``x``.

    ``x = light_noise[light]^2 / s^2``: the noise floor's share of each residual's variance.
    """
    if r.size < NOISE_FLOOR_MIN_COUNT * 2:
        return 0.0
    f2 = np.ones(1) if light_noise is None else np.asarray(light_noise, dtype=np.float64) ** 2
    x = f2[light if light_noise is not None else 0] / s**2
    order = _stable_order(x)
    x, r = x[order], r[order]
    size, extra = divmod(r.size, NOISE_FLOOR_BINS)  # np.array_split's equal-count bins
    rows, var = [], []
    end = 0
    for k in range(NOISE_FLOOR_BINS):
        start, end = end, end + size + (k < extra)
        if end - start < NOISE_FLOOR_MIN_COUNT:
            continue
        v = _noise_level(r[start:end]) ** 2
        if v > 0:
            mid = (start + end - 1) // 2, (start + end) // 2  # x is sorted: its median
            rows.append((0.5 * (x[mid[0]] + x[mid[1]]), 1.0))
            var.append(v)
    if len(var) < 2:
        return 0.0
    # Relative least squares (each bin's variance counts alike), both coefficients >= 0.
    a = np.array(rows) / np.array(var)[:, None]
    coef = np.linalg.lstsq(a, np.ones(len(var)), rcond=None)[0]
    if coef[1] < 0:
        coef = np.array([np.sum(a[:, 0]) / np.sum(a[:, 0] ** 2), 0.0])
    return float(math.sqrt(max(coef[0], 0.0)))


def _stable_order(x):
    """``np.argsort(x, kind="stable")``; sorts only the runs of equal values when there are few.

    Without per-light factors the noise floor's ``x`` is one value per pixel, repeated over its
    residuals: a run sorted by its value (stably) and expanded in place is the stable order.
    """
    starts = np.flatnonzero(np.concatenate(([True], x[1:] != x[:-1])))
    if starts.size > x.size // 4:
        return np.argsort(x, kind="stable")
    runs = np.argsort(x[starts], kind="stable")
    lengths = np.diff(np.append(starts, x.size))[runs]
    # output position k of a run placed at position q is its element starts[run] + k - q
    return np.repeat(starts[runs] - (np.cumsum(lengths) - lengths), lengths) + np.arange(x.size)


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
