"""Chrome-sphere light calibration: seeded round trips on rendered spheres (16-bit and DNG)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

import ps_lab.calibration._calibration_outputs as report
from ps_lab.calibration import (
    Circle,
    calibrate,
    fit_circle,
    highlights_from_light_directions,
    light_directions_from_highlights,
    rig_circles,
    write_calibration,
)
from ps_lab.errors import CalibrationError
from ps_lab.io.dng import write_dng
from ps_lab.io.raw import load_raw
from ps_lab.render import (
    random_light_directions,
    render,
    render_chrome_sphere,
    sphere_surface,
)


def angular_errors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


def quantised_frames(
    radiance: np.ndarray,
    rng: np.random.Generator,
    *,
    peak_over_white: float = 4.0,
    noise: float = 2e-4,
    light_radiance: float = 50.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Expose rendered radiance so a highlight peaks at ``peak_over_white`` x the white level,
    add noise, clip and quantise to 16 bits. Returns frames in [0, 1] and the saturation mask."""
    scaled = radiance * (peak_over_white / light_radiance) + rng.normal(0.0, noise, radiance.shape)
    counts = np.round(np.clip(scaled, 0.0, 1.0) * 65535.0)
    return (counts / 65535.0).astype(np.float32), counts >= 65535


def chrome_frames(
    radius: float, n_lights: int, seed: int, *, max_zenith_deg: float = 60.0, **kwargs
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, float]]:
    rng = np.random.default_rng(seed)
    lights = random_light_directions(n_lights, rng, max_zenith_deg=max_zenith_deg)
    size = int(2 * radius + 90)
    center = (size / 2 + rng.uniform(-15, 15), size / 2 + rng.uniform(-15, 15))
    radiance = render_chrome_sphere((size, size + 30), center, radius, lights)
    frames, saturated = quantised_frames(radiance, rng, **kwargs)
    return frames, saturated, lights, center


# --- geometry -----------------------------------------------------------------------------------


def test_mirror_law_round_trip(rng):
    lights = random_light_directions(50, rng, max_zenith_deg=85.0)
    circle = Circle(120.3, 97.8, 61.7)
    highlights = highlights_from_light_directions(lights, circle)
    back = light_directions_from_highlights(highlights, circle)
    assert angular_errors(back, lights).max() < 1e-6


def test_mirror_law_frame_conventions():
    circle = Circle(100.0, 100.0, 50.0)
    # Centre: light at the camera. Up in the image (smaller row) is +y; right is +x.
    pts = np.array(
        [
            [100.0, 100.0],
            [100.0, 100.0 - 50 * np.sin(np.radians(30))],
            [100.0 + 50 * np.sin(np.radians(30)), 100.0],
        ]
    )
    dirs = light_directions_from_highlights(pts, circle)
    np.testing.assert_allclose(dirs[0], [0, 0, 1], atol=1e-12)
    # Normal at 30 degrees from the view axis reflects the view vector to 60 degrees.
    np.testing.assert_allclose(
        dirs[1], [0, np.sin(np.radians(60)), np.cos(np.radians(60))], atol=1e-12
    )
    np.testing.assert_allclose(
        dirs[2], [np.sin(np.radians(60)), 0, np.cos(np.radians(60))], atol=1e-12
    )


def test_perspective_correction(rng):
    lights = random_light_directions(20, rng, max_zenith_deg=60.0)
    circle = Circle(400.0, 250.0, 80.0)
    highlights = highlights_from_light_directions(lights, circle)
    ortho = light_directions_from_highlights(highlights, circle)
    far = light_directions_from_highlights(
        highlights, circle, focal_length_px=1e9, principal_point=(320, 240)
    )
    assert angular_errors(far, ortho).max() < 1e-5
    # A sphere off the optical axis of a wide lens: its view vectors tilt by about the field angle.
    near = light_directions_from_highlights(
        highlights, circle, focal_length_px=800.0, principal_point=(320, 240)
    )
    shift = angular_errors(near, ortho)
    field = np.degrees(np.arctan(np.hypot(400 - 320, 250 - 240) / 800.0))
    assert 0.3 * field < shift.mean() < 2.5 * field


