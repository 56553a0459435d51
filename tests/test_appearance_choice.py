"""The interpolating models (bln, gp) and the appearance model chosen by cross-validation."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ps_lab.appearance.choice import (
    choose_model,
    loo_weights,
    predict_weights,
)
from ps_lab.appearance.fit import fit_appearance
from ps_lab.appearance.models import evaluate_appearance, hsh_basis, ptm_basis
from ps_lab.appearance.smoothers import bln_weights, gp_solve, gp_weights, grid_nodes
from ps_lab.appearance.store import read_appearance, write_appearance
from ps_lab.errors import DatasetError
from ps_lab.io.encoding import linear_to_srgb, srgb_to_linear


@pytest.fixture
def rng():
    return np.random.default_rng(38)


def _lights(rng, n, min_z=0.25):
    d = rng.normal(size=(8 * n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d[:, 2] > min_z][:n]
    assert len(d) == n
    return d


def test_bln_reproduces_a_function_bilinear_in_the_light_plane(rng):
    # Training lights at the grid's nodes: with a narrow Gaussian each node takes its own
    # light's value, and the bilinear interpolation of a bilinear function is the function.
    r = 9
    nodes = grid_nodes(r)
    inside = nodes[:, 0] ** 2 + nodes[:, 1] ** 2 <= 0.95
    lights = nodes[inside]
    a, b, c, d = rng.normal(size=4)

    def f(q):
        return a + b * q[..., 0] + c * q[..., 1] + d * q[..., 0] * q[..., 1]

    # query lights in the cells whose four corners are all training lights
    step = 2.0 / (r - 1)
    cells = np.array([(i, j) for i in range(r - 1) for j in range(r - 1)
                      if all(inside[(j + dj) * r + i + di] for di in (0, 1) for dj in (0, 1))])
    pick = cells[rng.integers(0, len(cells), 50)]
    xy = -1.0 + (pick + rng.uniform(0, 1, (50, 2))) * step
    query = np.column_stack([xy, np.sqrt(1.0 - np.sum(xy**2, axis=1))])
    w = bln_weights(query, lights, sigma=0.01, resolution=r)
    assert np.allclose(w.sum(axis=1), 1.0, atol=1e-12)
    # the nearest-node weight is exp(−(step/σ)²) ≈ e^-62 away from 1: exact to ~1e-12
    assert np.allclose(w @ f(lights), f(query), atol=1e-9)


@pytest.mark.parametrize("model,params", [
    ("ptm", {}),
    ("hsh3", {}),
    ("gp", {"sigma": 0.4, "ridge": 0.01}),
    ("gp", {"sigma": 1.2, "ridge": 1e-3}),
    ("gp", {"sigma": 2.0, "ridge": 1e-3}),  # the grid's ends (issue 38's wider grid)
    ("gp", {"sigma": 0.1, "ridge": 3.0}),
    ("rbf", {"sigma": 0.3}),
    ("bln", {"sigma": 0.2, "resolution": 8}),
])
def test_leave_one_out_closed_form_equals_explicit_refits(rng, model, params):
    lights = _lights(rng, 40)
    y = rng.normal(size=(40, 7))
    closed = loo_weights(model, params, lights) @ y
    explicit = np.empty_like(y)
    for i in range(40):
        keep = np.arange(40) != i
        explicit[i] = predict_weights(model, params, lights[keep], lights[i:i + 1])[0] @ y[keep]
    # gp's system has condition ~1e6 at σ 1.2: rounding of that order times 1e-16
    assert np.allclose(closed, explicit, atol=1e-7 * np.abs(y).max()), np.abs(closed - explicit).max()


def test_gp_weights_interpolate_the_training_lights_without_ridge(rng):
    lights = _lights(rng, 30)
    y = rng.normal(size=30)
    solve = gp_solve(lights, 0.5, 1e-10)
    assert np.allclose(gp_weights(lights, lights, 0.5, solve) @ y, y, atol=1e-5)


def _obs_from(model, rng, lights, pixels=300, noise=2e-3):
    basis = ptm_basis(lights) if model == "ptm" else hsh_basis(lights, 3)
    coeffs = rng.normal(size=(pixels, 3, basis.shape[1])) * 0.05
    coeffs[..., 0] += 0.5 if model == "ptm" else 1.2
    value = np.einsum("nk,pck->npc", basis, coeffs)
    return value + rng.normal(scale=noise, size=value.shape)


@pytest.mark.parametrize("truth", ["ptm", "hsh3"])
def test_the_choice_picks_the_generating_model_and_space(rng, truth):
    lights = _lights(rng, 48)
    encoded = np.clip(_obs_from(truth, rng, lights, pixels=100), 0.0, 1.0)
    linear = choose_model(encoded, lights)
    assert (linear.model, linear.space) == (truth, "linear"), linear.table[:3]
    srgb = choose_model(srgb_to_linear(encoded).astype(np.float64), lights)
    assert (srgb.model, srgb.space) == (truth, "srgb")
    assert srgb.score == max(row["loo_psnr"] for row in srgb.table)


def test_the_choice_prefers_interpolation_for_a_sharp_highlight(rng):
    lights = _lights(rng, 60)
    axis = np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93])
    lobe = np.exp(-np.sum((lights - axis) ** 2, axis=1) / 0.2**2)  # narrower than PTM's terms
    obs = 0.2 + 0.6 * lobe[:, None, None] * rng.uniform(0.5, 1.0, (1, 80, 3))
    choice = choose_model(obs, lights)
    assert choice.model in ("rbf", "bln", "gp"), choice.model
    best_poly = max(r["loo_psnr"] for r in choice.table if r["model"] in ("ptm", "hsh3"))
    assert choice.score > best_poly + 3.0


@pytest.mark.parametrize("model", ["auto", "bln", "gp"])
def test_chosen_model_round_trips_through_the_file(rng, tmp_path, model):
    lights = _lights(rng, 36)
    mask = np.zeros((12, 10), bool)
    mask[1:11, 2:9] = True
    obs = np.clip(_obs_from("hsh3", rng, lights, pixels=int(mask.sum())), 0, 1)
    fitted = fit_appearance(model, obs, lights, mask)
    assert fitted.model in ("ptm", "hsh3", "rbf", "bln", "gp")
    assert fitted.meta["space"] in ("linear", "srgb")
    assert fitted.meta["choice"]["requested"] == model
    write_appearance(tmp_path, fitted)
    back = read_appearance(tmp_path)
    light = _lights(rng, 1)[0]
    blank = np.zeros((12, 10, 3))
    a = evaluate_appearance(fitted, light, blank, blank)
    assert np.array_equal(a, evaluate_appearance(back, light, blank, blank))
    assert json.dumps(back.meta)  # JSON-safe
    # fitted at the training lights it reproduces the (smooth) data
    at = evaluate_appearance(back, lights[0], blank, blank)[mask]
    assert np.sqrt(np.mean((at - obs[0]) ** 2)) < 0.02


def test_srgb_fit_space_decodes_on_evaluation(rng, tmp_path):
    lights = _lights(rng, 30)
    mask = np.ones((4, 5), bool)
    encoded = np.clip(_obs_from("ptm", rng, lights, pixels=20, noise=0.0), 0, 1)
    fitted = fit_appearance("auto", srgb_to_linear(encoded).astype(np.float64), lights, mask)
    assert (fitted.model, fitted.meta["space"]) == ("ptm", "srgb")
    blank = np.zeros((4, 5, 3))
    picture = evaluate_appearance(fitted, lights[5], blank, blank)
    assert np.allclose(linear_to_srgb(picture.reshape(-1, 3)), encoded[5], atol=1e-4)


def test_file_with_an_unknown_fit_space_is_refused(rng, tmp_path):
    lights = _lights(rng, 20)
    mask = np.ones((3, 3), bool)
    fitted = fit_appearance("gp", np.clip(_obs_from("ptm", rng, lights, pixels=9), 0, 1),
                            lights, mask)
    fitted.meta["space"] = "log"
    write_appearance(tmp_path, fitted)
    with pytest.raises(DatasetError, match="fit space"):
        read_appearance(tmp_path)


def test_reconstruct_default_is_the_chosen_model_and_relights_as_recorded(tmp_path, rng):
    import cv2
    from typer.testing import CliRunner

    from ps_lab import render
    from ps_lab.cli import app
    from ps_lab.io.images import read_exr

    data = tmp_path / "data"
    data.mkdir()
    surface = render.sphere_surface((20, 20), albedo=0.6)
    lights = _lights(rng, 24, min_z=0.5)
    images = render.render(surface, lights, specular=0.3, cast_shadows=False)
    for i, image in enumerate(images):
        counts = np.clip(np.rint(image / images.max() * 0.9 * 65535), 0, 65535)
        assert cv2.imwrite(str(data / f"{i:03d}.png"), counts.astype(np.uint16))
    np.savetxt(data / "light_directions.txt", lights)
    cv2.imwrite(str(data / "mask.png"), surface.mask.astype(np.uint8) * 255)
    runner = CliRunner()
    out = tmp_path / "result"
    done = runner.invoke(app, ["reconstruct", str(data), "--method", "ls", "--out", str(out)])
    assert done.exit_code == 0, done.output
    recorded = json.loads((out / "metrics.json").read_text())["appearance"]
    fitted = read_appearance(out)
    assert recorded["model"] == fitted.model == recorded["choice"]["model"]
    assert recorded["choice"]["requested"] == "auto"
    assert "ps/linear" in recorded["choice"]["best_per_model"]  # ps was a candidate
    assert recorded["choice"]["loo_psnr"] == max(recorded["choice"]["best_per_model"].values())
    light = np.array([0.2, 0.3, 0.9]) / np.linalg.norm([0.2, 0.3, 0.9])
    relit = runner.invoke(app, ["relight", str(out), "--light", "0.2,0.3,0.9",
                                "--out", str(tmp_path / "pic.exr")])
    assert relit.exit_code == 0, relit.output
    expected = evaluate_appearance(fitted, light, np.load(out / "normals.npy"),
                                   np.load(out / "albedo.npy"))
    picture = read_exr(tmp_path / "pic.exr")
    inside = surface.mask
    assert np.allclose(picture[inside], np.broadcast_to(expected, picture.shape)[inside],
                       atol=1e-6)


@pytest.mark.parametrize("n", [6, 8, 9])
def test_a_basis_that_interpolates_every_light_is_not_a_candidate(rng, n):
    # hsh3 has 9 terms: on 8 lights (and 9, general position) every light has leverage 1, its
    # leave-one-out prediction is undefined (the closed form divided by ~0 and predicted each
    # light from itself: a perfect score); gp's PTM trend (6 terms) interpolates 6 lights
    lights = _lights(rng, n)
    assert loo_weights("hsh3", {}, lights) is None
    sample = rng.uniform(0.1, 0.9, (n, 64, 3))
    choice = choose_model(sample, lights)
    assert choice.model != "hsh3"
    assert all(row["model"] != "hsh3" for row in choice.table)
    if n == 6:
        with pytest.raises(DatasetError, match="cannot cross-validate"):
            choose_model(sample, lights, ("gp",))
