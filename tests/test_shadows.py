"""The automatic shadow threshold: the noise at black (negative observations) or the black level."""

from __future__ import annotations

import numpy as np
import pytest

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
    # a handful of negatives (below the minimum count) are not a measurement either
    clipped[0, :50] = -1e-3
    assert black_threshold(clipped, valid) is None
