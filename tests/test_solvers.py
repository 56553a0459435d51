"""Round trips and oracle checks for ps_lab.reconstruct.solve (LS, L1, SBL, R-PCA)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.solver_checks import assert_equals_oracle
from helpers.solver_scenes import corrupt, lights_upper, scene
from helpers.tolerances import assert_within, least_squares, light_conditioning

from ps_lab.errors import DatasetError
from ps_lab.reconstruct import (
    METHODS,
    SolverInputError,
    angular_errors_deg,
    error_summary,
    estimate_noise,
    estimate_noise_model,
    solve,
)
from ps_lab.reconstruct._noise import _noise_residuals, _stable_order, light_noise_factors
from ps_lab.reconstruct._solution import check_inputs as _check_inputs
from ps_lab.reconstruct._tiles import sbl_lambda

# Every test here goes through the numba kernels: run again for a generic CPU (Makefile).
pytestmark = pytest.mark.numerical


@pytest.fixture(scope="module")
def corrupted():
    rng = np.random.default_rng(7)
    lights = lights_upper(24, rng)
    y, normals, _ = scene("relief", (28, 28), lights, rng, specular=0.3)
    y, _ = corrupt(y, rng, 0.2)
    valid = rng.random(y.shape) > 0.08
    return y, lights, valid, normals


@pytest.mark.parametrize("method", METHODS)
def test_vectorised_equals_per_pixel_oracle(corrupted, method):
    y, lights, valid, _ = corrupted
    sol = solve(y, lights, method=method, valid=valid)
    assert_equals_oracle(sol, y, lights, valid, method)
    assert not sol.outliers[~valid].any()


def test_least_squares_exact_on_lambertian_data_with_shadows_dropped():
    rng = np.random.default_rng(1)
    lights = lights_upper(12, rng)
    y, normals, albedo = scene("sphere", (32, 32), lights, rng)
    y = y * 0.7
    sol = solve(y, lights, method="ls", valid=y > 0)
    solvable = (y > 0).sum(axis=0) >= 3
    assert solvable.mean() > 0.9
    # consistent data: the exact solution is the truth, the solve is least squares' rounding
    bound = least_squares(12, light_conditioning(lights, y > 0)[1][solvable])
    assert_within(sol.normals[solvable], normals[solvable], bound)
    truth = 0.7 * albedo[solvable]
    assert_within(sol.albedo[solvable], truth, 0.5 * bound * truth, "albedo")
    assert not sol.normals[~solvable].any()


def test_robust_methods_beat_least_squares_on_sparse_corruptions():
    rng = np.random.default_rng(2)
    lights = lights_upper(40, rng)
    y, normals, _ = scene("relief", (40, 40), lights, rng, specular=0.2)
    y, _ = corrupt(y, rng, 0.0)
    err = {m: error_summary(angular_errors_deg(solve(y, lights, method=m).normals, normals))
           for m in METHODS}
    assert err["sbl"]["mean"] < err["l1"]["mean"] < err["ls"]["mean"]
    assert err["rpca"]["mean"] < err["ls"]["mean"]
    assert err["sbl"]["median"] < 0.5 * err["ls"]["median"]
    assert err["sbl"]["median"] < 1.0


def test_sbl_flags_injected_corruptions_and_recovers_normals():
    rng = np.random.default_rng(3)
    lights = lights_upper(30, rng)
    y, normals, _ = scene("sphere", (30, 30), lights, rng)
    valid = y > 0
    y, hit = corrupt(y, rng, 0.5, where=valid)
    sol = solve(y, lights, method="sbl", valid=valid)
    assert sol.outliers[hit].mean() > 0.95
    assert sol.outliers[valid & ~hit].mean() < 0.02
    assert np.median(angular_errors_deg(sol.normals, normals)) < 0.05


@pytest.mark.parametrize("method", METHODS)
def test_dropped_observations_do_not_matter(method):
    rng = np.random.default_rng(4)
    lights = lights_upper(20, rng)
    y, _, _ = scene("sphere", (20, 20), lights, rng)
    valid = rng.random(y.shape) > 0.2
    garbage = np.where(valid, y, rng.uniform(-5, 50, y.shape))
    garbage[~valid & (rng.random(y.shape) < 0.3)] = np.nan
    a = solve(y, lights, method=method, valid=valid, lam=1e-4) if method == "sbl" else \
        solve(y, lights, method=method, valid=valid)
    b = solve(garbage, lights, method=method, valid=valid, lam=1e-4) if method == "sbl" else \
        solve(garbage, lights, method=method, valid=valid)
    # dropped entries are zeroed (weight 0) before any arithmetic: the same numbers, the same code
    assert np.array_equal(a.normals, b.normals)


@pytest.mark.parametrize("method", ("l1", "sbl"))
def test_tiles_and_threads_give_the_single_tile_result(corrupted, method):
    y, lights, valid, _ = corrupted
    params = {"lam": 1e-4} if method == "sbl" else {}
    ref = solve(y, lights, method=method, valid=valid, threads=1, tile_size=y.shape[1], **params)
    for tile, threads in ((13, 1), (64, 2), (200, 3), (10_000, 4)):
        sol = solve(y, lights, method=method, valid=valid, threads=threads, tile_size=tile, **params)
        # the kernel iterates each pixel on its own row and the shared light table: no tile or
        # thread changes a pixel's arithmetic (and the noise fit's pieces are bit-equal, below)
        assert np.array_equal(sol.normals, ref.normals)
        assert np.array_equal(sol.albedo, ref.albedo)
        assert np.array_equal(sol.iterations, ref.iterations)


def test_noise_fit_in_pieces_and_default_tiles_give_the_one_piece_result():
    rng = np.random.default_rng(5)
    lights = lights_upper(16, rng)
    y, _, _ = scene("relief", (64, 64), lights, rng, specular=0.3)
    y = y + rng.normal(0.0, 0.005, y.shape) + rng.normal(0.0, 0.02, y.shape) * (y > 0)
    obs, lights_, usable = _check_inputs(y, lights, None)
    one = _noise_residuals(obs, lights_, usable)
    for workers in (2, 3):
        pieces = _noise_residuals(obs, lights_, usable, workers=workers)
        assert all(np.array_equal(a, b) for a, b in zip(one, pieces, strict=True))
    ref = solve(y, lights, method="sbl", threads=1)
    sol = solve(y, lights, method="sbl", threads=3)  # 3 pieces, small tiles
    assert sol.params["tile_size"] == ref.params["tile_size"] == 4096  # the bound
    assert sol.params["noise_sigma"] == ref.params["noise_sigma"]
    assert sol.params["noise_floor"] == ref.params["noise_floor"]
    assert np.array_equal(sol.normals, ref.normals)  # same parameters, same per-pixel kernel


def test_stable_order_of_runs_is_the_stable_argsort():
    rng = np.random.default_rng(2)
    for _ in range(50):
        runs = rng.integers(1, 60)
        x = np.repeat(rng.integers(0, 9, runs).astype(float), rng.integers(1, 20, runs))
        assert np.array_equal(_stable_order(x), np.argsort(x, kind="stable"))
    x = rng.random(500)  # no runs: the plain stable argsort
    assert np.array_equal(_stable_order(x), np.argsort(x, kind="stable"))


def test_progress_reports_every_pixel_once(corrupted):
    y, lights, valid, _ = corrupted
    seen = []
    solve(y, lights, method="sbl", valid=valid, tile_size=50, threads=2, progress=seen.append)
    assert sum(seen) == y.shape[1]
    assert len(seen) == -(-y.shape[1] // 50)


def test_auto_lambda_follows_the_noise_level():
    rng = np.random.default_rng(5)
    lights = lights_upper(40, rng)
    y, _, _ = scene("sphere", (40, 40), lights, rng)
    sigmas = []
    for rel in (0.005, 0.02):
        noisy = y + rng.normal(0, rel * np.median(y[y > 0]), y.shape)
        sigmas.append(estimate_noise(noisy, lights, valid=y > 0))
        sol = solve(noisy, lights, method="sbl", valid=y > 0)
        assert sol.params["lambda"] is None  # per pixel, from noise_sigma and noise_floor
        assert sol.params["noise_sigma"] == sigmas[-1]  # the same fit (pieces are bit-equal)
    # relative to each pixel's median observation, so roughly proportional to the noise
    assert 2.5 < sigmas[1] / sigmas[0] < 6


def test_noise_estimate_does_not_count_the_l1_interpolations():
    # an L1 fit interpolates 3 observations per pixel (IRLS to ~1e-7, not 0); with 12 lights
    # they were a quarter of the kept residuals and the 25 % quantile fell to ~0.0007
    for n in (12, 40):
        rng = np.random.default_rng(11)
        lights = lights_upper(n, rng)
        y, _, _ = scene("relief", (48, 48), lights, rng)
        noisy = y * (1.0 + rng.normal(0.0, 0.02, y.shape))  # 2 % of y: ~2 % of the pixel scale
        sigma = estimate_noise(noisy, lights, valid=y > 0)
        assert 0.013 < sigma < 0.025, (n, sigma)


def test_noise_floor_separates_constant_from_proportional_noise():
    rng = np.random.default_rng(11)
    lights = lights_upper(40, rng)
    y, _, _ = scene("relief", (48, 48), lights, rng)  # albedo 0.55-1: pixel scales vary
    y = y * np.linspace(0.2, 1.0, y.shape[1])  # and more so: dark and bright pixels
    constant = y + rng.normal(0.0, 0.01, y.shape)
    proportional = y * (1.0 + rng.normal(0.0, 0.02, y.shape))
    sigma_c, floor_c = estimate_noise_model(constant, lights, valid=y > 0)
    sigma_p, floor_p = estimate_noise_model(proportional, lights, valid=y > 0)
    assert 0.006 < floor_c < 0.015  # the constant noise is found in the observations' units
    assert floor_p < 0.3 * floor_c and 0.01 < sigma_p < 0.03
    lam = sbl_lambda(np.array([0.1, 0.5, 0.0]), 0.02, 0.01)
    assert np.allclose(lam[:, 0], [0.02**2 + 0.1**2, 0.02**2 + 0.02**2, 0.02**2])


def test_light_noise_per_observation_equals_oracle(corrupted):
    y, lights, valid, _ = corrupted
    factors = np.random.default_rng(3).uniform(0.5, 2.0, len(lights))
    sol = solve(y, lights, method="sbl", valid=valid, light_noise=factors, noise_floor=0.02)
    assert sol.params["light_noise"] == pytest.approx(list(factors))
    assert_equals_oracle(sol, y, lights, valid, "sbl")
    plain = solve(y, lights, method="sbl", valid=valid, noise_floor=0.02)
    assert np.abs(plain.normals - sol.normals).max() > 1e-6  # the factors act
    # dimmer lights (divided by a smaller intensity) get a larger share of the floor
    f = light_noise_factors(np.array([[1.0, 1, 1], [2, 2, 2], [1, 1, 1]]))
    assert np.allclose(np.mean(f**2), 1.0) and f[0] == pytest.approx(2 * f[1])
    green = light_noise_factors(np.array([[1.0, 4, 1], [1, 2, 1]]), "g")
    assert np.allclose(green, [0.6325, 1.2649], atol=1e-4)
    with pytest.raises(SolverInputError, match="light_noise"):
        solve(y, lights, method="sbl", light_noise=factors[:3])
    with pytest.raises(SolverInputError, match="finite and positive"):
        light_noise_factors(np.array([[1.0, 1, 1], [0, 0, 0]]))


def test_solution_shapes_and_params(corrupted):
    y, lights, valid, _ = corrupted
    n, p = y.shape
    for method in METHODS:
        sol = solve(y, lights, method=method, valid=valid)
        assert sol.normals.shape == (p, 3) and sol.albedo.shape == (p,)
        assert sol.outliers.shape == (n, p) and sol.outliers.dtype == bool
        assert sol.iterations.shape == (p,)
        assert sol.params["method"] == method
        lengths = np.linalg.norm(sol.normals, axis=1)
        assert np.allclose(lengths[lengths > 0], 1.0)


@pytest.mark.parametrize(
    ("args", "kwargs", "match"),
    [
        ((np.ones((5, 4)), np.eye(3)), {}, "light_directions"),
        ((np.ones((3, 4)), np.array([[0, 0, 1.0], [0, 0, 1], [0, 1, 0]])), {}, "span"),
        ((np.ones((3, 4)), np.array([[np.nan, 0, 1.0], [1, 0, 0], [0, 1, 0]])), {}, "NaN"),
        ((np.ones(4), np.eye(3)), {}, "observations"),
        ((np.ones((3, 4)), np.eye(3)), {"method": "magic"}, "unknown method"),
        ((np.ones((3, 4)), np.eye(3)), {"method": "ls", "lam": 1.0}, "no parameter"),
        ((np.ones((3, 4)), np.eye(3)), {"valid": np.ones((3, 5), bool)}, "valid"),
    ],
)
def test_bad_input_raises_one_clear_error(args, kwargs, match):
    with pytest.raises(SolverInputError, match=match) as info:
        solve(*args, **kwargs)
    assert isinstance(info.value, DatasetError) and isinstance(info.value, ValueError)


def test_metrics():
    a = np.array([[0, 0, 1.0], [1, 0, 0], [0, 0, 2.0], [0, 0, 0]])
    b = np.array([[0, 0, 1.0], [0, 1, 0], [0, np.sin(0.1), np.cos(0.1)], [0, 0, 1]])
    e = angular_errors_deg(a, b)
    assert np.allclose(e, [0.0, 90.0, np.degrees(0.1), 90.0])
    s = error_summary(e)
    assert s["max"] == pytest.approx(90.0) and s["median"] == pytest.approx(np.median(e))


@pytest.mark.parametrize("method", ("l1", "sbl", "rpca"))
def test_given_noise_level_and_threshold_are_used(corrupted, method):
    y, lights, valid, _ = corrupted
    given = {"noise_floor": 0.0} if method == "sbl" else {}
    sol = solve(y, lights, method=method, valid=valid, noise_sigma=0.03, **given)
    assert sol.params["noise_sigma"] == 0.03
    assert sol.params["outlier_threshold"] == pytest.approx(0.09)
    if method == "sbl":
        assert sol.params["lambda"] is None and sol.params["noise_floor"] == 0.0
        same = solve(y, lights, method=method, valid=valid, lam=0.03**2)
        # lam = max(0.03^2 + 0, 1e-6) per pixel is 0.03^2, tol and threshold come from
        # sqrt(0.03^2) == 0.03: the kernel gets the same numbers
        assert np.array_equal(same.normals, sol.normals)
    fixed = solve(y, lights, method=method, valid=valid, outlier_threshold=0.2)
    assert fixed.params["outlier_threshold"] == 0.2