def test_fit_circle_geometric(rng):
    t = rng.uniform(0, 2 * np.pi, 200)
    pts = np.column_stack([31.2 + 47.9 * np.cos(t), -12.5 + 47.9 * np.sin(t)]) + rng.normal(
        0, 0.01, (200, 2)
    )
    c = fit_circle(pts)
    assert abs(c.x - 31.2) < 0.01 and abs(c.y + 12.5) < 0.01 and abs(c.radius - 47.9) < 0.01
    with pytest.raises(CalibrationError):
        fit_circle(pts[:2])


# --- accuracy on rendered spheres ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("radius", "n_lights", "peak", "mean_max", "max_max"),
    [(100, 40, 4.0, 0.15, 0.5), (97, 60, 20.0, 0.15, 0.5), (40, 20, 12.0, 0.3, 0.8)],
)
def test_automatic_calibration_accuracy(radius, n_lights, peak, mean_max, max_max):
    frames, saturated, lights, center = chrome_frames(
        radius, n_lights, seed=radius + n_lights, peak_over_white=peak
    )
    assert saturated.any(axis=(1, 2)).all()  # every highlight clips
    cal = calibrate(frames, saturated=saturated)
    assert cal.circle_source == "auto"
    assert np.hypot(cal.circle.x - center[0], cal.circle.y - center[1]) < 0.05
    assert abs(cal.circle.radius - radius) < 0.05
    assert cal.residual < 0.2
    err = angular_errors(cal.light_directions, lights)
    assert err.mean() <= mean_max and err.max() <= max_max, (err.mean(), err.max())
    np.testing.assert_array_equal(cal.light_intensities, np.ones((n_lights, 3)))
    assert cal.warnings == []


def test_saturation_inferred_without_mask():
    frames, _, lights, _ = chrome_frames(80, 24, seed=5, peak_over_white=6.0)
    cal = calibrate(frames)  # the clipping plateau at 1.0 is found without a mask
    assert angular_errors(cal.light_directions, lights).mean() < 0.15


def test_simulated_dng_half_size(tmp_path):
    rng = np.random.default_rng(11)
    lights = random_light_directions(24, rng, max_zenith_deg=55.0)
    full_radius, black, white = 200.0, 512, 16383
    center = (271.3, 236.6)
    radiance = render_chrome_sphere((480, 560), center, full_radius, lights)
    frames, saturated = [], []
    for k in range(len(lights)):
        dn = black + radiance[k] * (3.0 / 50.0) * (white - black)
        dn = (
            dn
            + rng.normal(0.0, 2.0, dn.shape)
            + rng.normal(0.0, 1.0, dn.shape) * np.sqrt(np.maximum(dn - black, 0) * 0.5)
        )
        path = tmp_path / f"L{k:02d}.dng"
        write_dng(
            path,
            np.clip(np.round(dn), 0, white).astype(np.uint16),
            black_level=black,
            white_level=white,
        )
        raw = load_raw(path)
        frames.append(raw.image)
        saturated.append(raw.saturated)
    images = np.stack(frames)
    assert images.shape[1:3] == (240, 280)
    cal = calibrate(images, saturated=np.stack(saturated))
    # Half-size binning: pixel i averages full-res pixels 2i..2i+1: x_half = (x + 0.5) / 2 - 0.5.
    assert abs(cal.circle.radius - full_radius / 2) < 0.05
    assert abs(cal.circle.x - ((center[0] + 0.5) / 2 - 0.5)) < 0.05
    err = angular_errors(cal.light_directions, lights)
    assert err.mean() <= 0.15 and err.max() <= 0.5, (err.mean(), err.max())


def test_matte_sphere_intensities():
    rng = np.random.default_rng(21)
    n = 20
    lights = random_light_directions(n, rng, max_zenith_deg=50.0)
    intensities = rng.uniform(0.6, 1.4, (n, 1)) * rng.uniform(0.9, 1.1, (n, 3))
    shape = (250, 480)
    chrome = render_chrome_sphere(shape, (120.4, 124.2), 90.0, lights)
    matte = render(
        sphere_surface(shape, (350.7, 125.1), 95.0, albedo=np.array([0.6, 0.6, 0.6])),
        lights,
        intensities,
        cast_shadows=False,
    )
    radiance = chrome[..., None] * intensities[:, None, None, :] + matte * 10.0
    frames, saturated = quantised_frames(radiance, rng, peak_over_white=4.0)
    cal = calibrate(frames, saturated=saturated.any(axis=-1), matte_hint=(351.0, 125.0, 94.0))
    assert cal.matte_circle is not None and abs(cal.matte_circle.radius - 95.0) < 0.1
    expected = intensities / intensities.mean()
    np.testing.assert_allclose(cal.light_intensities, expected, rtol=0.01)
    assert abs(cal.light_intensities.mean() - 1.0) < 1e-9
    assert angular_errors(cal.light_directions, lights).mean() < 0.15


