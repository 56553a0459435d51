"""The whole lab job through the CLI on a small simulated rig: capture → calibrate → reconstruct.

This is ``make demo`` in miniature: the simulated controller is served on a real pty and driven
through the OS serial layer, the simulated camera writes DNG files, calibration finds the chrome
sphere with no flags, and SBL with light refinement reconstructs the object.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from helpers.rigs import SMALL_SCENE
from typer.testing import CliRunner

from ps_lab.cli import app
from ps_lab.reconstruct.metrics import angular_errors_deg

SMALL_RIG = """
name = "simulated-small"

[controller]
driver = "simulated"
lights = 16
watchdog_ms = 5000
timeout_s = 0.5

[camera]
driver = "simulated"
exposure_s = 0.05
seed = 11

""" + SMALL_SCENE


def _invoke(args: list[str]) -> None:
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output


def test_capture_calibrate_reconstruct(tmp_path: Path) -> None:
    rig = tmp_path / "small.toml"
    rig.write_text(SMALL_RIG)
    run = tmp_path / "run"

    _invoke(["capture", "--rig", str(rig), "--out", str(run), "--quiet"])
    manifest = json.loads((run / "manifest.json").read_text())
    assert [f["kind"] for f in manifest["frames"]] == ["dark"] + ["light"] * 16

    # Calibration with no flags: the sphere comes from the rig snapshot in the manifest.
    _invoke(["calibrate", str(run)])
    estimated = np.loadtxt(run / "light_directions.txt")
    truth = np.loadtxt(run / "simulation" / "light_directions_true.txt")
    calibration_error = angular_errors_deg(estimated, truth)
    assert calibration_error.mean() < 0.5
    assert (run / "calibration.png").is_file()

    out = run / "recon" / "sbl"
    _invoke(["reconstruct", str(run), "--method", "sbl", "--refine-lights", "1", "--out", str(out)])
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["lights"] == 16
    assert metrics["angular_error_deg"]["mean"] < 2.0
    normals = np.load(out / "normals.npy")
    assert normals.shape == (120, 192, 3)
    for name in ("normal.png", "albedo.png", "corruption.png", "light_directions.txt"):
        assert (out / name).is_file(), name
