"""A capture end to end with the real firmware in the loop (rigs/simulated-firmware.toml).

The compiled sketch runs in simavr behind a pty; the simulated camera renders the scene under the
lights whose pins the emulated MCU drives, in the rig's wiring. Calibration then recovers every
light where wiring and sketch agree, and a wiring that disagrees with the sketch's pin table (two
swapped wires) shows in the images: exactly those lights come out in the wrong place.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from ps_lab.capture.rig import load_rig
from ps_lab.cli import app
from ps_lab.errors import RigError
from ps_lab.reconstruct.metrics import angular_errors_deg

RIG = Path(__file__).resolve().parents[1] / "rigs" / "simulated-firmware.toml"


def capture_and_calibrate(rig: Path, run: Path) -> np.ndarray:
    """Capture and calibrate through the CLI; return each light's direction error in degrees."""
    for args in (
        ["capture", "--rig", str(rig), "--out", str(run), "--quiet"],
        ["calibrate", str(run)],
    ):
        result = CliRunner().invoke(app, args)
        assert result.exit_code == 0, result.output
    estimated = np.loadtxt(run / "light_directions.txt")
    truth = np.loadtxt(run / "simulation" / "light_directions_true.txt")
    return angular_errors_deg(estimated, truth)


@pytest.fixture
def firmware_env(firmware_cache, monkeypatch):
    monkeypatch.setenv("PS_LAB_CACHE", str(firmware_cache))


def test_capture_through_the_emulated_firmware_lights_each_light_by_its_pin(firmware_env, tmp_path):
    errors = capture_and_calibrate(RIG, tmp_path / "run")
    assert errors.shape == (12,)
    assert errors.max() < 1.0, errors


def test_wiring_that_disagrees_with_the_pin_table_shows_in_the_images(firmware_env, tmp_path):
    # The rig is wired with lights 1 and 2 swapped (pins 5 and 3), the sketch drives its table.
    text = RIG.read_text()
    swapped, count = re.subn(r"pins = \[3, 5,", "pins = [5, 3,", text)
    assert count == 1
    rig = tmp_path / "swapped.toml"
    rig.write_text(swapped)
    errors = capture_and_calibrate(rig, tmp_path / "run")
    assert errors[:2].min() > 5.0, errors
    assert errors[2:].max() < 1.0, errors


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (("pins = [3, 5,", "pins = [5,"), r"\[controller\] pins: 11 pins for 12 lights"),
        (("pins = [3, 5,", "pins = [1, 5,"), r"own Uno pin 2-19"),
        (("pins = [3, 5,", "pins = [5, 5,"), r"own Uno pin 2-19"),
        (('driver = "firmware"', 'driver = "firmware"\nport = "/dev/ttyACM0"'), r"remove the port"),
    ],
)
def test_firmware_rig_wiring_is_checked(tmp_path, change, message):
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG.read_text().replace(*change, 1))
    with pytest.raises(RigError, match=message):
        load_rig(rig)
