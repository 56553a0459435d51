"""The default's per-pixel model choice (leave-one-out), the one albedo scale, shadows as atoms.

docs/solvers.md ("The default `auto`") gives the argument; these are seeded round trips.
"""

from __future__ import annotations

import numpy as np
import pytest

from ps_lab.reconstruct import angular_errors_deg, solve
from ps_lab.reconstruct._pl_model import _loo_lambertian, _loo_pl
from ps_lab.reconstruct._shadows import black_threshold
from ps_lab.reconstruct._solution import lambertian_albedo
from ps_lab.render import random_light_directions, relief_surface, render, sphere_surface

from helpers.tolerances import PL_NORMALS

METHODS = ("ls", "l1", "sbl", "plls", "plsbl", "auto", "rpca")


def _scene(shape=(32, 32), n_lights=40, seed=0, sphere=True):
    rng = np.random.default_rng(seed)
    lights = random_light_directions(n_lights, rng, max_zenith_deg=60.0)
    surface = sphere_surface(shape) if sphere else relief_surface(shape, seed=seed)
    obs = render(surface, lights, rng=rng)[:, surface.mask]
    return obs, lights, surface.normals[surface.mask], rng


def test_closed_form_leave_one_out_equals_refitting_without_each_observation():
    rng = np.random.default_rng(0)
    n, u = 20, 5
    a = rng.normal(size=(n, u))
    y = a @ rng.normal(size=u) + 0.1 * rng.normal(size=n)
    kv = np.where(rng.random(n) < 0.8, rng.uniform(0.5, 2.0, n), 0.0)
    # Lambertian: u = 3, the light table's rows (a a^T, a), ridge 1e-6
    tab = np.concatenate([np.stack([a[:, 0] ** 2, a[:, 1] ** 2, a[:, 2] ** 2, a[:, 0] * a[:, 1],
                                    a[:, 0] * a[:, 2], a[:, 1] * a[:, 2]]), a[:, :3].T])
    out = np.zeros(n)
    score = _loo_lambertian(y, kv, kv, np.ascontiguousarray(tab), n, 1e-6, out)
    brute = 0.0
    for i in np.flatnonzero(kv > 0):
        keep = (kv > 0) & (np.arange(n) != i)
        w = kv[keep]
        m = (a[keep, :3] * w[:, None]).T @ a[keep, :3] + 1e-6 * np.eye(3)
        x = np.linalg.solve(m, (a[keep, :3] * w[:, None]).T @ y[keep])
        brute += kv[i] * (y[i] - a[i, :3] @ x) ** 2
    # exact in real arithmetic (Sherman-Morrison); the 3x3 cofactor solve rounds at ~1e-12 here
    assert score == pytest.approx(brute, rel=1e-9)
    assert out.sum() == pytest.approx(score, rel=1e-12)
    # PL: u unknowns, prior precision P with right-hand side, fit weights kv / s^2 (noise of
    # y_i through the slope s_i), scored residual / s
    slope = rng.uniform(0.3, 1.5, n)
    prior = np.diag(rng.uniform(0.1, 1.0, u))
    prior_rhs = rng.normal(size=u)
    scratch = [np.zeros((u, u)) for _ in range(3)]
    score = _loo_pl(y, kv / slope**2, kv, slope, np.ascontiguousarray(a.T), n, u, prior,
                    prior_rhs, *scratch, np.zeros(u), out)
    brute = 0.0
    for i in np.flatnonzero(kv > 0):
        keep = (kv > 0) & (np.arange(n) != i)
        w = kv[keep] / slope[keep] ** 2
        m = (a[keep] * w[:, None]).T @ a[keep] + prior
        x = np.linalg.solve(m, (a[keep] * w[:, None]).T @ y[keep] + prior_rhs)
        brute += kv[i] * ((y[i] - a[i] @ x) / slope[i]) ** 2
    assert score == pytest.approx(brute, rel=1e-9)