def test_given_and_rig_circles():
    frames, saturated, lights, center = chrome_frames(70, 20, seed=3)
    given = calibrate(frames, saturated=saturated, sphere=(center[0], center[1], 70.0))
    assert given.circle_source == "given" and given.circle == Circle(center[0], center[1], 70.0)
    assert given.residual < 0.2
    rig = calibrate(frames, saturated=saturated, sphere_hint=(center[0] + 3, center[1] - 2, 73.0))
    assert rig.circle_source == "rig"
    assert np.hypot(rig.circle.x - center[0], rig.circle.y - center[1]) < 0.05
    assert angular_errors(rig.light_directions, lights).mean() < 0.15
    # A wrong nominal circle (the rig was moved) falls back to the automatic search, with a warning.
    moved = calibrate(frames, saturated=saturated, sphere_hint=(20.0, 20.0, 15.0))
    assert moved.circle_source == "auto" and any("not confirmed" in w for w in moved.warnings)
    assert np.hypot(moved.circle.x - center[0], moved.circle.y - center[1]) < 0.05
    manifest = {"rig": {"calibration": {"chrome_sphere": {"center": [62.0, 61.5], "radius": 52.0}}}}
    assert rig_circles(manifest) == (Circle(62.0, 61.5, 52.0), None)
    assert rig_circles(None) == (None, None)
    with pytest.raises(CalibrationError, match="chrome_sphere"):
        rig_circles({"rig": {"calibration": {"chrome_sphere": {"centre": [1, 2]}}}})


def test_second_blob_is_rejected_with_warning():
    frames, saturated, lights, _ = chrome_frames(90, 12, seed=8)
    # A fake inter-reflection: a copy of light 3's highlight, dimmer, elsewhere on the sphere.
    hl = highlights_from_light_directions(
        lights[2:3], Circle(*calibrate(frames, saturated=saturated).circle)
    )[0]
    x, y = int(round(hl[0])), int(round(hl[1]))
    patch = frames[2, y - 4 : y + 5, x - 4 : x + 5].copy()
    frames[2, y + 26 : y + 35, x - 4 : x + 5] = np.maximum(
        frames[2, y + 26 : y + 35, x - 4 : x + 5], 0.8 * patch
    )
    cal = calibrate(frames, saturated=saturated)
    assert any(w.startswith("light 3:") and "second bright spot" in w for w in cal.warnings)
    assert angular_errors(cal.light_directions, lights)[2] < 0.3


# --- bad input ------------------------------------------------------------------------------------


def test_no_sphere_found(rng):
    frames = rng.normal(0.01, 0.002, (10, 200, 220)).astype(np.float32)
    with pytest.raises(CalibrationError, match="no chrome sphere found"):
        calibrate(frames)


def test_sphere_cut_by_border():
    rng = np.random.default_rng(2)
    lights = random_light_directions(16, rng, max_zenith_deg=40.0)
    radiance = render_chrome_sphere((220, 240), (45.0, 110.0), 70.0, lights)
    frames, saturated = quantised_frames(radiance, rng)
    with pytest.raises(CalibrationError, match="cut by the image border"):
        calibrate(frames, saturated=saturated)
    with pytest.raises(CalibrationError, match="cut by the image border"):
        calibrate(frames, saturated=saturated, sphere=(45.0, 110.0, 70.0))


def test_frame_without_highlight():
    rng = np.random.default_rng(4)
    lights = random_light_directions(12, rng, max_zenith_deg=50.0)
    radiance = render_chrome_sphere((230, 230), (115.2, 114.7), 80.0, lights)
    radiance[5] = np.minimum(radiance[5], 0.02)  # light 6 did not switch on: ambient only
    frames, saturated = quantised_frames(radiance, rng)
    with pytest.raises(CalibrationError, match=r"^light 6 \(f6\): no highlight"):
        calibrate(frames, saturated=saturated, names=[f"f{k + 1}" for k in range(12)])


