"""``ps-lab capture`` with options, ports and output folders it cannot use, and its signals.

Exposures and light lists that are NaN, zero or beyond the rig; a camera or controller that
fails mid-run (one line, the complete frames kept for ``--resume``); serial ports that are not
ttys; ``--out`` onto a file or a dataset. Exit 2 (130 for a signal), one ``error:`` line.
"""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest
from helpers.bad_input import (
    SERIAL_PORTS,
    CaseTable,
    Workspace,
    finish,
    has,
    named_port,
    run,
    serial_port,
)
from helpers.hostile import assert_one_error_line, start, wait_until


CASES = CaseTable()
case = CASES.case


def capture_case(id: str, option: str, value: str):
    @case(id, (option,))
    def _(w):
        out = w.root / "out"
        return [
            "capture",
            "--rig",
            str(w.copy("rig") / "small.toml"),
            "--out",
            str(out),
            option,
            value,
            "-q",
        ]


capture_case("g2-exposure-negative", "--exposure", "-1")
capture_case("g2-exposure-zero", "--exposure", "0")
capture_case("g2-exposure-nan", "--exposure", "nan")
capture_case("g2-exposure-inf", "--exposure", "inf")
capture_case("g2-lights-zero", "--lights", "0")
capture_case("g2-lights-beyond-rig", "--lights", "1-99")
capture_case("g2-lights-backwards", "--lights", "5-2")
capture_case("g2-lights-word", "--lights", "all")
capture_case("g2-repeat-huge", "--repeat", "1000000000")
capture_case("g5-repeat-zero", "--repeat", "0")


@case("g5-capture-without-rig", ("--rig",))
def _(w):
    return ["capture", "--out", str(w.root / "out")]


# Group 6: one line, carrying what the user must know --------------------------------------------


FAULTY_CAMERA = (
    '\n[faults]\ncamera = [{ kind = "timeout", at = 3 }, { kind = "timeout", at = 4 }]\n'
)


@case(
    "g6-camera-fails-after-retry",
    lambda w: (str(w.root / "out"),),
    keeps_run=True,
    check=lambda w, r, line: has(line, "lights off", "--resume"),
)
def _(w):
    rig = w.copy("rig") / "small.toml"
    rig.write_text(rig.read_text().replace("timeout_s = 2.0", "timeout_s = 0.3") + FAULTY_CAMERA)
    return ["capture", "--rig", str(rig), "--out", str(w.root / "out")]


@case(
    "g6-controller-silent",
    ("small.toml", "controller", "out"),
    keeps_run=True,
    check=lambda w, r, line: has(line, "watchdog", "--resume"),
)
def _(w):
    rig = w.copy("rig") / "small.toml"
    rig.write_text(rig.read_text() + '\n[faults]\ncontroller = [{ kind = "silence", at = 6 }]\n')
    return ["capture", "--rig", str(rig), "--out", str(w.root / "out")]


@case("x-capture-out-is-a-file", lambda w: (str(w.root / "taken"),))
def _(w):
    (w.root / "taken").write_text("mine\n")
    return ["capture", "--rig", str(w.copy("rig") / "small.toml"), "--out", str(w.root / "taken")]


@case("x-capture-out-is-a-dataset", lambda w: (str(w.ds),))
def _(w):
    return ["capture", "--rig", str(w.copy("rig") / "small.toml"), "--out", str(w.png())]


def _serial_rig(w) -> Path:
    rig = w.copy("rig") / "small.toml"
    text = rig.read_text().replace(
        'driver = "simulated"\nlights', 'driver = "serial"\nport = "/dev/null"\nlights', 1
    )
    text = text.replace("seed = 2012", f'seed = 2012\nlight_state_file = "{w.root / "state.json"}"')
    rig.write_text(text)
    return rig


for _port_label, _port_text in SERIAL_PORTS:

    @case(f"x-capture-port-{_port_label}", named_port, timeout=60)
    def _(w, port=_port_text):
        rig = str(_serial_rig(w))
        return [
            "capture",
            "--rig",
            rig,
            "--out",
            str(w.root / "out"),
            "--port",
            serial_port(w, port),
            "-q",
        ]


@case("x-capture-resume-nothing", lambda w: (str(w.root / "out"),))
def _(w):
    return [
        "capture",
        "--rig",
        str(w.copy("rig") / "small.toml"),
        "--out",
        str(w.root / "out"),
        "--resume",
    ]


def _capture_args(w: Workspace) -> list[str]:
    rig = w.copy("rig") / "small.toml"
    rig.write_text(rig.read_text().replace("lights = 6", "lights = 12"))
    return ["capture", "--rig", str(rig), "--out", str(w.root / "out")]


@pytest.mark.parametrize(
    "sig",
    [signal.SIGHUP, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)],
    ids=lambda s: s.name,
)
def test_signal_during_capture(sig, workspace) -> None:
    args = _capture_args(workspace)
    frames = workspace.root / "out" / "frames"
    proc, out, err = start(args, workspace.root, workspace.home)
    wait_until(lambda: frames.is_dir() and len(list(frames.glob("*.dng"))) >= 2, proc)
    proc.send_signal(sig)
    result = finish(proc, out, err, timeout=60)
    line = assert_one_error_line(result, ("interrupted",), code=130)
    assert "lights off" in line and "--resume" in line, line
    resumed = run([*args, "--resume", "-q"], workspace.root, workspace.home)
    assert resumed.code == 0, resumed.stderr
    manifest = json.loads((workspace.root / "out" / "manifest.json").read_text())
    assert len(manifest["frames"]) == 13


#: The cases CI runs; ``pytest -m slow`` runs every case of the table.
CI_CASES = {
    "g2-exposure-nan",
    "g2-lights-beyond-rig",
    "g5-repeat-zero",
    "g6-camera-fails-after-retry",
    "g6-controller-silent",
    "x-capture-port-dev-null",
}
test_bad_input = CASES.test(CI_CASES)