def test_the_default_is_sbl_on_noisy_lambertian_data():
    # PL-SBL nests the Lambertian model: on Lambertian data it predicts as well, and where the
    # default keeps SBL (the gain under one standard error) it is SBL, bit for bit; where it
    # takes PL the two normals are equally good (measured: auto 0.0905, SBL 0.0898 deg; 43 % PL)
    obs, lights, normals, rng = _scene(seed=2)
    noisy = obs + rng.normal(0.0, 0.003, obs.shape)
    valid = noisy > 0.01
    auto = solve(noisy, lights, method="auto", valid=valid)
    sbl = solve(noisy, lights, method="sbl", valid=valid)
    counts = auto.params["pixels_per_segments"]
    # the same SBL, compiled into another kernel: fastmath may reassociate its sums differently,
    # and a pixel can stop one iteration apart at the tolerance (measured: 359 of 368 equal to
    # 1e-9 deg, all 368 within 1e-5)
    # (the default's last choice may take least squares on a few of its one-segment pixels)
    same = angular_errors_deg(auto.normals, sbl.normals) < 1e-5
    models = auto.params["pixels_per_model"]
    assert same.sum() >= models["sbl"] > 0.5 * sum(counts.values())
    assert models["sbl"] + models["ls"] == counts.get(1, 0)
    err_auto = angular_errors_deg(auto.normals, normals).mean()
    err_sbl = angular_errors_deg(sbl.normals, normals).mean()
    assert err_auto < 1.03 * err_sbl
    # a strong response curve (sqrt) is predicted better by the PL model nearly everywhere
    curved = np.sqrt(np.clip(noisy, 0.0, None))
    bent = solve(curved, lights, method="auto", valid=valid)
    counts = bent.params["pixels_per_segments"]
    assert counts.get(3, 0) > 0.8 * sum(counts.values()), counts


def test_every_method_has_the_lambertian_albedo_on_lambertian_data():
    obs, lights, _, rng = _scene(seed=3, sphere=False)
    rho = rng.uniform(0.3, 0.9, obs.shape[1])
    noisy = obs * rho + rng.normal(0.0, 0.002, obs.shape)
    valid = noisy > 0.01
    sols = {m: solve(noisy, lights, method=m, valid=valid) for m in METHODS}
    ref = sols["sbl"].albedo
    solved = ref > 0
    for method, sol in sols.items():
        assert sol.params["albedo"] == "lambertian-equivalent"
        # the bound: within 1 % of SBL's, every pixel (measured: at most 0.72 %, PL-LS);
        # R-PCA's normals differ from SBL's on a few pixels (its low-rank fit), so its albedo
        # there too: within 1 % on the median pixel (measured 0.06 %)
        off = np.abs(sol.albedo[solved] / ref[solved] - 1.0)
        assert (np.median(off) if method == "rpca" else off.max()) < 0.01, method
    # the definition: least-squares scale of max(n.l, 0) on the inliers
    sol = sols["plsbl"]
    again = lambertian_albedo(sol.normals, valid & ~sol.outliers, noisy, lights)
    np.testing.assert_allclose(again[solved], sol.albedo[solved], rtol=1e-9)


def test_exact_zero_shadows_are_dropped_when_sparse_noise_goes_negative():
    # a float render with exact-zero shadows and sparse additive noise (the authors' synthetic
    # data): ~1 % of the observations negative, yet black is the exact 0, not 3 sigma of them
    rng = np.random.default_rng(5)
    lights = random_light_directions(40, rng)
    surf = relief_surface((48, 48), seed=1)
    clean = render(surf, lights, rng=rng)[:, surf.mask]
    hit = rng.random(clean.shape) < 0.15
    obs = np.where(hit, clean + rng.normal(0.0, 0.1 * np.median(clean[clean > 0]), clean.shape),
                   clean)
    assert (obs < 0).mean() > 0.005 and (obs == 0).mean() > 0.05
    threshold = black_threshold(obs, np.ones(obs.shape, bool), light_directions=lights)
    assert threshold is not None
    kept = obs > threshold[:, None]
    assert not np.any(kept & (obs == 0))  # every exact zero is a shadow
    assert not np.any(kept & (obs < 0))
    # and nothing lit is lost beyond the noise that fell below 0 (float: no noise floor)
    lost = ~kept & (clean > 0)
    assert lost.sum() <= (hit & (clean > 0) & (obs <= threshold[:, None])).sum()


def test_dark_subtracted_quantised_noise_has_no_atom():
    # integer data minus a dark level: the noise at black is spread over many repeated values;
    # none of them is a pile-up, so the negative observations' 3 sigma rule applies
    rng = np.random.default_rng(6)
    n, m = 20, 3000
    signal = np.where(rng.random((n, m)) < 0.3, 0.0, rng.uniform(20, 200, (n, m)))
    dn = np.round(signal + rng.normal(0.0, 3.0, (n, m)))
    threshold = black_threshold(dn / 1000.0, np.ones((n, m), bool))
    # 3 sigma of the noise at black, sigma = 3 DN (rounding adds 1/12 DN^2)
    sigma = np.sqrt(9.0 + 1.0 / 12.0) / 1000.0
    np.testing.assert_allclose(threshold, 3.0 * sigma, rtol=0.1)


