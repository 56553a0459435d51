"""Observations indistinguishable from black: the automatic shadow threshold.

A pixel in shadow receives no light from the LED that is on, so after the dark frame is subtracted
its observation is pure sensor noise around zero: half of such observations are negative. They say
nothing about the pixel's normal except that the light is behind it, and they are the part of a
non-Lambertian corruption that is *not* sparse on rims and in concavities, where a third or more of
a pixel's lights are hidden (a near-light dome lights rims from low elevations: 11 % of all
observations of ``rigs/simulated-near.toml`` are in shadow, and keeping them costs SBL 0.24° ->
0.63°, see docs/solvers.md).

Real signals are never negative, so the negative observations measure the noise at black: for
zero-mean noise of standard deviation ``sigma`` at zero signal, ``E[x^2 | x < 0] = sigma^2``. Each
light's observations were divided by its intensity, so the raw noise is scaled per light by
:func:`ps_lab.reconstruct.light_noise_factors`. An observation at most ``k sigma_i`` (``k`` = 3)
is dropped as a shadow, as a saturated one is dropped.

Data without a dark-frame subtraction (8- and 16-bit benchmark PNGs, float renders) has no
negative values, but black is still visible in it: the sensor (or the renderer) clips at its
black level, so the darkest value of a light's images is an *atom*, many observations exactly
equal to it (0 in DiLiGenT's 8-bit crops, where everything under one grey level is 0; exact 0
in a render's shadows). Observations at that level are indistinguishable from black and are
dropped (the authors of SBL and PL-SBL drop observations <= 0). A light whose darkest value is
not repeated has no visible black level and keeps every observation.

Clipping hides the noise at black, not its effect: a shadowed observation is black plus noise, and
the half of that noise above black survives the clip as small positive values (a 16-bit capture
without a dark frame: up to 3 read-noise sigma above 0, with nothing negative to measure it by).
Given the light directions, the noise in the observations' own units (the *noise floor*:
quantisation and read noise, :func:`ps_lab.reconstruct.estimate_noise_model`, fitted on the
residuals of lit observations only) stands in for the unmeasurable noise at black, and an
observation at most ``k`` floors above its light's black level is a shadow too. Float renders
have no floor (0) and drop only their exact zeros; on a 12-light grey sphere at 16 bits the
surviving half of the shadows' noise gave SBL 0.7 % wild normals on the rim, and none once dropped
(docs/solvers.md).
"""

from __future__ import annotations

import numpy as np

from ._solve import estimate_noise_model

__all__ = ["BLACK_SIGMAS", "black_level", "black_threshold"]

# Observations within this many standard deviations of the noise at black are shadows: at 3,
# 0.13 % of a shadow's noise is kept, and a lit observation loses at most 3 sigma of signal.
BLACK_SIGMAS = 3.0
# Fewer negative observations than this (count, and share of the usable ones) measure no noise.
_MIN_NEGATIVE = 200
_MIN_NEGATIVE_SHARE = 1e-3


def black_threshold(
    observations: np.ndarray,
    valid: np.ndarray,
    light_noise: np.ndarray | None = None,
    sigmas: float = BLACK_SIGMAS,
    light_directions: np.ndarray | None = None,
) -> np.ndarray | None:
    """Per-light threshold below which an observation is black (a shadow), or None.

    Parameters
    ----------
    observations : ndarray of shape (n, m)
        A sample of pixels' observations (dark-subtracted, divided by the light intensities).
    valid : ndarray of shape (n, m), bool
        Their validity (saturated and otherwise unusable observations are False).
    light_noise : ndarray of shape (n,) or None
        Each light's relative noise after the intensity division
        (:func:`ps_lab.reconstruct.light_noise_factors`); None for the same in every light.
    sigmas : float
        The threshold in standard deviations of the noise at black.
    light_directions : ndarray of shape (n, 3), optional
        The lights; given, data without negative values also drop what lies within ``sigmas``
        noise floors above a light's black level (the module's text).

    Returns
    -------
    ndarray of shape (n,), float32, or None
        ``sigmas * sigma_black * light_noise``; with no negative observation at all, the black
        level of :func:`black_level`, plus ``sigmas * noise_floor * light_noise`` for the lights
        that have one when ``light_directions`` are given; None when too few observations are
        negative to measure the noise at black, or when nothing is at a black level.
    """
    obs = np.asarray(observations, dtype=np.float64)
    usable = np.asarray(valid, dtype=bool) & np.isfinite(obs)
    n = obs.shape[0]
    factors = np.ones(n) if light_noise is None else np.asarray(light_noise, dtype=np.float64)
    negative = usable & (obs < 0)
    count = int(negative.sum())
    if count < max(_MIN_NEGATIVE, _MIN_NEGATIVE_SHARE * int(usable.sum())):
        if count:
            return None
        atoms = _atoms(obs, usable)
        if atoms is None:
            return None
        low, atom = atoms
        level = np.where(atom, low, 0.0)
        if light_directions is not None:
            _, floor = estimate_noise_model(obs, light_directions, usable & (obs > level[:, None]),
                                            max_pixels=obs.shape[1], light_noise=factors)
            level = np.where(atom, level + sigmas * floor * factors, 0.0)
        return level.astype(np.float32)
    scaled = obs / factors[:, None]
    sigma = float(np.sqrt(np.mean(scaled[negative] ** 2)))
    if not np.isfinite(sigma) or sigma <= 0:
        return None
    return (sigmas * sigma * factors).astype(np.float32)


def black_level(observations: np.ndarray, usable: np.ndarray) -> np.ndarray | None:
    """Per-light clipping level of data without negative values, or None.

    Parameters
    ----------
    observations : ndarray of shape (n, m)
        A sample of pixels' observations (none negative).
    usable : ndarray of shape (n, m), bool
        Their validity (and finiteness).

    Returns
    -------
    ndarray of shape (n,), float32, or None
        Light i's darkest usable value where at least 2 observations equal it (an atom: the
        level the sensor or renderer clipped black to), 0 for a light without one (it keeps
        every positive observation); None when the atoms hold fewer than ``_MIN_NEGATIVE`` and
        ``_MIN_NEGATIVE_SHARE`` of the usable observations.
    """
    atoms = _atoms(np.asarray(observations, dtype=np.float64), np.asarray(usable, dtype=bool))
    if atoms is None:
        return None
    low, atom = atoms
    return np.where(atom, low, 0.0).astype(np.float32)


def _atoms(observations: np.ndarray, usable: np.ndarray):
    """Each light's darkest usable value (n,) and whether it is an atom (n,), or None (too few)."""
    obs = np.where(usable, observations, np.inf)
    low = obs.min(axis=1)
    at_low = (obs == low[:, None]) & usable
    counts = at_low.sum(axis=1)
    atom = np.isfinite(low) & (counts >= 2)
    total = int(counts[atom].sum())
    if total < max(_MIN_NEGATIVE, _MIN_NEGATIVE_SHARE * int(usable.sum())):
        return None
    return low, atom
