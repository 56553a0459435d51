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

Black is also visible as an *atom*: the sensor (or the renderer) clips at its black level, so many
observations of a light are exactly equal to one value at the bottom of its range (0 in DiLiGenT's
8-bit crops, where everything under one grey level is 0; exact 0 in a render's shadows). A value
repeated exactly at the bottom of a light's range is a clipped or rendered shadow whatever else the
data hold: a float render with sparse additive noise (the authors' synthetic bunny) has exact-zero
shadows on ~20 % of its observations *and* ~1 % negative values (the noise that fell on a shadow),
and those negatives are not noise at black (black is exact there). So, per light, the atom is
looked for first (:func:`_atoms`: the smallest repeated value holding at least as many observations
as lie below it and, where some do or where it is above 0, a pile-up over the next value up, which
the steps of a quantised noise distribution are not; and dark, near 0 against the light's bright
observations); observations at or below it are dropped (the authors of SBL
and PL-SBL drop observations <= 0). Only the lights without an atom use the negative observations'
3 sigma rule above, and with too few negatives to measure the noise, keep everything (a light whose
darkest value is not repeated and nothing negative drops observations <= 0 once another light has
an atom).

Clipping hides the noise at black, not its effect: a shadowed observation is black plus noise, and
the half of that noise above black survives the clip as small positive values (a 16-bit capture
without a dark frame: up to 3 read-noise sigma above 0, with nothing negative to measure it by).
Given the light directions, the noise in the observations' own units (the *noise floor*:
quantisation and read noise, :func:`ps_lab.reconstruct.estimate_noise_model`, fitted on the
residuals of lit observations only) stands in for the unmeasurable noise at black, and an
observation at most ``k`` floors above its light's black level is a shadow too (with or without
negative values elsewhere). Float renders have no floor (0) and drop only their exact zeros (and,
with sparse noise, the negative observations below them); on a 12-light grey sphere at 16 bits the
surviving half of the shadows' noise gave SBL 0.7 % wild normals on the rim, and none once dropped
(docs/solvers.md).
"""

from __future__ import annotations

import numpy as np

from ._noise import estimate_noise_model

__all__ = ["BLACK_SIGMAS", "KEEP_ALL", "black_level", "black_threshold"]

# Observations within this many standard deviations of the noise at black are shadows: at 3,
# 0.13 % of a shadow's noise is kept, and a lit observation loses at most 3 sigma of signal.
BLACK_SIGMAS = 3.0
# Fewer negative observations than this (count, and share of the usable ones) measure no noise.
_MIN_NEGATIVE = 200
_MIN_NEGATIVE_SHARE = 1e-3
# A black atom with observations below it holds at least this many times the observations of
# the next value above it (a pile-up, not a step of quantised noise), and is looked for in the
# darkest ATOM_SEARCH_SHARE of the light's observations.
ATOM_PILE_UP = 4
ATOM_SEARCH_SHARE = 0.5
# ... and is at most ATOM_MAX_SHARE of the light's ATOM_BRIGHT_QUANTILE quantile: a clipped
# black is near 0 whatever its offset (a dark frame, a 16-bit black level of a few DN).
ATOM_MAX_SHARE = 0.05
ATOM_BRIGHT_QUANTILE = 0.9
# The threshold of a light whose observations are all kept (finite, so metrics.json can hold it).
KEEP_ALL = float(np.finfo(np.float32).min)


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
        A sample of pixels' observations (divided by the light intensities).
    valid : ndarray of shape (n, m), bool
        Their validity (saturated and otherwise unusable observations are False).
    light_noise : ndarray of shape (n,) or None
        Each light's relative noise after the intensity division
        (:func:`ps_lab.reconstruct.light_noise_factors`); None for the same in every light.
    sigmas : float
        The threshold in standard deviations of the noise at black.
    light_directions : ndarray of shape (n, 3), optional
        The lights; given, what lies within ``sigmas`` noise floors above a light's black level
        is dropped too (the module's text).

    Returns
    -------
    ndarray of shape (n,), float32, or None
        Per light: where the light has a black atom (:func:`black_level`), the atom, plus
        ``sigmas * noise_floor * light_noise`` when ``light_directions`` are given, whether or
        not the data hold negative values (sparse noise on a render); for the other lights
        ``sigmas * sigma_black * light_noise`` with ``sigma_black`` measured on their negative
        observations, or, with too few negatives to measure it, ``KEEP_ALL`` (every observation
        kept). None when no light has an atom and the noise at black cannot be measured.
    """
    obs = np.asarray(observations, dtype=np.float64)
    usable = np.asarray(valid, dtype=bool) & np.isfinite(obs)
    n = obs.shape[0]
    factors = np.ones(n) if light_noise is None else np.asarray(light_noise, dtype=np.float64)
    atoms = _atoms(obs, usable)
    atom = np.zeros(n, bool) if atoms is None else atoms[1]
    level = np.full(n, KEEP_ALL, dtype=np.float64)
    if atom.any():
        level[atom] = atoms[0][atom]
        if light_directions is not None:
            lit = usable & (obs > np.where(atom, level, -np.inf)[:, None])
            _, floor = estimate_noise_model(obs, light_directions, lit, max_pixels=obs.shape[1],
                                            light_noise=factors)
            level[atom] += sigmas * floor * factors[atom]
    # the noise at black, from the negative observations of the lights without an atom
    rest = usable & ~atom[:, None]
    negative = rest & (obs < 0)
    count = int(negative.sum())
    if count and count >= max(_MIN_NEGATIVE, _MIN_NEGATIVE_SHARE * int(rest.sum())):
        scaled = obs / factors[:, None]
        sigma = float(np.sqrt(np.mean(scaled[negative] ** 2)))
        if np.isfinite(sigma) and sigma > 0:
            level[~atom] = sigmas * sigma * factors[~atom]
            return level.astype(np.float32)
    if not atom.any():
        return None
    # lights without an atom and without measurable noise: nothing negative -> drop <= 0 as the
    # atoms' lights do (a light whose darkest value is not repeated has at most one 0); else keep
    no_negative = ~(usable & (obs < 0)).any(axis=1)
    level[~atom & no_negative] = 0.0
    return level.astype(np.float32)


