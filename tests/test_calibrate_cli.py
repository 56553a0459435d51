"""`ps-lab calibrate` end to end: image folders, a simulated capture run, and every bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from ps_lab.cli import app
from ps_lab.render import random_light_directions, render_chrome_sphere

runner = CliRunner()
RIGS = Path(__file__).resolve().parents[1] / "rigs"


def angular_errors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


def write_png_folder(
    folder: Path, radiance: np.ndarray, rng: np.random.Generator, *, peak_over_white: float = 4.0
) -> None:
    folder.mkdir(parents=True)
    scaled = radiance * (peak_over_white / 50.0) + rng.normal(0.0, 2e-4, radiance.shape)
    counts = np.round(np.clip(scaled, 0.0, 1.0) * 65535.0).astype(np.uint16)
    for k, frame in enumerate(counts):
        assert cv2.imwrite(str(folder / f"L{k + 1:02d}.png"), frame)


def sphere_folder(
    tmp_path: Path,
    *,
    n: int = 16,
    center=(101.3, 96.8),
    radius: float = 70.0,
    shape=(200, 220),
    seed: int = 0,
    **kwargs,
) -> tuple[Path, np.ndarray]:
    rng = np.random.default_rng(seed)
    lights = random_light_directions(n, rng, max_zenith_deg=55.0)
    folder = tmp_path / "data"
    write_png_folder(folder, render_chrome_sphere(shape, center, radius, lights), rng, **kwargs)
    return folder, lights


def calibrate_cli(*args: str):
    return runner.invoke(app, ["calibrate", *args])


def assert_one_line_error(result, pattern: str, folder: Path, before: set[str]) -> None:
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    lines = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and pattern in lines[0], result.output
    assert {p.name for p in folder.iterdir()} == before  # no partial outputs, no staging folder


def test_image_folder(tmp_path):
    folder, lights = sphere_folder(tmp_path)
    result = calibrate_cli(str(folder))
    assert result.exit_code == 0, result.output
    assert "chrome sphere (101." in result.output and "[auto]" in result.output
    assert "16 lights calibrated" in result.output and "wrote" in result.output
    dirs = np.loadtxt(folder / "light_directions.txt")
    assert angular_errors(dirs, lights).mean() < 0.15
    np.testing.assert_array_equal(np.loadtxt(folder / "light_intensities.txt"), np.ones((16, 3)))
    record = json.loads((folder / "calibration.json").read_text())
    assert record["chrome_sphere"]["source"] == "auto" and len(record["lights"]) == 16
    assert (folder / "calibration.png").stat().st_size > 1000
    # Calibrating again reads the same frames (outputs are not taken for frames) and agrees.
    again = calibrate_cli(
        str(folder), "--out", str(tmp_path / "second"), "--sphere", "101.3,96.8,70"
    )
    assert again.exit_code == 0, again.output
    assert "[given]" in again.output
    dirs2 = np.loadtxt(tmp_path / "second" / "light_directions.txt")
    assert angular_errors(dirs2, lights).mean() < 0.15


def test_simulated_capture_run_calibrates_with_no_flags(tmp_path):
    run = tmp_path / "run"
    captured = runner.invoke(
        app,
        [
            "capture",
            "--rig",
            str(RIGS / "simulated.toml"),
            "--out",
            str(run),
            "--lights",
            "1-10",
            "--quiet",
        ],
    )
    assert captured.exit_code == 0, captured.output
    result = calibrate_cli(str(run))
    assert result.exit_code == 0, result.output
    assert "[rig]" in result.output and "intensities: matte sphere" in result.output
    truth = np.loadtxt(run / "simulation" / "light_directions_true.txt")
    err = angular_errors(np.loadtxt(run / "light_directions.txt"), truth)
    assert err.mean() <= 0.15 and err.max() <= 0.5, (err.mean(), err.max())
    true_int = np.loadtxt(run / "simulation" / "light_intensities_true.txt")
    fitted = np.loadtxt(run / "light_intensities.txt")
    np.testing.assert_allclose(fitted / fitted.mean(), true_int / true_int.mean(), rtol=0.04)


def test_no_sphere_found(tmp_path):
    folder = tmp_path / "data"
    write_png_folder(folder, np.full((6, 120, 140), 0.1), np.random.default_rng(1))
    before = {p.name for p in folder.iterdir()}
    assert_one_line_error(calibrate_cli(str(folder)), "no chrome sphere found", folder, before)


def test_sphere_cut_by_border(tmp_path):
    folder, _ = sphere_folder(tmp_path, center=(40.0, 100.0), radius=70.0)
    before = {p.name for p in folder.iterdir()}
    assert_one_line_error(calibrate_cli(str(folder)), "cut by the image border", folder, before)


def test_frame_without_highlight(tmp_path):
    rng = np.random.default_rng(3)
    lights = random_light_directions(10, rng, max_zenith_deg=50.0)
    radiance = render_chrome_sphere((200, 220), (105.2, 98.3), 70.0, lights)
    radiance[3] = np.minimum(radiance[3], 0.02)  # light 4 stayed dark
    folder = tmp_path / "data"
    write_png_folder(folder, radiance, rng)
    before = {p.name for p in folder.iterdir()}
    assert_one_line_error(
        calibrate_cli(str(folder)), "light 4 (L04.png): no highlight", folder, before
    )


def test_all_frames_saturated(tmp_path):
    folder, _ = sphere_folder(tmp_path, n=8, peak_over_white=5000.0)
    before = {p.name for p in folder.iterdir()}
    assert_one_line_error(
        calibrate_cli(str(folder), "--sphere", "101.3,96.8,70"),
        "all 8 frames are saturated",
        folder,
        before,
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--sphere", "10,20"], "--sphere expects CX,CY,R"),
        (["--roi", "a,b,c,d"], "--roi expects X,Y,W,H"),
        (["--focal-length", "50"], "--focal-length and --pixel-pitch go together"),
    ],
)
def test_bad_options(tmp_path, args, message):
    folder, _ = sphere_folder(tmp_path, n=4)
    before = {p.name for p in folder.iterdir()}
    assert_one_line_error(calibrate_cli(str(folder), *args), message, folder, before)


def test_missing_folder(tmp_path):
    result = calibrate_cli(str(tmp_path / "nope"))
    assert result.exit_code == 2 and "error:" in result.output and "Traceback" not in result.output
