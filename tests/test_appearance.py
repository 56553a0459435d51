"""Appearance models: bases, fits, appearance.npz, `reconstruct --appearance`, `ps-lab relight`."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from helpers.tolerances import EPS, EPS32
from ps_lab import render
from ps_lab.appearance.blocks import (
    PS_RIDGE,
    fit_linear,
    fit_ps,
    fit_rbf,
    fit_visibility,
    rbf_setup,
)
from ps_lab.appearance.fit import fit_appearance
from ps_lab.appearance.models import (
    APPEARANCE_FILE,
    PS_TERMS,
    Appearance,
    appearance_basis,
    coefficients_per_pixel,
    evaluate_appearance,
    hsh_basis,
    is_direct,
    ps_basis,
    ps_term,
    ps_visibility,
    ptm_basis,
    rbf_weights,
)
from ps_lab.appearance.store import read_appearance, write_appearance
from ps_lab.bench import relight as bench_relight
from ps_lab.cli import app
from ps_lab.errors import DatasetError
from ps_lab.io.images import read_exr
from ps_lab.io.result import RESULT_FORMAT

runner = CliRunner()


def hemisphere(n: int, rng: np.random.Generator, max_zenith_deg: float = 80.0) -> np.ndarray:
    """``n`` random unit directions with zenith below ``max_zenith_deg``."""
    z = rng.uniform(math.cos(math.radians(max_zenith_deg)), 1.0, n)
    phi = rng.uniform(0, 2 * math.pi, n)
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


# --- bases -------------------------------------------------------------------------------------


def test_ptm_terms_in_relightlab_order():
    d = np.array([[0.3, -0.4, math.sqrt(1 - 0.25)]])
    assert np.allclose(ptm_basis(d), [[1, 0.3, -0.4, 0.09, -0.12, 0.16]], atol=4 * EPS)


def test_hsh_closed_forms_at_the_pole_and_the_horizon():
    pole = hsh_basis(np.array([0.0, 0.0, 1.0]))
    c = 1.0  # cos(theta): s = sqrt(c - c^2) = 0
    expected = [1 / math.sqrt(2 * math.pi), 0, math.sqrt(3 / (2 * math.pi)) * (2 * c - 1), 0, 0, 0,
                math.sqrt(5 / (2 * math.pi)) * (6 * c * c - 6 * c + 1), 0, 0]
    assert np.allclose(pole, expected, atol=8 * EPS)
    # at the horizon (c = 0, phi = 90 deg): h3 = 0, h2 = -sqrt(3/2pi), h6 = sqrt(5/2pi)
    side = hsh_basis(np.array([0.0, 1.0, 0.0]))
    assert side[2] == pytest.approx(-math.sqrt(3 / (2 * math.pi)))
    assert side[6] == pytest.approx(math.sqrt(5 / (2 * math.pi)))
    assert hsh_basis(np.array([0.0, 0.0, 1.0]), 2).shape == (4,)


def test_hsh_is_orthonormal_on_the_hemisphere():
    # Gauss-Legendre in cos(theta) on [0, 1] x uniform phi: exact for these polynomials in
    # (c, s cos phi, s sin phi) up to the quadrature's degree; the s = sqrt(c - c^2) factors make
    # products with one s^k of odd k non-polynomial in c, and those vanish by the phi integral.
    nodes, weights = np.polynomial.legendre.leggauss(64)
    c = (nodes + 1) / 2
    w_c = weights / 2
    phi = np.arange(128) * 2 * math.pi / 128
    cc, pp = np.meshgrid(c, phi, indexing="ij")
    s = np.sqrt(1 - cc**2)
    d = np.stack([s * np.cos(pp), s * np.sin(pp), cc], axis=-1)
    h = hsh_basis(d)  # (64, 128, 9)
    w = (w_c[:, None] * np.full(phi.shape, 2 * math.pi / 128)[None])[..., None, None]
    gram = np.sum(h[..., :, None] * h[..., None, :] * w, axis=(0, 1))
    # The cos(theta) - cos^2 factors are polynomials in c of degree <= 4 once squared, integrated
    # exactly by 64 nodes; the bound is the sums' rounding.
    assert np.allclose(gram, np.eye(9), atol=1e-12)


def test_ps_terms_closed_forms():
    normal = np.array([[0.0, 0.0, 1.0]])
    light = np.array([[0.6, 0.0, 0.8], [0.0, 0.0, -1.0]])
    b = ps_basis(light, normal, ("lx", "ly", "lz", "ambient", "lobe:4", "lobe:32", "lambert"))
    half = np.array([0.6, 0.0, 1.8]) / np.linalg.norm([0.6, 0.0, 1.8])
    lit = [0.6, 0.0, 0.8, 1.0, half[2] ** 4, half[2] ** 32, 0.8]
    assert np.allclose(b[0, 0], lit, atol=8 * EPS)
    # a light behind the surface: every term but the ambient is zero
    assert np.allclose(b[1, 0], [0, 0, 0, 1, 0, 0, 0])


def test_rbf_weights_are_relightlabs_normalised_gaussian():
    lights = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    w = rbf_weights(np.array([0.0, 0.0, 1.0]), lights, 0.5)
    d2 = 0.36 + 0.04
    expected = np.array([1.0, math.exp(-d2 / 0.25)])
    assert np.allclose(w, expected / expected.sum(), atol=4 * EPS)


# --- fits: data in each model's span is recovered ----------------------------------------------


@pytest.mark.parametrize("model", ["ptm", "hsh2", "hsh3"])
def test_linear_fit_round_trip(model, rng):
    lights = hemisphere(40, rng)
    basis = appearance_basis(model, lights)
    truth = rng.normal(size=(30, 3, basis.shape[1]))
    obs = np.einsum("nk,pck->npc", basis, truth)
    coeffs = fit_linear(model, obs, lights)
    # Least squares of exact data: cond(B)^2 n eps from the solve, plus float32 storage.
    cond = np.linalg.cond(basis)
    bound = 12 * 40 * EPS * cond**2 * np.abs(truth).max() + EPS32 * np.abs(truth).max()
    assert np.max(np.abs(coeffs - truth)) <= bound
    # relit images under a new light match the model's own prediction
    mask = np.zeros((5, 6), bool)
    mask.flat[:30] = True
    app = fit_appearance(model, obs, lights, mask)
    new = hemisphere(1, rng)[0]
    picture = evaluate_appearance(app, new, np.zeros((5, 6, 3)), np.zeros((5, 6)))
    expected = np.einsum("k,pck->pc", appearance_basis(model, new), truth)
    assert np.allclose(picture[mask], expected, atol=50 * bound * basis.shape[1])


def test_ps_fit_round_trip(rng):
    lights = hemisphere(48, rng, 60)
    normals = hemisphere(40, rng, 40)
    albedo = rng.uniform(0.2, 0.9, (40, 3))
    truth = rng.normal(scale=0.1, size=(40, 3, len(PS_TERMS)))
    basis = ps_basis(lights, normals, PS_TERMS)  # (n, P, K)
    shade = np.maximum(lights @ normals.T, 0)
    obs = albedo[None] * shade[..., None] + np.einsum("npk,pck->npc", basis, truth)
    coeffs = fit_ps(obs, lights, normals, albedo, ridge=0.0)
    cond = max(np.linalg.cond(basis[:, p]) for p in range(40))
    bound = 12 * 48 * EPS * cond**2 + EPS32
    assert np.max(np.abs(coeffs - truth)) <= bound * np.abs(truth).max() * 10
    # and relighting through the file format reproduces the model
    normal_image = normals.reshape(5, 8, 3)
    app = Appearance("ps", coeffs.reshape(5, 8, 3, -1),
                     {"basis": "ps", "K": len(PS_TERMS), "terms": list(PS_TERMS)})
    new = hemisphere(1, rng, 60)[0]
    picture = evaluate_appearance(app, new, normal_image, albedo.reshape(5, 8, 3))
    expected = albedo * np.maximum(normals @ new, 0)[:, None] + np.einsum(
        "pk,pck->pc", ps_basis(new[None], normals, PS_TERMS)[0], truth)
    assert np.allclose(picture.reshape(40, 3), expected, atol=1e-5)


def test_ps_fit_with_a_visibility_round_trip(rng):
    # Data exactly in the model's span for a given visibility: V·(ρ·max(n·l, 0) + direct terms)
    # + ambient; the coefficients are recovered and the file relights as the formula says.
    lights = hemisphere(48, rng, 60)
    normals = hemisphere(40, rng, 40)
    albedo = rng.uniform(0.2, 0.9, (40, 3))
    vis = np.concatenate([rng.normal(scale=0.8, size=(40, 3)), rng.uniform(0.6, 1.2, (40, 1))], 1)
    truth = rng.normal(scale=0.1, size=(40, 3, len(PS_TERMS)))
    v = ps_visibility(lights, vis)  # (n, P)
    assert 0 < np.mean(v < 1) < 1  # some lights are (partly) shadowed
    direct = np.array([is_direct(t) for t in PS_TERMS])
    assert list(direct) == [True, True, True, False, True, True]
    basis = ps_basis(lights, normals, PS_TERMS)
    basis = np.where(direct, basis * v[..., None], basis)
    shade = np.maximum(lights @ normals.T, 0) * v
    obs = albedo[None] * shade[..., None] + np.einsum("npk,pck->npc", basis, truth)
    coeffs = fit_ps(obs, lights, normals, albedo, ridge=0.0, visibility=vis)
    cond = max(np.linalg.cond(basis[:, p]) for p in range(40))
    bound = 12 * 48 * EPS * cond**2 + EPS32
    assert np.max(np.abs(coeffs - truth)) <= bound * np.abs(truth).max() * 10
    app = Appearance("ps", coeffs.reshape(5, 8, 3, -1),
                     {"basis": "ps", "K": len(PS_TERMS), "terms": list(PS_TERMS)},
                     {"visibility": vis.reshape(5, 8, 4).astype(np.float32)})
    new = hemisphere(1, rng, 60)[0]
    picture = evaluate_appearance(app, new, normals.reshape(5, 8, 3), albedo.reshape(5, 8, 3))
    v_new = np.clip(vis.astype(np.float32).astype(np.float64) @ np.append(new, 1.0), 0, 1)
    b_new = ps_basis(new[None], normals, PS_TERMS)[0]
    b_new = np.where(direct, b_new * v_new[:, None], b_new)
    expected = (albedo * (np.maximum(normals @ new, 0) * v_new)[:, None]
                + np.einsum("pk,pck->pc", b_new, truth))
    assert np.allclose(picture.reshape(40, 3), expected, atol=1e-5)


def test_visibility_is_one_without_shadows_and_separates_a_cast_shadow(rng):
    lights = hemisphere(60, rng, 70)
    normals = np.tile([0.0, 0.0, 1.0], (3, 1))
    albedo = np.full((3, 3), 0.5)
    obs = albedo[None] * np.maximum(lights @ normals.T, 0)[..., None]
    # pixel 1: shadowed from every light with l_x < -0.2 (a wall on its left); pixel 2: a
    # shadow on the right, half as deep (ambient light fills it): below half -> shadowed
    obs[lights[:, 0] < -0.2, 1] = 0.0
    obs[lights[:, 0] > 0.3, 2] *= 0.3
    w = fit_visibility(obs, lights, normals, albedo)
    # no shadow: exactly the prior V = 1 (labels all 1 agree with it)
    assert np.allclose(w[0], [0, 0, 0, 1], atol=1e-9)
    v = ps_visibility(lights, w)
    assert np.allclose(v[:, 0], 1.0, atol=1e-9)
    # the half-space separates the training lights: V > 1/2 where lit, < 1/2 where shadowed
    # (except lights within 0.1 of the boundary in l_x, where a least-squares ramp is soft)
    for p, shadowed in ((1, lights[:, 0] < -0.2), (2, lights[:, 0] > 0.3)):
        edge = np.abs(lights[:, 0] - (-0.2 if p == 1 else 0.3)) < 0.1
        assert np.all(v[shadowed & ~edge, p] < 0.5)
        assert np.all(v[~shadowed & ~edge, p] > 0.5)


def test_visibility_of_a_ps_model_is_validated(tmp_path):
    app = Appearance("ps", np.zeros((2, 3, 3, len(PS_TERMS)), np.float32),
                     {"basis": "ps", "K": len(PS_TERMS), "terms": list(PS_TERMS)},
                     {"visibility": np.zeros((2, 3, 3), np.float32)})
    write_appearance(tmp_path, app)
    with pytest.raises(DatasetError, match="appearance.npz: visibility must be"):
        read_appearance(tmp_path)
    good = Appearance(app.model, app.coefficients, app.meta,
                      {"visibility": np.ones((2, 3, 4), np.float32)})
    write_appearance(tmp_path, good)
    back = read_appearance(tmp_path)
    assert np.array_equal(back.extra["visibility"], good.extra["visibility"])
    assert coefficients_per_pixel(back) == 3 * len(PS_TERMS) + 4


def test_visibility_helps_on_held_out_lights_of_a_relief_with_cast_shadows(rng):
    surface = render.relief_surface((48, 48), seed=3)
    lights = hemisphere(64, rng, 65)
    images = render.render(surface, lights, cast_shadows=True)  # (n, H, W)
    mask = surface.mask
    obs = images[:, mask]
    train, test = bench_relight.split_lights(len(lights))
    normals = surface.normals[mask]
    albedo = surface.albedo[mask]
    with_vis = fit_appearance("ps", obs[train], lights[train], mask, normals, albedo)
    coeffs = fit_ps(obs[train], lights[train], normals, albedo)
    without = Appearance("ps", np.zeros_like(with_vis.coefficients), with_vis.meta)
    without.coefficients[mask] = coeffs
    errors = {"vis": [], "none": []}
    for k in test:
        truth = np.clip(obs[k], 0, 1)
        for name, app in (("vis", with_vis), ("none", without)):
            picture = evaluate_appearance(app, lights[k], surface.normals, surface.albedo)
            errors[name].append(np.mean((np.clip(picture[mask][..., 0], 0, 1) - truth) ** 2))
    gain = 10 * np.log10(np.mean(errors["none"]) / np.mean(errors["vis"]))
    assert gain > 1.0, (gain, errors)


def test_rbf_fit_keeps_data_of_low_rank(rng):
    lights = hemisphere(30, rng)
    planes = rng.normal(size=(30, 4))  # rank 4 < 9 terms: the basis spans it
    obs = np.einsum("nk,pk->np", planes, rng.normal(size=(50, 4)))[..., None]
    sigma, basis = rbf_setup(obs, lights)
    coeffs = fit_rbf(obs, basis)
    back = np.einsum("cnk,pck->npc", basis, coeffs)
    assert np.allclose(back, obs, atol=1e-5 * np.abs(obs).max())
    assert 0 < sigma <= 1.0


# --- the model: relights a glossy object better than the RTI bases ----------------------------


def _glossy_scene(rng):
    surface = render.sphere_surface((40, 40), albedo=(0.7, 0.45, 0.3))
    lights = hemisphere(64, rng, 60)
    images = render.render(surface, lights, specular=0.4, roughness=0.2, cast_shadows=False)
    mask = surface.mask
    return surface, lights, images[:, mask], mask


def test_ps_model_beats_rti_bases_on_held_out_lights_of_a_glossy_render(rng):
    surface, lights, obs, mask = _glossy_scene(rng)
    train, test = bench_relight.split_lights(len(lights))
    normals = surface.normals[mask]
    albedo = surface.albedo[mask]
    psnr = {}
    for model in ("ptm", "hsh2", "hsh3", "rbf", "ps"):
        app = fit_appearance(model, obs[train], lights[train], mask, normals, albedo)
        errors = []
        for k in test:
            picture = evaluate_appearance(app, lights[k], surface.normals, surface.albedo)
            errors.append(np.mean((np.clip(picture[mask], 0, 1) - np.clip(obs[k], 0, 1)) ** 2))
        psnr[model] = 10 * np.log10(1 / np.mean(errors))
    best_rti = max(psnr[m] for m in ("ptm", "hsh2", "hsh3", "rbf"))
    assert psnr["ps"] >= best_rti + 1.0, psnr


def test_ssim_of_identical_images_is_one_and_drops_with_noise(rng):
    a = rng.uniform(0, 1, (32, 32))
    mask = np.ones((32, 32), bool)
    assert bench_relight.ssim(a, a, mask) == pytest.approx(1.0, abs=1e-12)
    assert bench_relight.ssim(a, a + rng.normal(scale=0.2, size=a.shape), mask) < 0.9


# --- the file ----------------------------------------------------------------------------------


def test_appearance_file_round_trip_and_validation(tmp_path, rng):
    coeffs = rng.normal(size=(4, 5, 3, 9)).astype(np.float32)
    app = Appearance("hsh3", coeffs, {"basis": "hsh3", "K": 9, "terms": []})
    write_appearance(tmp_path, app)
    back = read_appearance(tmp_path)
    assert back.model == "hsh3" and np.array_equal(back.coefficients, coeffs)
    assert read_appearance(tmp_path / "absent") is None
    bad = Appearance("hsh3", coeffs[..., :4], {"basis": "hsh3"})
    write_appearance(tmp_path, bad)
    with pytest.raises(DatasetError, match="appearance.npz: hsh3 has 9 terms"):
        read_appearance(tmp_path)
    (tmp_path / APPEARANCE_FILE).write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match="not a readable appearance file"):
        read_appearance(tmp_path)


# --- reconstruct --appearance and relight, end to end --------------------------------------------


def _write_dataset(folder: Path, rng) -> None:
    folder.mkdir()
    surface = render.sphere_surface((24, 24), albedo=0.7)
    lights = hemisphere(24, rng, 60)
    images = render.render(surface, lights, specular=0.2, cast_shadows=False)
    for i, image in enumerate(images):
        counts = np.clip(np.rint(image / images.max() * 0.9 * 65535), 0, 65535).astype(np.uint16)
        assert cv2.imwrite(str(folder / f"{i:03d}.png"), counts)
    np.savetxt(folder / "light_directions.txt", lights)
    cv2.imwrite(str(folder / "mask.png"), surface.mask.astype(np.uint8) * 255)


@pytest.mark.parametrize("model", ["ps", "hsh2", "rbf"])
def test_reconstruct_appearance_then_relight(tmp_path, rng, model):
    _write_dataset(tmp_path / "data", rng)
    out = tmp_path / "result"
    done = runner.invoke(app, ["reconstruct", str(tmp_path / "data"), "--method", "ls",
                               "--out", str(out), "--appearance", model])
    assert done.exit_code == 0, done.output
    metrics = json.loads((out / "metrics.json").read_text())
    fitted = read_appearance(out)
    assert metrics["appearance"]["model"] == model == fitted.model
    assert metrics["appearance"]["coefficients_per_pixel"] == coefficients_per_pixel(fitted)
    relit = runner.invoke(app, ["relight", str(out), "--light", "0.2,0.3,0.9",
                                "--light", "0,0,1", "--out", str(tmp_path / "pic.exr")])
    assert relit.exit_code == 0, relit.output
    first = read_exr(tmp_path / "pic_light01.exr")
    normals = np.load(out / "normals.npy")
    expected = evaluate_appearance(fitted, np.array([0.2, 0.3, 0.9]) / np.linalg.norm(
        [0.2, 0.3, 0.9]), normals, np.load(out / "albedo.npy"))
    solved = np.linalg.norm(normals, axis=-1) > 0.5
    assert np.allclose(first[solved], np.repeat(expected, 3, axis=2)[solved], atol=1e-6)
    assert (tmp_path / "pic_light02.exr").is_file()
    png = runner.invoke(app, ["relight", str(out), "--light", "0,0,1", "--appearance",
                              "lambertian", "--out", str(tmp_path / "pic.png")])
    assert png.exit_code == 0, png.output
    assert cv2.imread(str(tmp_path / "pic.png")).shape == (24, 24, 3)


def test_reconstruct_appearance_none_writes_no_file(tmp_path, rng):
    _write_dataset(tmp_path / "data", rng)
    out = tmp_path / "result"
    done = runner.invoke(app, ["reconstruct", str(tmp_path / "data"), "--method", "ls",
                               "--out", str(out), "--appearance", "none"])
    assert done.exit_code == 0, done.output
    assert not (out / APPEARANCE_FILE).exists()
    assert json.loads((out / "metrics.json").read_text())["appearance"]["model"] == "none"


def _tiny_result(folder: Path, with_appearance: bool = True) -> None:
    folder.mkdir()
    normals = np.zeros((3, 4, 3), np.float32)
    normals[..., 2] = 1
    np.save(folder / "normals.npy", normals)
    np.save(folder / "albedo.npy", np.full((3, 4), 0.5, np.float32))
    (folder / "metrics.json").write_text(json.dumps({"format": RESULT_FORMAT}))
    if with_appearance:
        write_appearance(folder, Appearance("ptm", np.ones((3, 4, 1, 6), np.float32),
                                            {"basis": "ptm", "K": 6, "terms": []}))


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--light", "1,2"], "--light '1,2': expected three numbers"),
        (["--light", "0,0,0"], "the direction is zero"),
        (["--light", "0,0,1", "--out", "x.jpg"], "must end in .exr"),
        (["--light", "0,0,1", "--appearance", "fitted", "NOAPP"], "no appearance.npz"),
        (["--light", "0,0,1", "NOTRESULT"], "not a ps-lab reconstruct result"),
    ],
)
def test_relight_bad_input_one_error_line(tmp_path, args, message):
    _tiny_result(tmp_path / "result")
    _tiny_result(tmp_path / "noapp", with_appearance=False)
    (tmp_path / "notresult").mkdir()
    folder = {"NOAPP": "noapp", "NOTRESULT": "notresult"}
    target = tmp_path / "result"
    rest = []
    for a in args:
        if a in folder:
            target = tmp_path / folder[a]
        else:
            rest.append(a)
    if "--out" not in rest:
        rest += ["--out", str(tmp_path / "pic.exr")]
    else:
        i = rest.index("--out")
        rest[i + 1] = str(tmp_path / rest[i + 1])
    before = sorted(p.name for p in tmp_path.iterdir())
    done = runner.invoke(app, ["relight", str(target), *rest])
    assert done.exit_code == 2
    lines = [line for line in done.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and message in lines[0], done.output
    assert sorted(p.name for p in tmp_path.iterdir()) == before


# --- real data ---------------------------------------------------------------------------------


@pytest.mark.slow
def test_ps_model_beats_rti_on_a_real_object():
    folder = bench_relight.DEFAULT_FOLDER / "goblet"
    if not folder.is_dir():
        pytest.skip(f"{folder} absent")
    row = bench_relight.evaluate_capture(folder)
    best = max(row.cells[m]["psnr"] for m in ("ptm", "hsh2", "hsh3", "rbf"))
    assert row.cells["ps"]["psnr"] > best


def test_relight_near_result_by_led_position(tmp_path):
    folder = tmp_path / "near"
    _tiny_result(folder, with_appearance=False)
    (folder / "metrics.json").write_text(json.dumps({"format": RESULT_FORMAT,
                                                     "light_model": "near"}))
    np.save(folder / "depth.npy", np.zeros((3, 4), np.float32))
    done = runner.invoke(app, ["relight", str(folder), "--light", "0,0,100", "--appearance",
                               "lambertian", "--out", str(tmp_path / "near.exr")])
    assert done.exit_code == 0, done.output
    picture = read_exr(tmp_path / "near.exr")[..., 0]
    # scene frame: origin at the image centre ((W-1)/2, (H-1)/2) = (1.5, 1); pixel (row 1,
    # col 1) is the point (-0.5, 0, 0): cos = 100 / r, falloff (100 / r)^2, r^2 = 100^2 + 0.25
    r = math.sqrt(100**2 + 0.25)
    assert picture[1, 1] == pytest.approx(0.5 * (100 / r) * (100 / r) ** 2, rel=1e-6)


@pytest.mark.parametrize("model", ["ps", "hsh3", "rbf"])
def test_streamed_fit_equals_the_whole_array_fit(tmp_path, rng, model):
    from ps_lab.io.bands import ObservationStore, plan_bands
    from ps_lab.appearance.fit import fit_appearance_bands

    surface, lights, obs, mask = _glossy_scene(rng)
    grey = obs.mean(axis=2).astype(np.float32)  # (n, P): one channel, as the store holds now
    bands = plan_bands(mask, 300)  # several bands
    assert len(bands) > 2
    store = ObservationStore(bands, len(lights), mask, in_memory=True)
    image = np.zeros((len(lights), *mask.shape), np.float32)
    image[:, mask] = grey
    for i in range(len(lights)):
        store.write_frame(i, image[i], np.ones(mask.shape, bool))
    normals = surface.normals.astype(np.float32)
    albedo = surface.albedo.mean(axis=2).astype(np.float32)
    np.save(tmp_path / "normals.npy", normals)
    np.save(tmp_path / "albedo.npy", albedo)
    with store:
        record = fit_appearance_bands(store, tmp_path, model, lights)
    streamed = read_appearance(tmp_path)
    whole = fit_appearance(model, grey, lights, mask, normals[mask], albedo[mask])
    assert record["coefficients_per_pixel"] == coefficients_per_pixel(whole)
    if model == "rbf":  # the basis comes from the store's sample, the whole fit's from all pixels
        assert streamed.meta["sigma"] > 0
        return
    # Same sums per pixel in another block order: float32 storage of both.
    scale = np.abs(whole.coefficients).max()
    assert np.allclose(streamed.coefficients, whole.coefficients, atol=4 * EPS32 * scale)
    if model == "ps":
        assert np.allclose(streamed.extra["visibility"], whole.extra["visibility"],
                           atol=4 * EPS32 * np.abs(whole.extra["visibility"]).max())


# --- the fast fits against a per-pixel reference (issue 37) ------------------------------------


def _reference_visibility(obs, directions, normals, albedo):
    """fit_visibility's maths pixel by pixel with numpy's solve (the implementation before 37)."""
    from ps_lab.appearance._ps_kernel import VIS_LABEL, VIS_MARGIN, VIS_RIDGE, VIS_ROUNDS

    n, p, _ = obs.shape
    rho = albedo.mean(axis=1) if albedo.ndim == 2 else albedo
    ridge = np.diag([VIS_RIDGE] * 3 + [1e-6]) * n
    prior = ridge @ np.array([0.0, 0.0, 0.0, 1.0])
    out = np.zeros((p, 4))
    for q in range(p):
        d = directions if directions.ndim == 2 else directions[:, q]
        good = np.isfinite(obs[:, q])
        count = good.sum(axis=1)
        mean = np.where(good, obs[:, q], 0.0).sum(axis=1) / np.maximum(count, 1)
        shade = d @ normals[q]
        facing = (shade > VIS_MARGIN) & (count > 0)
        label = (mean >= VIS_LABEL * rho[q] * np.maximum(shade, 0.0)).astype(float)
        features = np.column_stack([d, np.ones(n)])
        weight = facing.astype(float)
        for _ in range(VIS_ROUNDS):
            gram = (features * weight[:, None]).T @ features
            w = np.linalg.solve(gram + ridge, features.T @ (weight * label) + prior)
            value = features @ w
            settled = ((value >= 1) & (label == 1)) | ((value <= 0) & (label == 0))
            weight = (facing & ~settled).astype(float)
        out[q] = w
    return out


def _reference_ps(obs, directions, normals, albedo, visibility, terms, ridge):
    """fit_ps's maths pixel by pixel and channel by channel: ps_term, numpy's solve."""
    n, p, c = obs.shape
    rho = np.broadcast_to(albedo[:, None] if albedo.ndim == 1 else albedo, (p, c))
    direct = np.array([is_direct(t) for t in terms])
    out = np.zeros((p, c, len(terms)))
    for q in range(p):
        if not np.linalg.norm(normals[q]) > 0.5:
            continue
        d = directions if directions.ndim == 2 else directions[:, q]
        basis = np.stack([ps_term(t, d, normals[q]) for t in terms], axis=1)  # (n, K)
        v = np.ones(n)
        if visibility is not None:
            v = np.clip(d @ visibility[q, :3] + visibility[q, 3], 0.0, 1.0)
        basis[:, direct] *= v[:, None]
        shade = np.maximum(d @ normals[q], 0.0) * v
        for ch in range(c):
            good = np.isfinite(obs[:, q, ch])
            b = basis[good]
            r = obs[good, q, ch] - rho[q, ch] * shade[good]
            gram = b.T @ b
            shift = ridge * np.trace(gram) / len(terms) + 1e-12
            out[q, ch] = np.linalg.solve(gram + shift * np.eye(len(terms)), b.T @ r)
    return out


def _shadowed_block(rng, pixels=150, lights=40, per_pixel=False):
    """Colour observations of a block with cast shadows, noise, missing values and unsolved
    pixels; directions (n, 3) or per pixel (n, P, 3)."""
    d = hemisphere(lights, rng, 70)
    normals = hemisphere(pixels, rng, 50)
    if per_pixel:  # lights at a finite distance: each pixel's own unit directions
        points = np.concatenate([rng.uniform(-0.3, 0.3, (pixels, 2)), np.zeros((pixels, 1))], 1)
        to_light = 3.0 * d[:, None, :] - points[None]
        d = to_light / np.linalg.norm(to_light, axis=-1, keepdims=True)  # (n, P, 3)
        shade = np.einsum("npk,pk->np", d, normals)
    else:
        shade = d @ normals.T
    albedo = rng.uniform(0.2, 0.9, (pixels, 3))
    wall = np.concatenate([rng.normal(scale=1.5, size=(pixels, 3)),
                           rng.uniform(0.3, 1.5, (pixels, 1))], axis=1)
    dd = d if d.ndim == 3 else np.broadcast_to(d[:, None], (lights, pixels, 3))
    lit = (np.einsum("npk,pk->np", dd, wall[:, :3]) + wall[:, 3]) > 0.5  # a cast shadow
    obs = albedo[None] * (np.maximum(shade, 0) * np.where(lit, 1.0, 0.15))[..., None]
    obs += 0.05 * np.maximum(shade, 0)[..., None] ** 8 + rng.normal(scale=0.01, size=obs.shape)
    obs[rng.random(obs.shape) < 0.03] = np.nan  # missing channels
    obs[3, 5] = np.nan  # a light without any channel
    obs[:, 7, 1] = np.inf
    normals[[0, 9, 40]] = 0.0  # unsolved
    normals[11] = np.nan
    return obs, d, normals, albedo


# cond of a ps normal matrix (ridge 1e-4 of its mean diagonal) is at most ~1e4 and that of the
# visibility's (ridge 1e-6 n on the constant) ~1e6: float64 solves by Cholesky and by LU agree
# to cond · n · eps < 1e-8 relative; 1e-9 of the largest value holds on these data with margin.
REFERENCE_TOL = 1e-9


@pytest.mark.parametrize("per_pixel", [False, True])
def test_visibility_equals_the_per_pixel_reference(rng, per_pixel):
    obs, d, normals, albedo = _shadowed_block(rng, per_pixel=per_pixel)
    fast = fit_visibility(obs, d, normals, albedo)
    ref = _reference_visibility(obs, d, normals, albedo)
    assert fast.dtype == np.float64 and fast.shape == ref.shape
    solved = np.linalg.norm(normals, axis=1) > 0.5
    # shadows are fitted (not only the prior w = (0, 0, 0, 1)) on most of the pixels
    assert np.mean(np.abs(ref[solved] - [0, 0, 0, 1]).max(axis=1) > 1e-3) > 0.5
    scale = np.abs(ref).max(axis=1, keepdims=True)
    assert np.all(np.abs(fast - ref) <= REFERENCE_TOL * np.maximum(scale, 1.0))


@pytest.mark.parametrize("per_pixel", [False, True])
@pytest.mark.parametrize("terms", [PS_TERMS, ("lambert", "ambient", "lobex:8", "lobey:8", "lobe:16",
                                              "lobe:2.5", "hsh:1", "hsh:5")])
def test_ps_fit_equals_the_per_pixel_reference(rng, per_pixel, terms):
    obs, d, normals, albedo = _shadowed_block(rng, per_pixel=per_pixel)
    vis = _reference_visibility(obs, d, normals, albedo)
    for visibility in (vis, None):
        fast = fit_ps(obs, d, normals, albedo, terms, visibility=visibility)
        ref = _reference_ps(obs, d, normals, albedo, visibility, terms, PS_RIDGE)
        assert fast.dtype == np.float32 and fast.shape == ref.shape
        # the kernel's float64 result rounded once to float32: within half a float32 ulp of
        # the reference plus the float64 difference
        bound = 0.5 * EPS32 * np.abs(ref) + REFERENCE_TOL * np.abs(ref).max()
        assert np.all(np.abs(fast - ref) <= bound)
        solved = np.linalg.norm(normals, axis=1) > 0.5
        observed = np.isfinite(obs).any(axis=0) & solved[:, None]  # (P, C): pixel 7's G is not
        assert np.all(fast[~solved] == 0) and np.all(fast[~observed] == 0)
        assert np.all(np.abs(fast[observed]).max(axis=1) > 0)


def test_ps_block_from_float32_with_a_scale_equals_the_reference(rng):
    # the reconstruction's path: the store's float32 observations, each light's divisor, the
    # fused visibility and ps fit; unsolved pixels get V = 1 and no coefficients
    from ps_lab.appearance.blocks import fit_block

    obs, d, normals, albedo = _shadowed_block(rng, pixels=200)
    stored = obs.astype(np.float32)
    factor = rng.uniform(0.5, 2.0, len(d))
    part = slice(30, 170)
    coeffs, vis = fit_block("ps", stored, d, normals=normals[part], albedo=albedo[part],
                            pixels=part, scale=factor)
    divided = stored[:, part].astype(np.float64) / factor[:, None, None]
    ref_vis = _reference_visibility(divided, d, normals[part], albedo[part])
    solved = np.linalg.norm(normals[part], axis=1) > 0.5
    ref_vis[~solved] = (0.0, 0.0, 0.0, 1.0)
    ref = _reference_ps(divided, d, normals[part], albedo[part], ref_vis, PS_TERMS, PS_RIDGE)
    # x / s and x * (1 / s) differ by an ulp: the same bounds as above
    assert vis.dtype == np.float32
    assert np.allclose(vis, ref_vis, rtol=0.5 * EPS32, atol=REFERENCE_TOL * np.abs(ref_vis).max())
    bound = 0.5 * EPS32 * np.abs(ref) + REFERENCE_TOL * np.abs(ref).max()
    assert np.all(np.abs(coeffs - ref) <= bound)


@pytest.mark.parametrize("model", ["ptm", "hsh3"])
def test_linear_fit_equals_per_pixel_least_squares(rng, model):
    obs, d, _, _ = _shadowed_block(rng, pixels=60)
    obs[:, 20:] = np.nan_to_num(obs[:, 20:], nan=0.3, posinf=0.3)  # pixels 20.. all finite
    basis = appearance_basis(model, d)
    factor = rng.uniform(0.5, 2.0, len(d))
    fast = fit_linear(model, obs.astype(np.float32), d, factor)
    y = obs.astype(np.float32).astype(np.float64) / factor[:, None, None]
    ref = np.zeros(fast.shape)
    k = basis.shape[1]
    for q in range(obs.shape[1]):
        complete = np.isfinite(y[:, q]).all()  # a pixel with all its observations: lstsq
        for ch in range(3):
            good = np.isfinite(y[:, q, ch])
            if complete:
                ref[q, ch] = np.linalg.lstsq(basis, y[:, q, ch], rcond=None)[0]
            else:  # normal equations on the finite ones, regularised by 1e-9 of the trace
                b = basis[good]
                gram = b.T @ b + 1e-9 * np.trace(basis.T @ basis) * np.eye(k)
                ref[q, ch] = np.linalg.solve(gram, b.T @ y[good, q, ch])
    cond = np.linalg.cond(basis)
    bound = 0.5 * EPS32 * np.abs(ref) + 16 * len(d) * EPS * cond**2 * np.abs(ref).max()
    assert np.all(np.abs(fast - ref) <= bound)


def test_streamed_colour_fit_does_not_depend_on_the_threads(tmp_path, rng, monkeypatch):
    from ps_lab.io.bands import ObservationStore, plan_bands
    from ps_lab.io.coding import float_coding
    from ps_lab.appearance import fit as appearance_module

    surface, lights, obs, mask = _glossy_scene(rng)
    obs = obs.astype(np.float32)
    obs[rng.random(obs.shape) < 0.01] = np.nan
    monkeypatch.setattr(appearance_module, "FIT_CHUNK", 64)  # several blocks per band
    bands = plan_bands(mask, 400)
    store = ObservationStore(bands, len(lights), mask, in_memory=True, colours=3,
                             coding=float_coding(3))
    colour = np.zeros((len(lights), *mask.shape, 3), np.float32)
    colour[:, mask] = obs
    for i in range(len(lights)):
        store.write_frame(i, colour[i], np.ones(mask.shape, bool))
    np.save(tmp_path / "normals.npy", surface.normals.astype(np.float32))
    np.save(tmp_path / "albedo.npy", surface.albedo.astype(np.float32))
    scale = rng.uniform(0.8, 1.25, len(lights))
    results = []
    with store:
        for workers in (1, 2):
            appearance_module.fit_appearance_bands(store, tmp_path, "ps", lights, scale,
                                                   workers=workers)
            results.append(read_appearance(tmp_path))
    one, two = results
    assert np.array_equal(one.coefficients, two.coefficients)
    assert np.array_equal(one.extra["visibility"], two.extra["visibility"])
    # and the same numbers as the whole-array fit of the divided observations
    whole = fit_appearance("ps", obs / scale[:, None, None], lights, mask,
                           surface.normals[mask].astype(np.float32),
                           surface.albedo[mask].astype(np.float32))
    assert np.allclose(one.coefficients, whole.coefficients,
                       atol=4 * EPS32 * np.abs(whole.coefficients).max())
    assert np.allclose(one.extra["visibility"], whole.extra["visibility"], atol=4 * EPS32)


def test_the_warm_up_compiles_every_type_the_ps_fits_pass(rng):
    # The install step's two versions of the kernel (float32 from the store, float64) are all
    # that the fits ever call: grey or colour, C or sliced or read-only observations, other
    # dtypes, per-pixel directions, a given visibility, missing values, a divisor.
    from ps_lab.appearance import _ps_kernel, _ps_terms
    from ps_lab.appearance.blocks import fit_block
    from ps_lab.reconstruct._warm_up import GROUPS

    GROUPS["appearance"].run()
    kernels = [v for module in (_ps_kernel, _ps_terms) for v in vars(module).values()
               if hasattr(v, "signatures")]
    warmed = {k.py_func.__name__: set(k.signatures) for k in kernels}
    obs, d, normals, albedo = _shadowed_block(rng, pixels=50)
    per_pixel = np.ascontiguousarray(np.broadcast_to(d[:, None], (len(d), 50, 3)))
    read_only = obs.astype(np.float32)
    read_only.flags.writeable = False
    for o in (obs, obs.astype(np.float32), obs[:, 2:], obs[..., 0], read_only,
              obs.astype(np.float16)):
        p = o.shape[1]
        rho = (albedo if o.ndim == 3 else albedo.mean(axis=1))[-p:]
        for lights in (d, per_pixel[:, -p:]):
            fit_visibility(o, lights, normals[-p:], rho)
            fit_ps(o, lights, normals[-p:], rho, visibility=np.ones((p, 4)))
            fit_block("ps", o, lights, normals=normals[-p:][1:5], albedo=rho[1:5],
                      pixels=slice(1, 5), scale=np.full(len(d), 2.0))
    assert {k.py_func.__name__: set(k.signatures) for k in kernels} == warmed
    assert len(warmed["_ps_kernel"]) == 2


def test_masked_projection_is_the_least_squares_of_the_finite_observations():
    # the smoothers' path (Woodbury over the missing rows of the basis) against the per-pixel
    # normal equations on the finite observations (_masked_solve, same ridge)
    from ps_lab.appearance.blocks import _masked_solve, masked_projection

    rng = np.random.default_rng(43)
    n, k, q = 40, 12, 300
    basis, _ = np.linalg.qr(rng.normal(size=(n, k)))
    basis = basis * rng.uniform(0.5, 2.0, k)  # any basis: columns not of unit length
    sub = rng.normal(size=(n, q))
    sub[rng.random((n, q)) < 0.15] = np.nan
    sub[: n - 20, :5] = np.nan  # 20 finite observations left for 12 terms
    out = masked_projection(sub, basis)
    reference = _masked_solve(basis, sub[..., None])[:, 0]
    # both solve the same well-conditioned systems (>= 20 finite rows of 40 for 12 terms):
    # agreement to the rounding of a 12 x 12 solve
    np.testing.assert_allclose(out, reference, rtol=0, atol=1e-9 * np.abs(reference).max())
