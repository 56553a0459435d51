"""The real firmware in the loop: the compiled sketch runs in simavr, driven through its pty.

The Arduino sketch in rigs/firmware is built for an Uno (arduino-mk) and run by the simavr harness
in rigs/firmware/simavr; every test talks to it through the operating system's serial layer, as to
a board on /dev/ttyACM0, and checks the light pins the emulated MCU drives. Without Debian's
toolchain (arduino-mk, arduino-core-avr, libsimavr-dev, gcc, make) these tests skip, naming the
packages; `.ci/run` installs them.
"""

from __future__ import annotations

import os
import time

import pytest
import serial
from helpers.device_servers import switch_through_served_device
from typer.testing import CliRunner

from ps_lab.capture.light_controllers import LightState, SerialLightController
from ps_lab.capture.simulated import avr_firmware
from ps_lab.capture.simulated.avr_firmware import EmulatedFirmware, sketch_pins
from ps_lab.cli import app
from ps_lab.errors import RigError

PINS = sketch_pins()
LIGHTS = len(PINS)
PWM_PINS = {3, 5, 6, 9, 10, 11}  # an Uno's PWM pins: the others switch fully on at any level
DRIVER = dict(reply_timeout=0.5, boot_timeout=2.5, retries=3)


@pytest.fixture
def board(firmware_cache):
    with EmulatedFirmware(build_dir=firmware_cache / "firmware") as running:
        yield running


def expected_pins(lit: set[int], level: int) -> tuple[frozenset[int], tuple[int, ...]]:
    """What the pins must show when the controller has ``lit`` lit at ``level``."""
    levels = tuple(
        (level if PINS[i - 1] in PWM_PINS else 255) if i in lit and level > 0 else 0
        for i in range(1, LIGHTS + 1)
    )
    return frozenset(i for i in lit if level > 0), levels


def assert_pins(board: EmulatedFirmware, lit: set[int], level: int) -> None:
    state = board.pin_state()
    assert (state.lit, state.levels) == expected_pins(lit, level)


class RawPort:
    """The pty opened like a terminal program would, one command line at a time."""

    def __init__(self, path: str) -> None:
        self.port = serial.Serial(path, 115200, timeout=0.05, exclusive=True)

    def line(self, timeout: float = 1.0) -> bytes | None:
        deadline = time.monotonic() + timeout
        data = b""
        while time.monotonic() < deadline:
            data += self.port.read(1)
            if data.endswith(b"\n"):
                return data[:-1]
        return None

    def ask(self, command: bytes) -> bytes | None:
        self.port.reset_input_buffer()
        self.port.write(command + b"\n")
        return self.line()

    def close(self) -> None:
        self.port.close()


def test_opening_the_port_resets_the_board_and_the_bootloader_swallows_input(board):
    port = RawPort(board.path)
    try:
        port.port.write(b"ID\n")  # sent at once, as the driver does: the bootloader eats it
        assert port.line(timeout=2.0) == f"READY ps-lab-lights 1 {LIGHTS}".encode()
        assert port.line(timeout=0.3) is None
        assert port.ask(b"ID") == f"ID ps-lab-lights 1 {LIGHTS}".encode()
        assert board.pin_state().lit == frozenset()
    finally:
        port.close()


def test_every_command_and_error_code_on_the_compiled_firmware(board):
    port = RawPort(board.path)
    try:
        assert port.line(timeout=2.0).startswith(b"READY ")
        exchanges = [
            (b"STATE", b"STATE NONE", set(), 255),
            (b"ON 3", b"OK ON 3", {3}, 255),
            (b"STATE", b"STATE 3", {3}, 255),
            (f"on 1 {LIGHTS}".encode(), f"OK ON 1 {LIGHTS}".encode(), {1, LIGHTS}, 255),
            (b"LEVEL 128", b"OK LEVEL 128", {1, LIGHTS}, 128),
            (b"OFF", b"OK OFF", set(), 128),
            (b"ON 2 7", b"OK ON 2 7", {2, 7}, 128),
            (b"FOO", b"ERR 1 unknown command", {2, 7}, 128),
            (b"\xff\xfe\x00garbage", b"ERR 1 unknown command", {2, 7}, 128),
            (b"ON x", b"ERR 2 bad argument", {2, 7}, 128),
            (b"LEVEL 256", b"ERR 2 bad argument", {2, 7}, 128),
            (f"ON {LIGHTS + 1}".encode(), b"ERR 3 light out of range", {2, 7}, 128),
            # 203 characters: longer than the sketch's 200-character line buffer, refused whole
            (b"ON " + b"1 " * 100 + b"2", b"ERR 2 bad argument", {2, 7}, 128),
            (b"ON " + b"1 " * 98 + b"2", b"OK ON " + b"1 " * 98 + b"2", {1, 2}, 128),
            (b"LEVEL 0", b"OK LEVEL 0", {1, 2}, 0),
            (b"STATE", b"STATE 1 2", {1, 2}, 0),
            (b"LEVEL 255", b"OK LEVEL 255", {1, 2}, 255),
            (b"OFF", b"OK OFF", set(), 255),
        ]
        for command, reply, lit, level in exchanges:
            assert port.ask(command) == reply, command
            assert_pins(board, lit, level)
    finally:
        port.close()