def black_level(observations: np.ndarray, usable: np.ndarray) -> np.ndarray | None:
    """Per-light clipping level (the black atom), or None.

    Parameters
    ----------
    observations : ndarray of shape (n, m)
        A sample of pixels' observations.
    usable : ndarray of shape (n, m), bool
        Their validity (and finiteness).

    Returns
    -------
    ndarray of shape (n,), float32, or None
        Light i's black atom (:func:`_atoms`: the level the sensor or renderer clipped black to),
        0 for a light without one; None when the atoms hold fewer than ``_MIN_NEGATIVE`` and
        ``_MIN_NEGATIVE_SHARE`` of the usable observations.
    """
    atoms = _atoms(np.asarray(observations, dtype=np.float64), np.asarray(usable, dtype=bool))
    if atoms is None:
        return None
    low, atom = atoms
    return np.where(atom, low, 0.0).astype(np.float32)


def _atoms(observations: np.ndarray, usable: np.ndarray):
    """Each light's black atom (n,) and whether it has one (n,), or None (too few in all).

    The atom of a light is the smallest value ``v`` of its usable observations that is repeated
    (at least 2) and a pile-up at the bottom of the light's range: no more observations lie
    below ``v`` than at it, and, where some do (negative noise on a render's exact zeros), ``v``
    holds ``ATOM_PILE_UP`` times the observations of the next value above it (a clipped or
    rendered black, not a step of a quantised noise distribution). Without anything below it,
    the darkest value is the atom when it is repeated and at or below 0 (a clip at black: 8-bit
    zeros), or, above 0, when it is such a pile-up too. Every atom is dark: at most
    ``ATOM_MAX_SHARE`` of the light's ``ATOM_BRIGHT_QUANTILE`` quantile (issue 42: an 8-bit JPEG
    of a lit object repeats its darkest code, and a flat matte region piles up on its own grey;
    SynthRTI lost 32-47 % of some collections' lit observations to them).
    """
    n = observations.shape[0]
    low = np.zeros(n)
    atom = np.zeros(n, bool)
    total = 0
    for i in range(n):
        v = np.sort(observations[i][usable[i]])
        if v.size < 2:
            continue
        starts = np.flatnonzero(np.concatenate(([True], v[1:] != v[:-1])))
        counts = np.diff(np.append(starts, v.size))
        nxt = np.append(counts[1:], 0)
        # a pile-up over the next value up, with or without values below it: the darkest code
        # of an 8-bit JPEG of a lit object is repeated too, but no more often than its
        # neighbours (SynthRTI: 32 % of material4's lit observations were taken for black)
        bottom = (starts == 0) & (v[starts] <= 0.0)  # a clip at or below black: any repeat
        # black is dark: near zero against the light's bright observations (a flat matte
        # region piles up on one value of its own, a lit grey: SynthRTI material1)
        dark = v[starts] <= ATOM_MAX_SHARE * v[int(ATOM_BRIGHT_QUANTILE * (v.size - 1))]
        pile = (counts >= 2) & (counts >= starts) & dark & (
            bottom | (counts >= ATOM_PILE_UP * nxt))
        # only the bottom of the range: the first value holding more than what lies below
        first = np.flatnonzero(pile & (np.cumsum(counts) <= ATOM_SEARCH_SHARE * v.size + counts))
        if first.size:
            j = first[0]
            low[i] = v[starts[j]]
            atom[i] = True
            total += int(counts[j])
    if total < max(_MIN_NEGATIVE, _MIN_NEGATIVE_SHARE * int(usable.sum())):
        return None
    return low, atom
