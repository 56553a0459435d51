"""``ps-lab rig check``, ``rig serve-sim`` and ``rig serve-firmware`` with bad options and signals.

NaN or infinite timeouts and dwells, no port, zero lights, firmware files that are not AVR
executables; a controller that falls silent mid-check names the light left lit. Exit 2 (130 for
a signal), one ``error:`` line, no temporary folder left.
"""

from __future__ import annotations

import re
import signal
import struct
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from helpers.bad_input import (
    SERIAL_PORTS,
    CaseTable,
    Workspace,
    finish,
    named_port,
    run,
    serial_port,
)
from helpers.hostile import assert_one_error_line, start, temporary_leftovers, wait_until


CASES = CaseTable()
case = CASES.case
option_case = CASES.option_case


for _option, _value in (
    ("--timeout", "nan"),
    ("--dwell", "nan"),
    ("--dwell", "inf"),
    ("--timeout", "inf"),
):


    @case(f"g2-rig-check{_option}-{_value}", (_option,), timeout=30)
    def _(w, option=_option, value=_value):
        return ["rig", "check", "--port", "pslabsim://", "--lights", "24", option, value]


@case("g2-serve-sim-delay-nan", ("--delay",), timeout=30)
def _(w):
    return ["rig", "serve-sim", "--lights", "4", "--delay", "nan"]


option_case("g5-serve-sim-zero-lights", ["rig", "serve-sim"], "--lights", "0", where="")


@case("g5-rig-check-without-port", ("--port",))
def _(w):
    return ["rig", "check", "--lights", "4"]


for _port_label, _port_text in SERIAL_PORTS:

    @case(f"x-rig-check-port-{_port_label}", named_port, timeout=60)
    def _(w, port=_port_text):
        return ["rig", "check", "--port", serial_port(w, port), "--lights", "4"]


@contextmanager
def simulated_controller(workspace: Workspace, *faults: str) -> Iterator[str]:
    """Serve a 4-light simulated controller (``ps-lab rig serve-sim``); yield its port."""
    server, sout, serr = start(
        ["rig", "serve-sim", "--lights", "4", *faults], workspace.root, workspace.home
    )
    try:
        wait_until(lambda: sout.stat().st_size > 0, server)
        yield sout.read_text().split()[0]
    finally:
        server.send_signal(signal.SIGINT)
        finish(server, sout, serr, timeout=30)


def _check_home(workspace: Workspace) -> Path:
    home = workspace.root / "h2"
    home.mkdir()
    return home


def test_signal_during_rig_check(workspace) -> None:
    with simulated_controller(workspace) as port:
        proc, out, err = start(
            ["rig", "check", "--port", port, "--lights", "4", "--dwell", "5"],
            workspace.root,
            _check_home(workspace),
        )
        time.sleep(3)
        proc.send_signal(signal.SIGTERM)
        result = finish(proc, out, err, timeout=30)
    line = assert_one_error_line(result, ("interrupted",), code=130)
    assert "lights off" in line or "lit" in line, line


def test_rig_check_names_the_light_left_lit(workspace) -> None:
    """A controller that falls silent mid-check: the one line says which light may be lit."""
    with simulated_controller(workspace, "--fault", "silence@6") as port:
        result = run(
            ["rig", "check", "--port", port, "--lights", "4"],
            workspace.root,
            _check_home(workspace),
        )
    line = assert_one_error_line(result, (port,))
    assert re.search(r"light \d may still be lit: .*watchdog", line), line


def _elf32(machine: int, *, cut: int | None = None) -> bytes:
    """A minimal 32-bit little-endian ELF executable for ``machine`` (one loadable segment)."""
    code = bytes(64)
    header = b"\x7fELF" + bytes([1, 1, 1]) + bytes(9)
    header += struct.pack("<HHIIIIIHHHHHH", 2, machine, 1, 0, 52, 0, 0, 52, 32, 1, 40, 0, 0)
    segment = struct.pack("<IIIIIIII", 1, 84, 0, 0, len(code), len(code), 5, 2)
    data = header + segment + code
    return data if cut is None else data[:cut]


for _label, _content in (
    ("empty", b""),
    ("not-elf", b"#!/bin/sh\necho firmware\n"),
    ("header-cut", _elf32(83, cut=40)),
    ("program-cut", _elf32(83, cut=100)),
    ("arm", _elf32(40)),
    ("x86-64", b"\x7fELF\x02\x01\x01" + bytes(57)),
):

    @case(f"s6-serve-firmware-elf-{_label}", lambda w: (str(w.root / "sketch.elf"),),
          check=lambda w, r, line: _no_temporary(w), timeout=60)
    def _(w, content=_content):
        (w.root / "sketch.elf").write_bytes(content)
        return ["rig", "serve-firmware", "--elf", str(w.root / "sketch.elf")]


def _no_temporary(w: Workspace) -> None:
    assert not temporary_leftovers(w.home), temporary_leftovers(w.home)


def test_serve_firmware_refused_by_simavr_leaves_no_temporary_folder(tmp_path) -> None:
    """An AVR ELF simavr cannot load: one line naming it, and the state folder is gone."""
    from ps_lab.capture.simulated.avr_firmware import missing_packages

    missing = missing_packages(sketch=False)
    if missing:
        pytest.skip(f"simavr harness not buildable here: {' '.join(missing)} missing")
    home, root = tmp_path / "home", tmp_path / "case"
    home.mkdir()
    root.mkdir()
    elf = root / "blank.elf"
    elf.write_bytes(_elf32(83))  # a sound header, and nothing simavr can load
    result = run(["rig", "serve-firmware", "--elf", str(elf), "--pins", "3,5,6"], root, home)
    assert_one_error_line(result, (str(elf),))
    assert not temporary_leftovers(home), temporary_leftovers(home)


#: The cases CI runs; ``pytest -m slow`` runs every case of the table.
CI_CASES = {
    "g2-rig-check--dwell-inf",
    "x-rig-check-port-regular-file",
    "s6-serve-firmware-elf-arm",
    "s6-serve-firmware-elf-empty",
}
test_bad_input = CASES.test(CI_CASES)