def test_highlight_outside_safe_radius():
    rng = np.random.default_rng(6)
    lights = random_light_directions(8, rng, max_zenith_deg=40.0)
    t = np.radians(140.0)  # normal at 70 degrees: 0.94 of the radius
    lights[2] = [np.sin(t), 0.0, np.cos(t)]
    radiance = render_chrome_sphere((230, 230), (115.0, 115.0), 80.0, lights)
    frames, saturated = quantised_frames(radiance, rng)
    with pytest.raises(CalibrationError, match="light 3.*outside the safe radius"):
        calibrate(frames, saturated=saturated)


def test_all_frames_saturated():
    frames, saturated, _, center = chrome_frames(60, 10, seed=9, peak_over_white=2000.0)
    frames = np.where(frames > 0.0005, 1.0, frames).astype(np.float32)  # the whole sphere clips
    with pytest.raises(CalibrationError, match="all 10 frames are saturated"):
        calibrate(frames, saturated=frames >= 1.0, sphere=(center[0], center[1], 60.0))


# --- outputs --------------------------------------------------------------------------------------


def test_write_calibration_outputs(tmp_path):
    frames, saturated, lights, _ = chrome_frames(60, 16, seed=12)
    cal = calibrate(frames, saturated=saturated, names=[f"L{k + 1:02d}.png" for k in range(16)])
    paths = write_calibration(cal, tmp_path / "out")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(paths)
    dirs = np.loadtxt(paths["light_directions.txt"])
    assert dirs.shape == (16, 3) and angular_errors(dirs, lights).mean() < 0.2
    assert np.loadtxt(paths["light_intensities.txt"]).shape == (16, 3)
    record = json.loads(paths["calibration.json"].read_text())
    assert record["chrome_sphere"]["radius"] == pytest.approx(cal.circle.radius, abs=1e-3)
    assert [d["frame"] for d in record["lights"]] == cal.names
    np.testing.assert_allclose(
        [d["highlight"] for d in record["lights"]], cal.highlights, atol=1e-3
    )

    picture = cv2.imread(str(paths["calibration.png"]))
    assert picture is not None and picture.shape[1] > picture.shape[0] > 300


def test_write_calibration_leaves_nothing_on_failure(tmp_path, monkeypatch):
    frames, saturated, _, _ = chrome_frames(50, 10, seed=13)
    cal = calibrate(frames, saturated=saturated)
    out = tmp_path / "run"
    out.mkdir()
    (out / "light_directions.txt").write_text("old\n")

    monkeypatch.setattr(report, "imwrite", lambda *a, **k: False)
    with pytest.raises(CalibrationError, match="cannot write"):
        write_calibration(cal, out)
    assert sorted(p.name for p in out.iterdir()) == ["light_directions.txt"]
    assert (out / "light_directions.txt").read_text() == "old\n"


@pytest.mark.slow
@pytest.mark.parametrize("radius", [40, 55, 70, 85, 100, 115, 130, 150])
def test_error_against_radius_sweep(radius):
    # The table in docs/calibration.md: 40 lights, peaks 4x the white level, 16-bit, noise 2e-4.
    errs = []
    for seed in range(3):
        frames, saturated, lights, _ = chrome_frames(radius, 40, seed=1000 * seed + radius)
        errs.append(angular_errors(calibrate(frames, saturated=saturated).light_directions, lights))
    err = np.concatenate(errs)
    limit = 0.15 if radius >= 85 else 0.35
    assert err.mean() <= limit, err.mean()


def test_extended_light_source_correction():
    # A 5-degree light: the highlight's centroid sits at cos(b) of the mirror point (b = 2.5 deg);
    # the correction from the blob's second moments removes that radial bias.
    rng = np.random.default_rng(17)
    lights = random_light_directions(16, rng, max_zenith_deg=75.0)
    radiance = render_chrome_sphere(
        (330, 330), (165.2, 164.6), 130.0, lights, light_angular_radius_deg=5.0
    )
    frames, saturated = quantised_frames(radiance, rng)
    cal = calibrate(frames, saturated=saturated)
    assert 4.0 < np.median(cal.source_radius_deg) < 8.0
    centre = np.array(cal.circle[:2])
    uncorrected = (
        centre + (cal.highlights - centre) * np.cos(np.radians(cal.source_radius_deg / 2))[:, None]
    )
    err = angular_errors(cal.light_directions, lights)
    err_raw = angular_errors(light_directions_from_highlights(uncorrected, cal.circle), lights)
    assert err.mean() < 0.06 and err.mean() < 0.8 * err_raw.mean(), (err.mean(), err_raw.mean())
