"""The automatic shadow threshold: the noise at black, or the black level and the noise floor."""

from __future__ import annotations

import numpy as np
import pytest

from ps_lab import render
from ps_lab.reconstruct import light_noise_factors
from ps_lab.reconstruct._shadows import BLACK_SIGMAS, black_threshold


def _observations(rng: np.random.Generator, sigma: float, factors: np.ndarray, shadow: float):
    """Lit observations in (0.05, 1) and a share ``shadow`` at zero signal, plus noise."""
    n, m = factors.size, 20000
    signal = rng.uniform(0.05, 1.0, (n, m))
    signal[rng.random((n, m)) < shadow] = 0.0
    return signal + rng.normal(0.0, sigma, (n, m)) * factors[:, None]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_black_threshold_measures_the_noise_per_light(seed: int) -> None:
    rng = np.random.default_rng(seed)
    intensities = rng.uniform(0.5, 1.5, (24, 3))
    factors = light_noise_factors(intensities)
    sigma = 1.2e-4
    obs = _observations(rng, sigma, factors, shadow=0.1)
    valid = np.ones(obs.shape, bool)
    valid[:, ::7] = False  # unusable observations are not counted
    threshold = black_threshold(obs, valid, factors)
    assert threshold is not None and threshold.shape == (24,)
    np.testing.assert_allclose(threshold, BLACK_SIGMAS * sigma * factors, rtol=0.03)
    # nearly every shadow is dropped, nearly no lit observation
    shadows = obs < 1e-2
    below = obs <= threshold[:, None]
    assert below[shadows].mean() > 0.99
    assert below[~shadows].mean() == 0.0


def test_without_negatives_the_clipped_black_level_is_the_threshold() -> None:
    rng = np.random.default_rng(3)
    clipped = np.clip(_observations(rng, 1e-3, np.ones(8), shadow=0.2), 0.0, None)
    valid = np.ones(clipped.shape, bool)
    # clipped at 0 (10 % of the observations, the shadows' negative half): the level is 0
    np.testing.assert_array_equal(black_threshold(clipped, valid), np.zeros(8))
    # the same with a black level of 0.002 in light 3 only, and light 5 never at black
    level = clipped.copy()
    level[3] = np.maximum(level[3], 0.002)
    level[5] = rng.uniform(0.01, 1.0, level.shape[1])
    expected = np.zeros(8, np.float32)
    expected[3] = 0.002
    np.testing.assert_array_equal(black_threshold(level, valid), expected)
    # nothing repeated at the bottom (no clipping, no dark-frame subtraction): nothing measured
    smooth = rng.uniform(1e-3, 1.0, clipped.shape)
    assert black_threshold(smooth, valid) is None
    # a handful of distinct negatives (too few to measure noise at black) do not hide the atoms
    # at 0 (issue 31: a render's exact zeros with sparse noise): every light's level stays 0
    clipped[0, :50] = -rng.uniform(1e-4, 1e-3, 50)
    np.testing.assert_array_equal(black_threshold(clipped, valid), np.zeros(8))
    # a value repeated at the bottom of a light's range is that light's black, negative or not
    clipped[0, :50] = -1e-3
    expected = np.zeros(8, np.float32)
    expected[0] = -1e-3
    np.testing.assert_array_equal(black_threshold(clipped, valid), expected)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_clipped_noise_above_black_is_dropped_with_the_noise_floor(seed: int) -> None:
    # a 16-bit capture without a dark frame: shadows are black + noise, clipped at 0, so the
    # upper half of their noise survives as small positive values, with no negative to measure
    rng = np.random.default_rng(seed)
    lights = render.random_light_directions(24, rng)
    surf = render.sphere_surface((64, 64))
    clean = render.render(surf, lights, cast_shadows=False)[:, surf.mask]
    factors = light_noise_factors(rng.uniform(0.5, 1.5, (24, 3)))
    sigma = 2e-3
    obs = np.clip(clean + rng.normal(0.0, sigma, clean.shape) * factors[:, None], 0.0, None)
    valid = np.ones(obs.shape, bool)
    atom = black_threshold(obs, valid, factors)
    np.testing.assert_array_equal(atom, np.zeros(24))  # the clipped level alone
    threshold = black_threshold(obs, valid, factors, light_directions=lights)
    # the noise floor (fitted on the lit residuals) stands in for the noise at black; the fit
    # reads it within 10 % here (1.10-1.11 over these seeds)
    ratio = threshold / (BLACK_SIGMAS * sigma * factors)
    assert np.all((ratio > 0.8) & (ratio < 1.3)), ratio
    below = obs <= threshold[:, None]
    assert below[clean == 0].mean() > 0.99  # nearly every shadow
    assert not below[clean > 0.05].any()  # no lit observation


def test_a_noise_free_render_drops_only_its_exact_zeros() -> None:
    rng = np.random.default_rng(4)
    lights = render.random_light_directions(40, rng)
    surf = render.relief_surface((64, 64), seed=1)
    obs = render.render(surf, lights, specular=0.5, roughness=0.15, rng=rng)[:, surf.mask]
    valid = np.ones(obs.shape, bool)
    threshold = black_threshold(obs, valid, light_directions=lights)
    np.testing.assert_array_equal(threshold, np.zeros(40))  # no noise floor: 0 exactly