def test_watchdog_switches_the_pins_off_after_the_configured_time(board):
    port = RawPort(board.path)
    try:
        assert port.line(timeout=2.0).startswith(b"READY ")
        assert port.ask(b"WATCHDOG 400") == b"OK WATCHDOG 400"
        assert port.ask(b"ON 4") == b"OK ON 4"
        sent = time.monotonic()
        while board.pin_state().lit and time.monotonic() - sent < 2.0:
            time.sleep(0.005)
        off_after = time.monotonic() - sent
        assert board.pin_state().lit == frozenset()
        # The MCU counts 400 ms from the command's arrival, shortly before its reply was read.
        assert 0.3 < off_after < 0.9, off_after
        assert port.ask(b"STATE") == b"STATE NONE"
    finally:
        port.close()


def test_driver_handshakes_after_boot_and_the_pins_follow_every_command(board):
    with SerialLightController(board.path, LIGHTS, **DRIVER) as controller:
        assert controller.reboots_seen == 0
        level = 255
        for light in range(1, LIGHTS + 1):
            controller.switch(light)
            assert controller.state().lit == {light}
            assert_pins(board, {light}, level)
        for level, lit in [(40, {1, 2, 7}), (200, {3, 12}), (0, {5}), (255, set())]:
            controller.set_level(level)
            controller.switch(lit)
            assert controller.state() == LightState(frozenset(lit), level)
            assert_pins(board, lit, level)
    assert board.pin_state().lit == frozenset()


def test_driver_recovers_when_the_board_resets_between_commands(board):
    with SerialLightController(board.path, LIGHTS, level=90, **DRIVER) as controller:
        controller.switch(3)
        board.reset()  # a brown-out during an exposure: every output off, READY unasked
        deadline = time.monotonic() + 2.0
        while board.pin_state().lit and time.monotonic() < deadline:
            time.sleep(0.005)
        assert board.pin_state().lit == frozenset()
        time.sleep(0.1)  # let READY arrive before the next command
        assert controller.state().lit == {3}
        assert controller.reboots_seen == 1
        assert_pins(board, {3}, 90)
    assert board.pin_state().lit == frozenset()


def test_serve_firmware_prints_the_device_path_and_serves_until_sigterm(firmware_cache, tmp_path):
    switch_through_served_device(
        ["serve-firmware"], tmp_path / "pins.json", LIGHTS, DRIVER, wait_s=60,
        env={**os.environ, "PS_LAB_CACHE": str(firmware_cache)},
    )


def test_missing_toolchain_is_one_error_line_naming_the_packages(monkeypatch):
    monkeypatch.setitem(avr_firmware.FIRMWARE_PACKAGES, "libsimavr-dev", "/nonexistent/uart_pty.h")
    result = CliRunner().invoke(app, ["rig", "serve-firmware"])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "libsimavr-dev" in lines[0] and "apt-get install" in lines[0]


def test_a_missing_elf_and_a_bad_wiring_are_rig_errors(tmp_path):
    with pytest.raises(RigError, match="does not exist"):
        EmulatedFirmware(tmp_path / "nope.elf").start()
    with pytest.raises(RigError, match="Uno pin 2-19"):
        avr_firmware.parse_pins("3,5,1")
    with pytest.raises(RigError, match="separated by commas"):
        avr_firmware.parse_pins("3;5")