def test_score_gate_fails_at_its_false_alarm_rate_on_lambertian_data():
    """Known additive noise (sigma of each pixel's scale): the gate's chi^2 test fails on ~1 %."""
    from ps_lab.reconstruct import _pl_kernels, _tiles

    fails, tested = 0, 0
    for seed in (0, 1):
        rng = np.random.default_rng(seed)
        lights = random_light_directions(40, rng, max_zenith_deg=60.0)
        surface = relief_surface((48, 48), seed=seed)
        clean = render(surface, lights, rng=rng)[:, surface.mask]
        sigma = 0.05
        scale = np.array([np.median(c[c > 0]) for c in clean.T])
        obs = clean + sigma * scale * rng.standard_normal(clean.shape)
        y, w, _, ok = _tiles._prepare_tile(obs, clean > 0, lights, 0, obs.shape[1])
        res = _pl_kernels.pl_tile(y[ok], w[ok], lights, segments=3, lam=sigma**2, choose=True,
                                  lam_test=sigma**2, stage="sbl", outlier_threshold=3 * sigma)
        gate = res.gate[np.isfinite(res.gate)]
        fails += int(np.sum(gate > 0))
        tested += gate.size
    # binomial(2900, 0.01): 29 +- 5.4; the window is +-3 standard deviations and more
    assert 0.003 < fails / tested < 0.02


def test_default_is_sbl_on_noisy_lambertian_data():
    """No pixel of a Lambertian render with noise fails the gate: the default is SBL, exactly."""
    obs, lights, truth, rng = _scene(shape=(40, 40), n_lights=40, seed=3, sphere=False)
    valid = obs > 0  # the shadows, known
    obs = obs + 0.01 * rng.standard_normal(obs.shape) * obs.max()
    auto = solve(obs, lights, valid=valid, method="auto", threads=1)
    sbl = solve(obs, lights, valid=valid, method="sbl", threads=1)
    assert auto.params["pixels_per_segments"] == {1: obs.shape[1]}
    # the same SBL, summed over the lights in another kernel (rounding: PL_NORMALS)
    np.testing.assert_allclose(auto.normals, sbl.normals, rtol=0, atol=PL_NORMALS)


def _lambertian_pixels(rng, m, lights, sigma):
    normals = rng.normal(size=(m, 3))
    normals[:, 2] = np.abs(normals[:, 2]) + 1.5
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    clean = normals @ lights.T
    return normals, clean, clean + rng.normal(0.0, sigma, clean.shape)


def test_last_choice_keeps_sbl_where_outliers_exist_and_takes_ls_where_sbl_discards():
    """The truncated left-out rule (_auto.last_choice) on seeded pixels with a known answer."""
    from ps_lab.reconstruct._auto import last_choice

    rng = np.random.default_rng(11)
    lights = random_light_directions(40, rng, max_zenith_deg=60.0)
    m, sigma = 400, 0.01
    normals, clean, y = _lambertian_pixels(rng, m, lights, sigma)
    w = np.ones_like(y)
    lam = np.full((m, 1), sigma**2)
    x_ls = np.linalg.lstsq(lights, y.T, rcond=None)[0].T
    # sparse gross outliers (speculars): SBL's weights d drop them; LS is pulled by them
    hit = rng.random(y.shape) < 0.1
    bad = y + hit * rng.uniform(0.5, 1.0, y.shape)
    d = np.where(hit, 1e-6, 1.0 / sigma**2)
    x_sbl = np.stack([np.linalg.lstsq(lights[~h], bad[p, ~h], rcond=None)[0]
                      for p, h in enumerate(hit)])
    model, x = last_choice(bad, w, lights, lam, x_sbl, d, x_sbl, np.zeros(m, bool))
    assert (model == 1).mean() > 0.95  # measured 1.0
    np.testing.assert_allclose(x[model == 1], x_sbl[model == 1])
    # clean Lambertian pixels, but an SBL that flagged a third of good observations (a bad
    # noise level): least squares predicts them, and is taken
    drop = rng.random(y.shape) < 0.33
    d = np.where(drop, 1e-6, 1.0 / sigma**2)
    x_sub = np.stack([np.linalg.lstsq(lights[~h], y[p, ~h], rcond=None)[0]
                      for p, h in enumerate(drop)])
    model, x = last_choice(y, w, lights, lam, x_sub, d, x_sub, np.zeros(m, bool))
    # a subset fit predicts its left-out third about as well (unbiased): the one-standard-error
    # rule keeps SBL on many; where LS is taken it is least squares exactly
    ls = model == 0
    np.testing.assert_allclose(x[ls], x_ls[ls], atol=1e-12)
    err = angular_errors_deg(x, normals).mean()
    bound = max(angular_errors_deg(x_ls, normals).mean(),
                angular_errors_deg(x_sub, normals).mean())
    assert err <= bound  # never worse than the worse part; in practice near the better
    # an SBL that kept a quarter of the observations (a far too small noise level): its fit is
    # three times noisier, and least squares is taken nearly everywhere
    few = np.where(rng.random(y.shape) < 0.75, 1e-6, 1.0 / sigma**2)
    model, _ = last_choice(y, w, lights, lam, x_sub, few, x_sub, np.zeros(m, bool))
    assert (model == 0).mean() > 0.5, (model == 0).mean()


