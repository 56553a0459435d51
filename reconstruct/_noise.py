"""The noise model of the solvers: the relative noise level, the noise floor and each light's
share of it, and the piecewise-linear models' own level.

Every estimate is made on an evenly spaced sample of pixels (``NOISE_SAMPLE_PIXELS``) from the
residuals of a robust fit (:func:`estimate_noise`, :func:`estimate_noise_model`,
:func:`pl_noise_level`); :func:`ps_lab.reconstruct.solve` turns them into SBL's default ``lam``
(:func:`._tiles.sbl_lambda`), the outlier threshold and SBL's tolerance (``_solve.noise_defaults``).
"""

from __future__ import annotations

import math

import numpy as np

from . import _kernels, _pl_kernels
from ._solution import SolverInputError
from ._solution import check_inputs as _check_inputs
from ._tiles import LAMBDA_FLOOR, _prepare_tile

# The noise fit's pixel sample is cut into pieces of at least this many pixels for the threads.
NOISE_PIECE_PIXELS = 1000
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
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):  # refused just below
        if channel == "mean":
            f2 = (1.0 / intensity**2).sum(axis=1)
        else:
            f2 = 1.0 / intensity[:, pick[channel]] ** 2
    if not np.all(np.isfinite(f2)) or not np.all(f2 > 0):
        raise SolverInputError("light intensities must be finite and positive")
    return np.sqrt(f2 / f2.mean())


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
