"""LED beams and flat-field (issue 33): fits on a flat matte board, round trips, the CLI path.

The board frames come from ``ps_lab.render.table_rig`` (its own LED, beam and shading code), on a
small copy of the table rig (half size) so each test takes seconds.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from ps_lab.calibration import calibrate
from ps_lab.calibration._highlight import locate_highlight
from ps_lab.calibration._leds import (
    beam_intensities_at_origin,
    fit_flat_field,
    fit_led_beams,
)
from ps_lab.calibration._positions import ray_sigmas, triangulate_lights
from ps_lab.cli import app
from ps_lab.geometry import near_light_vectors, scene_points
from ps_lab.io.led_model import read_flat_field, read_light_axes
from ps_lab.render.table_rig import (
    TableRig,
    chrome_frames,
    render_board,
    write_board_frames,
    write_table_rig,
)

# Half the table rig: 240x180, dome 330 px, spheres of radius 20, object of radius 57.
SMALL = TableRig(shape=(180, 240), origin_px=(118.0, 92.0), dome_radius=330.0,
                 spheres=((30.0, 148.0, 20.0), (210.0, 31.0, 20.0)), object_center=(122.0, 88.0),
                 object_radius=57.0, object_top=15.0, led_radius=5.0)
BEAMS = replace(SMALL, beam_mu=2.0, beam_tilt_deg=8.0, output_spread=0.1)
TABLE = -20.0  # the table in ps-lab's scene frame: minus the spheres' radius


def _scene_leds(rig: TableRig) -> np.ndarray:
    h, w = rig.shape
    shift = [rig.origin_px[0] - (w - 1) / 2, (h - 1) / 2 - rig.origin_px[1], -rig.spheres[0][2]]
    return rig.led_positions() + np.array(shift)


def test_beam_fit_recovers_axis_exponent_and_output() -> None:
    board = render_board(BEAMS)["frames"]
    rng = np.random.default_rng(3)
    noisy = board * (1.0 + rng.normal(0.0, 2e-3, board.shape))  # 0.2 % per pixel
    beams = fit_led_beams(noisy, _scene_leds(BEAMS), TABLE)
    # ~2500 pixels per LED at 0.2 %: the fit's own scatter is ~1e-4 in log brightness; the
    # bounds are the model's curvature over the board (about 10 %) times that, with margin.
    np.testing.assert_allclose(beams.mu, 2.0, atol=0.05)
    cos = np.clip(np.sum(beams.axes * BEAMS.led_axes(), axis=1), -1.0, 1.0)
    assert np.degrees(np.arccos(cos)).max() < 0.5
    truth = BEAMS.led_outputs() / BEAMS.led_outputs().mean()
    np.testing.assert_allclose(beams.outputs, truth, rtol=5e-3)
    assert beams.rms_pct.max() < 0.5  # the 0.2 % noise, not model error
    iso = fit_led_beams(render_board(SMALL)["frames"], _scene_leds(SMALL), TABLE)
    np.testing.assert_allclose(iso.mu, 0.0, atol=1e-3)
    np.testing.assert_allclose(beam_intensities_at_origin(iso, _scene_leds(SMALL)),
                               1.0 / np.sum(_scene_leds(SMALL) ** 2, axis=1)
                               / np.mean(1.0 / np.sum(_scene_leds(SMALL) ** 2, axis=1)),
                               rtol=5e-3)


def test_flat_field_carries_the_beam_to_other_heights() -> None:
    """Gains measured on the table predict a board 12 px higher (looked up along each LED's ray)."""
    leds = _scene_leds(BEAMS)
    low = render_board(BEAMS)["frames"]
    e = np.ones(len(leds))
    flat = fit_flat_field(low, leds, e, TABLE, cell=4)
    high = render_board(BEAMS, height=12.0)["frames"]
    h, w = BEAMS.shape
    rows, cols = np.mgrid[4:h - 4:5, 4:w - 4:5]
    pts = scene_points((h, w), rows.ravel(), cols.ravel(), np.full(rows.size, TABLE + 12.0))
    vectors = near_light_vectors(pts, leds, leds) * flat.at(pts)[:, :, None]
    predicted = vectors[..., 2].T  # the board's normal is z
    measured = high[:, rows.ravel(), cols.ravel()]
    ratio = measured / predicted
    ratio /= np.median(ratio)
    # bilinear between 4 px cells of a smooth beam: the interpolation error is below 0.1 %;
    # the rest is the beam's change across a cell's own footprint
    assert np.abs(ratio - 1.0).max() < 5e-3, np.abs(ratio - 1.0).max()
    # without the gains the beam's 10-20 % variation is left
    plain = measured / near_light_vectors(pts, leds, leds)[..., 2].T
    assert np.abs(plain / np.median(plain) - 1.0).max() > 0.05


def test_flat_board_normals_after_flat_field() -> None:
    """A board 8 px above the one the flat-field was measured on: per-pixel normals, truth depth."""
    leds = _scene_leds(BEAMS)
    e = beam_intensities_at_origin(fit_led_beams(render_board(BEAMS)["frames"], leds, TABLE),
                                   leds)
    flat = fit_flat_field(render_board(BEAMS)["frames"], leds, e, TABLE)
    frames = render_board(BEAMS, height=8.0)["frames"]
    h, w = BEAMS.shape
    rows, cols = np.mgrid[0:h:6, 0:w:6]
    pts = scene_points((h, w), rows.ravel(), cols.ravel(), np.full(rows.size, TABLE + 8.0))
    equal = 1.0 / np.sum(leds * leds, axis=1)  # no board: identical isotropic LEDs
    errors = {}
    for name, vectors, scale in (("isotropic", near_light_vectors(pts, leds, leds), equal),
                                 ("flat-field", near_light_vectors(pts, leds, leds)
                                  * flat.at(pts)[:, :, None], e)):
        obs = frames[:, rows.ravel(), cols.ravel()] / scale[:, None]
        x = np.linalg.solve(np.einsum("mnk,mnl->mkl", vectors, vectors),
                            np.einsum("mnk,nm->mk", vectors, obs)[..., None])[..., 0]
        errors[name] = np.degrees(np.arccos(x[:, 2] / np.linalg.norm(x, axis=1)))
    # noise-free: what is left is the 8 px cells' interpolation of a smooth beam (target 0.5 deg)
    assert errors["flat-field"].max() < 0.15, errors["flat-field"].max()
    assert errors["isotropic"].mean() > 1.0  # the cos^2 beams and outputs, uncorrected


def test_point_like_highlight_is_not_corrected_for_blur() -> None:
    """An isotropic blur is not source size: the centroid of a blurred point stays put."""
    h = w = 101
    cx, cy, r = 50.0, 50.0, 40.0
    yy, xx = np.mgrid[0:h, 0:w]
    for hx, hy in ((72.3, 41.6), (30.2, 70.7), (55.4, 48.1)):
        frame = np.where(np.hypot(xx - cx, yy - cy) < r, 0.01, 0.0)
        frame = frame + np.exp(-((xx - hx) ** 2 + (yy - hy) ** 2) / (2 * 0.9 ** 2))
        hl = locate_highlight(frame, (cx, cy, r))
        # no source-size correction: the blob is round (the former estimate read its 0.9 px
        # as a 2.6 deg source and moved the highlight outward by 0.01-0.02 px)
        assert np.hypot(hl.x - hl.centroid[0], hl.y - hl.centroid[1]) < 1e-3
        # the half-peak window (grown by 2 px) cuts the Gaussian's tails at ~2.5 sigma
        assert np.hypot(hl.x - hx, hl.y - hy) < 6e-3, (hl.x - hx, hl.y - hy)


def test_led_positions_from_small_spheres_within_one_percent() -> None:
    """Noise-free chrome frames of the small rig (spheres of 20 px, LED discs under a 0.8 px blur).

    What is left is the 3-4 pixel highlights' sampling (~0.007 px rms, up to 0.02 px at the
    light's end of a 19 deg ray pair: ~0.7 % of the dome); the blur read as source size (before
    issue 33) left 0.57 / 1.80 % (mean / worst).
    """
    frames = np.clip(chrome_frames(SMALL), 0.0, 1.0)
    cal = calibrate(frames, sphere=SMALL.spheres[0], extra_spheres=[SMALL.spheres[1]],
                    saturated=frames >= 1.0)
    error = np.linalg.norm(cal.triangulation.positions - _scene_leds(SMALL), axis=1)
    error /= SMALL.dome_radius
    assert error.max() < 0.01 and error.mean() < 0.004, (error.mean(), error.max())


def test_weighted_triangulation_is_exact_and_weights_the_far_ray_down() -> None:
    rng = np.random.default_rng(5)
    light = np.array([100.0, 50.0, 400.0])
    origins = np.array([[[0.0, 0.0, 0.0]], [[300.0, 0.0, 0.0]], [[-150.0, 200.0, 0.0]]])
    d = light[None, None, :] - origins
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    sigmas = np.full((3, 1), 1e-3)
    exact = triangulate_lights(origins, d, sigmas=sigmas)
    np.testing.assert_allclose(exact.positions[0], light, atol=1e-8)
    # turn each ray by its own noise; the weighted point is the better one on average
    errors = {"equal": [], "weighted": []}
    sig = np.array([[1e-3], [1e-3], [8e-3]])  # the third sphere is 8x less precise
    for _ in range(200):
        noisy = d + rng.normal(0.0, 1.0, d.shape) * sig[..., None]
        noisy /= np.linalg.norm(noisy, axis=2, keepdims=True)
        errors["equal"].append(np.linalg.norm(triangulate_lights(origins, noisy).positions[0]
                                              - light))
        errors["weighted"].append(np.linalg.norm(
            triangulate_lights(origins, noisy, sigmas=sig).positions[0] - light))
    assert np.mean(errors["weighted"]) < 0.8 * np.mean(errors["equal"])
    # ray precision: a highlight near the limb is foreshortened
    s = ray_sigmas(np.array([[50.0, 50.0], [88.0, 50.0]]), (50.0, 50.0, 40.0), 0.1)
    assert s[0] == pytest.approx(2 * 0.1 / 40.0) and s[1] > 2.5 * s[0]


def test_calibrate_flat_field_and_reconstruct_led_models(tmp_path: Path) -> None:
    """The whole path: board frames -> calibration files and dome -> reconstruct --led-model."""
    near, board = tmp_path / "near", tmp_path / "board"
    write_table_rig(near, BEAMS)
    write_board_frames(board, BEAMS)
    spheres = [a for c in BEAMS.spheres for a in ("--sphere", f"{c[0]:g},{c[1]:g},{c[2]:g}")]
    runner = CliRunner()
    result = runner.invoke(app, ["calibrate", str(near), *spheres, "--object", "table",
                                 "--flat-field", str(board)])
    assert result.exit_code == 0, result.output
    axes = read_light_axes(near / "light_axes.txt", 24)
    cos = np.clip(np.sum(axes * BEAMS.led_axes(), axis=1), -1.0, 1.0)
    # calibrated positions (~1 px off) and 16-bit shot noise on a 240x180 board: the low LEDs'
    # axes, seen over a narrow cone, move by up to ~2 deg; the exponent stays within a few %
    assert np.degrees(np.arccos(cos)).max() < 3.0
    np.testing.assert_allclose(np.loadtxt(near / "light_anisotropy.txt"), 2.0, atol=0.2)
    assert read_flat_field(near / "flat_field.npz", 24).gains.shape[0] == 24
    dome = json.loads((near / "lights.dome").read_text())
    assert len(dome["ledModel"]) == 24 and "led_model" in json.loads(
        (near / "calibration.json").read_text())
    errors = {}
    for model in ("isotropic", "beam", "flat-field"):
        out = tmp_path / model
        result = runner.invoke(app, ["reconstruct", str(near), "--led-model", model,
                                     "--out", str(out)])
        assert result.exit_code == 0, result.output
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["near"]["led_model"] == model
        errors[model] = metrics["angular_error_deg"]["mean"]
    # the reference: the same rig with isotropic LEDs of equal output, calibrated without a board
    plain = tmp_path / "plain"
    write_table_rig(plain, SMALL)
    for args in (["calibrate", str(plain), *spheres, "--object", "table"],
                 ["reconstruct", str(plain), "--out", str(tmp_path / "p")]):
        result = runner.invoke(app, args)
        assert result.exit_code == 0, result.output
    reference = json.loads((tmp_path / "p" / "metrics.json").read_text())
    reference = reference["angular_error_deg"]["mean"]
    # target: within 1.5x of the isotropic case (measured 1.1x at full size, docs/results.md)
    assert errors["beam"] < 1.3 * reference, (errors, reference)
    assert errors["flat-field"] < 1.3 * reference, (errors, reference)
    assert errors["isotropic"] > 1.3 * errors["beam"]  # the beam ignored costs
    bad = runner.invoke(app, ["calibrate", str(near), *spheres, "--flat-field", str(board),
                              "--board", "shelf"])
    assert bad.exit_code == 2 and "--board" in bad.output


def test_light_vectors_with_led_axes() -> None:
    """``axes`` aimed at the origin is the default; any axis gives ``(c(X) / c(O))^mu``."""
    rng = np.random.default_rng(9)
    pos = rng.normal(0.0, 1.0, (5, 3)) * 100 + [0.0, 0.0, 400.0]
    pts = rng.normal(0.0, 30.0, (7, 3))
    mu = np.array([0.0, 1.0, 2.0, 3.0, 1.5])
    toward = -pos / np.linalg.norm(pos, axis=1, keepdims=True)
    default = near_light_vectors(pts, pos, pos, anisotropy=mu)
    np.testing.assert_allclose(near_light_vectors(pts, pos, pos, anisotropy=mu, axes=toward),
                               default, rtol=1e-12)
    axes = toward + rng.normal(0.0, 0.1, toward.shape)
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    got = near_light_vectors(pts, pos, pos, anisotropy=mu, axes=axes)
    ray = pts[:, None, :] - pos[None]
    c_x = np.einsum("mnk,nk->mn", ray, axes) / np.linalg.norm(ray, axis=2)
    c_o = np.einsum("nk,nk->n", -pos, axes) / np.linalg.norm(pos, axis=1)
    iso = near_light_vectors(pts, pos, pos)
    np.testing.assert_allclose(got, iso * ((c_x / c_o) ** mu)[:, :, None], rtol=1e-10)