def test_pl_sbl_is_not_used_with_lights_in_rings():
    """A dome of rings of equal elevation (light_rings): the default keeps SBL and LS."""
    from ps_lab.reconstruct._auto import light_rings

    rng = np.random.default_rng(13)
    rings = [(e, k) for e, k in ((10.0, 18), (30.0, 12), (50.0, 10), (70.0, 8))]
    dome = np.concatenate([
        np.stack([np.cos(np.radians(e)) * np.cos(a), np.cos(np.radians(e)) * np.sin(a),
                  np.full(k, np.sin(np.radians(e)))], axis=1)
        for e, k in rings for a in [np.linspace(0, 2 * np.pi, k, endpoint=False)]])
    assert light_rings(dome) == 1.0
    scattered = random_light_directions(48, rng, max_zenith_deg=60.0)
    assert light_rings(scattered) == 0.0
    surface = relief_surface((24, 24), seed=3)
    obs = np.sqrt(np.clip(render(surface, dome, rng=rng), 0.0, None))[:, surface.mask]
    sol = solve(obs, dome, method="auto", valid=obs > 0.01)
    assert sol.params["pixels_per_model"]["plsbl"] == 0
    assert sol.params["lights_in_rings"] == 1.0
    # the same bent response under scattered lights: PL-SBL is taken (the test above)


def test_the_default_is_not_worse_than_the_better_of_ls_and_sbl_on_a_glossy_sphere():
    """The default against LS and SBL on a seeded specular render (issue 42's bound: the better
    of the two, + 5 % + 0.1 deg: the choice is per pixel, by the noise, not by the truth).

    Not against PL-SBL: measured auto 0.65, SBL 0.83, PL-SBL 0.33 deg (the PL stage keeps SBL
    on pixels where PL would be better; open in issue 42)."""
    rng = np.random.default_rng(12)
    lights = random_light_directions(40, rng, max_zenith_deg=60.0)
    surface = sphere_surface((40, 40))
    obs = render(surface, lights, rng=rng, specular=0.5, roughness=0.2, noise_sigma=0.003,
                 noise_fraction=1.0)[:, surface.mask]
    truth = surface.normals[surface.mask]
    valid = obs > 0.01
    errs = {m: angular_errors_deg(solve(obs, lights, method=m, valid=valid).normals,
                                  truth).mean() for m in ("auto", "ls", "sbl", "plsbl")}
    best = min(errs["ls"], errs["sbl"])
    assert errs["auto"] <= 1.05 * best + 0.1, errs


def test_the_last_choice_equals_its_oracle_where_least_squares_is_taken():
    """The default against the per-pixel oracle (helpers/solver_oracles.py: each model refitted
    without each observation) on a scene where the last choice takes least squares: Lambertian
    data with a noise variance given larger than the noise (measured: LS on 61 of 376 pixels)."""
    from helpers.solver_checks import assert_equals_oracle

    obs, lights, _, rng = _scene(shape=(24, 24), n_lights=20, seed=1)
    noisy = obs + rng.normal(0.0, 0.002, obs.shape)
    valid = noisy > 0.005
    sol = solve(noisy, lights, method="auto", valid=valid, lam=1e-4)
    assert sol.params["pixels_per_model"]["ls"] > 10
    assert_equals_oracle(sol, noisy, lights, valid, "auto")
