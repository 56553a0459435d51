"""Near lights: LED positions from two chrome spheres, per-pixel-light solvers, the whole job.

Seeded round trips: the renderer's LEDs at a finite distance, calibrated back from two chrome
spheres, and the relief's normals solved with per-pixel light vectors against the truth; the end
to end test runs ``rigs/simulated-near.toml`` through capture -> calibrate -> reconstruct and
checks the issue's targets with margin.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers.solver_oracles import solve_oracle
from helpers.tolerances import EPS, assert_flags_agree, assert_within, solver_bounds
from typer.testing import CliRunner

from ps_lab import render
from ps_lab.calibration import (
    Circle,
    calibrate,
    locate_highlight,
    reflected_rays,
    triangulate_lights,
)
from ps_lab.cli import app
from ps_lab.geometry import near_light_vectors, scene_points
from ps_lab.io.light_files import read_light_positions
from ps_lab.reconstruct import angular_errors_deg, solve
from ps_lab.reconstruct._linalg import pixel_scale
from ps_lab.reconstruct._tiles import sbl_lambda
from ps_lab.reconstruct.near import (
    NearLights,
    fit_depth_offset,
    near_light_reconstruct,
    solve_near,
)

RIGS = Path(__file__).resolve().parents[1] / "rigs"
SHAPE = (150, 200)


def _relief() -> render.Surface:
    h, w = SHAPE
    return render.relief_surface(SHAPE, seed=3, center=((w - 1) / 2, (h - 1) / 2), radius=50)


@pytest.mark.numerical
def test_near_light_vectors_tend_to_directional() -> None:
    rng = np.random.default_rng(0)
    directions = render.random_light_directions(6, rng)
    points = rng.uniform(-50, 50, size=(40, 3))
    distance, intensity = 1e9, np.arange(1, 7)
    far = near_light_vectors(points, distance * directions, directions, intensity)
    expected = np.broadcast_to(directions * intensity[:, None], far.shape)
    # L - I u = I (3 (u.X) u - X) / D + O(1/D^2) (direction and 1/d^2 fall-off to first order),
    # of length <= 2 I |X| / D
    reach = 2.0 * intensity.max() * np.linalg.norm(points, axis=1).max() / distance
    np.testing.assert_allclose(far, expected, rtol=0, atol=reach)
    # at the origin every light has its intensity, whatever the anisotropy
    near = near_light_vectors(np.zeros((1, 3)), 300 * directions, directions, anisotropy=2.0)
    np.testing.assert_allclose(np.linalg.norm(near[0], axis=1), 1.0)
    # a NaN position is a directional light
    positions = 300 * directions
    positions[2] = np.nan
    mixed = near_light_vectors(points, positions, directions)
    np.testing.assert_allclose(mixed[:, 2], np.broadcast_to(directions[2], (40, 3)))


def test_led_positions_from_two_chrome_spheres() -> None:
    rng = np.random.default_rng(4)
    positions = render.dome_light_positions(12, 450.0, rng)
    shape = (300, 400)
    spheres = [Circle(50.0, 50.0, 45.0), Circle(349.0, 249.0, 45.0)]
    origins, rays = [], []
    for sphere in spheres:
        frames = render.render_chrome_near(shape, sphere.center, sphere.radius, positions)
        frames += rng.normal(0.0, 2e-3, frames.shape)
        found = [locate_highlight(frame, sphere) for frame in frames]
        o, d = reflected_rays(np.array([[h.x, h.y] for h in found]), sphere, shape)
        origins.append(o)
        rays.append(d)
    result = triangulate_lights(np.array(origins), np.array(rays))
    error = np.linalg.norm(result.positions - positions, axis=1) / 450.0
    assert error.max() < 0.005, error
    assert result.miss.max() < 1.0
    # rays of the same light from nearly the same place are too parallel to triangulate
    close = triangulate_lights(np.array([origins[0], origins[0] + 0.01]), np.array([rays[0]] * 2))
    assert close.too_far.all()
    # the mean of two equal unit rays, normalised: a few roundings of numbers <= 1
    np.testing.assert_allclose(close.light_directions, rays[0], rtol=0, atol=4 * EPS)


def test_calibrate_finds_both_spheres_and_the_intensities() -> None:
    """No circles given: the automatic search keeps both chrome spheres; near-light intensities."""
    rng = np.random.default_rng(8)
    directions = render.random_light_directions(10, rng, max_zenith_deg=50)
    leds = render.PointLights(400.0 * directions, anisotropy=1.0)
    intensities = np.repeat(1 + 0.1 * rng.uniform(-1, 1, (10, 1)), 3, axis=1)
    scene = render.Scene(260, 180, (
        render.SceneObject("chrome", (45.0, 45.0), 38.0, (0.9, 0.9, 0.9)),
        render.SceneObject("chrome", (214.0, 134.0), 38.0, (0.9, 0.9, 0.9)),
        render.SceneObject("matte", (214.0, 45.0), 38.0, (0.7, 0.7, 0.7)),
    ))
    frames = np.array([
        render.render_scene(scene, directions[j : j + 1], intensities[j : j + 1],
                            point_lights=leds.select([j]))
        for j in range(10)
    ])
    frames += rng.normal(0.0, 1e-3, frames.shape)
    cal = calibrate(frames, matte_sphere=(214.0, 45.0, 38.0), anisotropy=1.0)
    assert len(cal.circles) == 2 and cal.triangulation is not None
    error = np.linalg.norm(cal.light_positions - leds.positions, axis=1) / 400.0
    assert error.max() < 0.01, error
    relative = cal.light_intensities[:, 0] / intensities[:, 0]
    assert np.std(relative / relative.mean()) < 0.01


@pytest.mark.numerical
def test_per_pixel_kernels_equal_the_directional_ones() -> None:
    rng = np.random.default_rng(1)
    lights = render.random_light_directions(20, rng)
    surface = _relief()
    images = render.render(surface, lights, specular=0.3, roughness=0.15)
    rows, cols = np.nonzero(surface.mask)
    obs = images[:, rows, cols]
    vectors = np.ascontiguousarray(np.broadcast_to(lights, (rows.size, 20, 3)))
    for method in ("ls", "l1", "sbl"):
        a = solve(obs, lights, method=method)
        b = solve_near(obs, vectors, method=method)
        if method != "ls":  # a noise-free render: the parameters sit at their floors in both
            assert b.params["tol"] == a.params["tol"]
            assert b.params["outlier_threshold"] == a.params["outlier_threshold"]
        if method == "sbl":
            scale = pixel_scale(np.ascontiguousarray(obs.T), np.ones(obs.T.shape, bool))
            lam = sbl_lambda(scale, a.params["noise_sigma"], a.params["noise_floor"])
            assert np.all(lam == b.params["lambda"])
        # The same iteration, compiled twice: with fastmath the sums are split by SIMD width, so
        # the two agree to rounding, or to the stopping rule where the counts differ
        # (helpers/tolerances.py, solver_bounds).
        same = a.iterations == b.iterations
        bound, margin = solver_bounds(method, a.params, obs, lights, None, a.albedo, same)
        assert_within(b.normals, a.normals, bound)
        if not np.array_equal(b.outliers, a.outliers):
            differ = np.flatnonzero((b.outliers != a.outliers).any(axis=0))
            params = {k: a.params[k] for k in ("max_iter", "tol", "delta", "sigma_x2",
                                               "gamma_floor", "gamma_start") if k in a.params}
            if method == "sbl":
                params["lam"] = b.params["lambda"]
            statistic = np.full(obs.shape, np.inf)
            statistic[:, differ] = solve_oracle(obs[:, differ], lights, method, statistic=True,
                                                **params)[4]
            assert_flags_agree(b.outliers, a.outliers, statistic,
                               a.params["outlier_threshold"], 2.0 * margin)  # either vs oracle


def _near_scene(radius: float, z_offset: float = 0.0):
    surface = _relief()
    positions = render.dome_light_positions(24, radius, np.random.default_rng(11))
    intensities = 1 + 0.1 * np.random.default_rng(12).uniform(-1, 1, 24)
    images = render.render_near(surface, positions, intensities, anisotropy=1.0,
                                z_offset=z_offset, specular=0.2, roughness=0.12)
    images += np.random.default_rng(13).normal(0, 2e-3, images.shape)
    rows, cols = np.nonzero(surface.mask)
    obs = images[:, rows, cols] / intensities[:, None]
    directions = positions / np.linalg.norm(positions, axis=1, keepdims=True)
    return surface, obs, NearLights(positions, directions, np.full(24, 1.0)), rows, cols


@pytest.mark.numerical
def test_depth_offset_is_recovered_from_the_shading() -> None:
    surface, obs, lights, rows, cols = _near_scene(300.0, z_offset=6.0)
    points = scene_points(SHAPE, rows, cols, surface.height[rows, cols])  # 6 px too low
    inliers = ~solve_near(obs, lights.vectors(points + [0, 0, 6.0]), valid=obs > 0.02).outliers
    shift = fit_depth_offset(obs, (obs > 0.02) & inliers, points, lights)
    assert abs(shift - 6.0) < 0.5


@pytest.mark.numerical
def test_near_light_sbl_against_directional() -> None:
    surface, obs, lights, rows, cols = _near_scene(300.0)  # dome = 3x the object
    gt = surface.normals[rows, cols]
    valid = obs > 0.02
    directional = solve(obs, lights.directions, valid=valid)
    near, rounds = near_light_reconstruct(obs, surface.mask, lights, valid=valid)
    e_dir = angular_errors_deg(directional.normals, gt).mean()
    e_near = angular_errors_deg(near.normals, gt).mean()
    assert e_dir > 5.0
    assert e_near < 0.1 * e_dir
    assert e_near < 0.5
    # the outline's height searched (no statement), then the last height settled
    assert rounds.outline_source == "fitted" and rounds.changes[-1] < 0.5
    assert len(rounds.offsets) <= 3 * 8
    depth_error = rounds.depth[surface.mask] - surface.height[surface.mask]
    assert abs(depth_error.mean()) < 1.5


def _invoke(args: list[str]) -> str:
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    return result.output


def _mean_error(folder: Path) -> float:
    return json.loads((folder / "metrics.json").read_text())["angular_error_deg"]["mean"]


def test_near_rig_end_to_end(tmp_path: Path) -> None:
    """The issue's targets on rigs/simulated-near.toml (24 LEDs, dome 3x the object)."""
    near_run, far_run = tmp_path / "near", tmp_path / "far"
    _invoke(["capture", "--rig", str(RIGS / "simulated-near.toml"), "--out", str(near_run),
             "--quiet"])
    _invoke(["calibrate", str(near_run)])
    positions = read_light_positions(near_run / "light_positions.txt")
    truth = np.loadtxt(near_run / "simulation" / "light_positions_true.txt")
    dome = float(np.linalg.norm(truth, axis=1).mean())
    error = np.linalg.norm(positions - truth, axis=1) / dome
    assert error.mean() < 0.006 and error.max() < 0.0125, error  # target: within 1 % of the dome
    relightlab = json.loads((near_run / "lights.dome").read_text())  # the LEDs for RelightLab
    stored = [[p["x"], p["y"], p["z"]] for p in relightlab["positions3d"]]
    np.testing.assert_allclose(stored, positions, atol=1e-6)
    # default options (the automatic shadow threshold): what a user gets
    threshold: list[str] = []
    _invoke(["reconstruct", str(near_run), *threshold, "--out", str(near_run / "near")])
    _invoke(["reconstruct", str(near_run), *threshold, "--lights", "directional",
             "--out", str(near_run / "dir")])
    # the same object lit from the same directions at infinity, calibrated from one sphere
    far_rig = tmp_path / "far.toml"
    text = (RIGS / "simulated-near.toml").read_text()
    lines = [line for line in text.splitlines() if not line.startswith("dome_radius")]
    far_rig.write_text("\n".join(lines))
    _invoke(["capture", "--rig", str(far_rig), "--out", str(far_run), "--quiet"])
    _invoke(["calibrate", str(far_run), "--sphere", "55,55,50"])
    assert not (far_run / "light_positions.txt").exists()
    assert not (far_run / "lights.dome").exists()
    _invoke(["reconstruct", str(far_run), *threshold, "--out", str(far_run / "sbl")])
    e_near, e_dir = _mean_error(near_run / "near"), _mean_error(near_run / "dir")
    e_far = _mean_error(far_run / "sbl")
    assert e_near <= 0.1 * e_dir, (e_near, e_dir)  # target 1/4
    assert e_near <= 1.3 * e_far, (e_near, e_far)  # target 1.5x
    metrics = json.loads((near_run / "near" / "metrics.json").read_text())
    assert metrics["light_model"] == "near" and metrics["near"]["rounds"] <= 30
    print(f"near-rig end to end: LED mean {error.mean():.4f} max {error.max():.4f}, "
          f"near {e_near:.3f} directional {e_dir:.3f} far {e_far:.3f}, outline "
          f"{metrics['near']['outline_height_px']} px")
    assert (near_run / "near" / "depth.npy").is_file()


@pytest.mark.parametrize(
    "args", [["--refine-lights", "1", "--fixed-intensities"], ["--method", "rpca"]]
)
def test_near_lights_refuse_what_they_cannot_do(tmp_path: Path, args: list[str]) -> None:
    h, w = 12, 16
    folder = tmp_path / "data"
    folder.mkdir()
    lights = render.random_light_directions(5, np.random.default_rng(0))
    for i in range(5):
        np.save(folder / f"{i:03d}.npy", np.full((h, w), 0.5, np.float32))
    np.savetxt(folder / "light_directions.txt", lights)
    np.savetxt(folder / "light_positions.txt", 300 * lights)
    result = CliRunner().invoke(app, ["reconstruct", str(folder), *args])
    assert result.exit_code == 2
    assert "--lights directional" in result.output
