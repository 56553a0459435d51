"""`ps-lab capture` end to end through the CLI on the simulated rig, and every bad input."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import serial
from helpers.capture_runs import N_FRAMES, frame_hashes, write_rig
from typer.testing import CliRunner

from ps_lab.cli import app

runner = CliRunner()

SERIAL_RIG = """
[controller]
driver = "serial"
port = "{port}"
lights = 4
timeout_s = 0.1
[camera]
driver = "folder"
folder = "{folder}"
exposure_s = 0.05
timeout_s = 1.0
"""


def capture(*args: str):
    return runner.invoke(app, ["capture", *args, "--quiet"])


def error_lines(result) -> list[str]:
    text = result.output
    assert "Traceback" not in text
    return [line for line in text.splitlines() if line.startswith("error:")]


def assert_one_line_error(result, pattern: str, code: int = 2) -> None:
    assert result.exit_code == code, result.output
    lines = error_lines(result)
    assert len(lines) == 1, result.output
    assert pattern in lines[0], lines[0]


def test_capture_dry_run_resume_and_nothing_to_do(tmp_path: Path) -> None:
    rig = write_rig(tmp_path)
    run = tmp_path / "run"
    result = capture("--rig", str(rig), "--out", str(run), "--dry-run")
    assert result.exit_code == 0, result.output
    assert f"= {N_FRAMES} frames" in result.output and "rig ready" in result.output
    assert not run.exists()  # a dry run writes nothing

    result = capture("--rig", str(rig), "--out", str(run), "--lights", "1-3,6")
    assert result.exit_code == 0, result.output
    assert "5 of 5 frames saved" in result.output
    manifest = json.loads((run / "manifest.json").read_text())
    assert manifest["plan"] == {"lights": [1, 2, 3, 6], "repeat": 1}
    assert [r["file"] for r in manifest["frames"]][-1] == "frames/0004-L06-r0.dng"

    result = capture("--rig", str(rig), "--out", str(run), "--resume")
    assert result.exit_code == 0 and "nothing to do" in result.output

    # Without --resume an existing run is never touched.
    before = frame_hashes(run)
    assert_one_line_error(capture("--rig", str(rig), "--out", str(run)), "add --resume")
    assert frame_hashes(run) == before


def test_capture_overrides_and_resume_refusal(tmp_path: Path) -> None:
    rig = write_rig(tmp_path)
    run = tmp_path / "run"
    result = capture(
        "--rig", str(rig), "--out", str(run), "--lights", "2", "--repeat", "2", "--exposure", "0.02"
    )
    assert result.exit_code == 0, result.output
    manifest = json.loads((run / "manifest.json").read_text())
    assert manifest["camera_settings"]["exposure_s"] == 0.02
    assert all(r["exposure_s"] == 0.02 for r in manifest["frames"])
    assert [r["repeat"] for r in manifest["frames"]] == [0, 0, 1]
    # Same rig but the file's exposure: the settings changed, so resume refuses.
    assert_one_line_error(
        capture("--rig", str(rig), "--out", str(run), "--resume"), "camera.exposure_s"
    )
    assert_one_line_error(
        capture(
            "--rig", str(rig), "--out", str(run), "--resume", "--exposure", "0.02", "--lights", "3"
        ),
        "--lights differs",
    )
    assert_one_line_error(
        capture("--rig", str(rig), "--out", str(run), "--port", "/dev/null"), "--port applies"
    )


def test_capture_stops_with_one_line_and_resumes(tmp_path: Path) -> None:
    faults = '[faults]\ncamera = [{ kind = "truncated", at = 4 }]\n'
    faulty = write_rig(tmp_path, faults=faults, retries=0, name="faulty.toml")
    run = tmp_path / "run"
    result = capture("--rig", str(faulty), "--out", str(run))
    assert_one_line_error(result, "capture stopped at frame 3 (light 3)")
    assert "3 of 9 frames saved" in error_lines(result)[0] and "--resume" in error_lines(result)[0]
    result = capture("--rig", str(write_rig(tmp_path)), "--out", str(run), "--resume")
    assert result.exit_code == 0, result.output
    reference = tmp_path / "reference"
    assert capture("--rig", str(write_rig(tmp_path)), "--out", str(reference)).exit_code == 0
    assert frame_hashes(run) == frame_hashes(reference)


def test_bad_rig_files(tmp_path: Path) -> None:
    out = str(tmp_path / "run")
    assert_one_line_error(
        capture("--rig", str(tmp_path / "missing.toml"), "--out", out), "does not exist"
    )
    bad = tmp_path / "bad.toml"
    bad.write_text("[controller\n")
    assert_one_line_error(capture("--rig", str(bad), "--out", out), "not valid TOML")
    unknown = tmp_path / "unknown.toml"
    unknown.write_text(
        write_rig(tmp_path).read_text().replace('driver = "simulated"', 'driver = "bluetooth"', 1)
    )
    assert_one_line_error(
        capture("--rig", str(unknown), "--out", out),
        "[controller] driver: unknown value 'bluetooth'",
    )
    typo = tmp_path / "typo.toml"
    typo.write_text(write_rig(tmp_path).read_text().replace("exposure_s", "exposure", 1))
    assert_one_line_error(capture("--rig", str(typo), "--out", out), "exposure")
    assert_one_line_error(
        capture("--rig", str(write_rig(tmp_path)), "--out", out, "--lights", "0-3"), "--lights"
    )
    assert not (tmp_path / "run").exists()


def test_output_folder_that_is_not_a_run(tmp_path: Path) -> None:
    rig = str(write_rig(tmp_path))
    other = tmp_path / "photos"
    other.mkdir()
    (other / "holiday.jpg").write_bytes(b"jpeg")
    assert_one_line_error(
        capture("--rig", rig, "--out", str(other)), "exists and is not a ps-lab run"
    )
    assert_one_line_error(
        capture("--rig", rig, "--out", str(other), "--resume"), "not a capture run"
    )
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    assert_one_line_error(capture("--rig", rig, "--out", str(a_file)), "is not a folder")
    assert sorted(p.name for p in other.iterdir()) == ["holiday.jpg"]


def serial_rig(tmp_path: Path, port: str) -> Path:
    folder = tmp_path / "tether"
    folder.mkdir(exist_ok=True)
    path = tmp_path / "serial.toml"
    path.write_text(SERIAL_RIG.format(port=port, folder=folder))
    return path


def test_port_that_does_not_exist(tmp_path: Path) -> None:
    rig = serial_rig(tmp_path, str(tmp_path / "ttyACM9"))
    result = capture("--rig", str(rig), "--out", str(tmp_path / "run"))
    assert_one_line_error(result, "does not exist")
    # --port overrides the file and is checked the same way.
    result = capture("--rig", str(rig), "--out", str(tmp_path / "run"), "--port", "/dev/ttyUSB77")
    assert_one_line_error(result, "/dev/ttyUSB77 does not exist")


def test_port_busy(tmp_path: Path) -> None:
    master, slave = os.openpty()
    path = os.ttyname(slave)
    try:
        with serial.Serial(path, exclusive=True):  # another program holds the port
            result = capture(
                "--rig", str(serial_rig(tmp_path, path)), "--out", str(tmp_path / "run")
            )
        assert_one_line_error(result, "is busy")
    finally:
        os.close(master)
        os.close(slave)


def test_permission_denied_simulated(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Root passes every permission check, so the OS refusal is simulated at os.open for this path.
    master, slave = os.openpty()
    path = os.ttyname(slave)
    real_open = os.open

    def guarded_open(file, flags, *args, **kwargs):
        if os.fspath(file) == path:
            raise PermissionError(13, "Permission denied", path)
        return real_open(file, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", guarded_open)
    try:
        result = capture("--rig", str(serial_rig(tmp_path, path)), "--out", str(tmp_path / "run"))
    finally:
        monkeypatch.undo()
        os.close(master)
        os.close(slave)
    assert_one_line_error(result, "permission denied")


@pytest.mark.skipif(
    os.geteuid() == 0, reason="root ignores file modes; see test_permission_denied_simulated"
)
def test_permission_denied_by_file_mode(tmp_path: Path) -> None:
    port = tmp_path / "ttyFAKE"
    port.write_text("")
    port.chmod(0)
    result = capture("--rig", str(serial_rig(tmp_path, str(port))), "--out", str(tmp_path / "run"))
    assert_one_line_error(result, "permission denied")


def test_no_controller_answers(tmp_path: Path) -> None:
    # A serial device with nothing behind it (the other end of a pty nobody serves).
    master, slave = os.openpty()
    try:
        result = capture(
            "--rig", str(serial_rig(tmp_path, os.ttyname(slave))), "--out", str(tmp_path / "run")
        )
    finally:
        os.close(master)
        os.close(slave)
    assert_one_line_error(result, "no ps-lab light controller answers")
