"""One contract for every light-controller transport.

The same tests run against the simulated controller in-process (``pslabsim://``), over a real
pseudo-terminal through the OS serial layer, against the compiled Arduino sketch running in simavr
behind a pty (``firmware``: the real firmware, its lights read from its pins; skipped, naming the
Debian packages, where the toolchain is missing), and against a double that replays exact byte
exchanges. Each test declares with ``@exchanges`` the bytes it expects between the handshake and
the final OFF; the double enforces them, the simulators and the firmware answer them for real.
"""

from __future__ import annotations

import itertools
import logging
import os
import signal
import threading

import pytest
from helpers.lights_doubles import CLOSE, LIGHTS, ExpectedProtocolPort, expected_protocol, handshake

from ps_lab.capture.light_controllers import LightState, SerialLightController
from ps_lab.capture.simulated.avr_firmware import EmulatedFirmware
from ps_lab.capture.simulated.firmware import (
    ManualClock,
    SimulatedFirmware,
    firmware_for,
)
from ps_lab.capture.simulated.pty_server import PtyServer
from ps_lab.errors import RigError

# No timeout expires in these tests (no faults), so a generous one costs nothing and keeps the pty
# backend robust on a busy machine.
TIMEOUT = dict(reply_timeout=1.0, boot_timeout=1.0, retries=2)
_names = itertools.count()


def exchanges(*pairs: tuple[bytes, bytes], handshake_: bool = True, close: bool = True):
    """Declare the bytes a test exchanges (enforced by the double, answered by the simulators)."""

    def mark(test):
        test.exchanges = (
            (handshake() if handshake_ else []) + list(pairs) + (CLOSE if close else [])
        )
        return test

    return mark


class Backend:
    """Opens controllers on one transport and tells what the controller saw."""

    def __init__(self, kind: str, request: pytest.FixtureRequest) -> None:
        self.kind = kind
        self.firmware: SimulatedFirmware | None = None
        self.board: EmulatedFirmware | None = None
        self.firmware_cache = None  # set for "firmware": where the sketch and harness are built
        self._server: PtyServer | None = None
        self._double: ExpectedProtocolPort | None = None
        self._script = list(getattr(request.function, "exchanges", []))

    def open(self, lights: int = LIGHTS) -> SerialLightController:
        if self.kind == "firmware":
            # No bootloader wait: the driver's ID, sent as the port opens, is answered after READY.
            self.board = EmulatedFirmware(build_dir=self.firmware_cache / "firmware", boot_ms=0)
            self.board.start()
            return SerialLightController(self.board.path, lights, **TIMEOUT)
        if self.kind == "url":
            name = f"contract-{next(_names)}"
            url = f"pslabsim://{name}?lights={LIGHTS}&clock=manual"
            try:
                return SerialLightController(url, lights, **TIMEOUT)
            finally:
                self.firmware = firmware_for(name)
        if self.kind == "pty":
            self.firmware = SimulatedFirmware(LIGHTS, clock=ManualClock())
            self._server = PtyServer(self.firmware).start()
            return SerialLightController(self._server.path, lights, **TIMEOUT)
        self._context = expected_protocol(self._script)
        self._double = self._context.__enter__()
        return SerialLightController(self._double, lights, **TIMEOUT)

    def lit(self) -> frozenset[int] | None:
        """What the simulated controller has lit (None for the double: it has no state)."""
        if self.board is not None:
            return self.board.pin_state().lit
        return None if self.firmware is None else self.firmware.state().lit

    def assert_ended_safely(self) -> None:
        if self.board is not None:
            assert self.board.pin_state().lit == frozenset()  # every light pin off
        elif self.firmware is not None:
            assert self.firmware.ended_safely(), self.firmware.log[-5:]
            assert self.firmware.commands()[-1] == "OFF"
        else:
            assert self._double is not None and not self._double.remaining()

    def finish(self) -> None:
        if self.board is not None:
            self.board.stop()
        if self._server is not None:
            self._server.stop()
        if self._double is not None:
            self._context.__exit__(None, None, None)


@pytest.fixture(params=["url", "pty", "firmware", "double"])
def backend(request: pytest.FixtureRequest):
    b = Backend(request.param, request)
    if request.param == "firmware":
        b.firmware_cache = request.getfixturevalue("firmware_cache")
    yield b
    b.finish()


@exchanges((b"STATE\n", b"STATE NONE\n"))
def test_open_handshakes_and_starts_dark(backend):
    controller = backend.open()
    assert controller.count == LIGHTS
    assert controller.state() == LightState(frozenset(), 255)
    if backend.firmware is not None:
        assert backend.firmware.commands()[:4] == ["ID", "WATCHDOG 10000", "LEVEL 255", "OFF"]
    controller.close()
    backend.assert_ended_safely()


@exchanges((b"ON 3\n", b"OK ON 3\n"), (b"STATE\n", b"STATE 3\n"))
def test_switch_lights_one_light(backend):
    with backend.open() as controller:
        controller.switch(3)
        assert backend.lit() in (None, frozenset({3}))
        assert controller.state().lit == {3}
    backend.assert_ended_safely()


@exchanges(
    (b"ON 5\n", b"OK ON 5\n"),
    (b"ON 2 9 12\n", b"OK ON 2 9 12\n"),
    (b"STATE\n", b"STATE 2 9 12\n"),
)
def test_switch_a_set_lights_exactly_that_set(backend):
    with backend.open() as controller:
        controller.switch(5)
        controller.switch({12, 9, 2})
        assert backend.lit() in (None, frozenset({2, 9, 12}))
        assert controller.state().lit == {2, 9, 12}
    backend.assert_ended_safely()


@exchanges(
    (b"ON 7\n", b"OK ON 7\n"),
    (b"OFF\n", b"OK OFF\n"),
    (b"STATE\n", b"STATE NONE\n"),
    (b"ON 8\n", b"OK ON 8\n"),
    (b"OFF\n", b"OK OFF\n"),
)
def test_all_off_and_empty_switch_switch_everything_off(backend):
    with backend.open() as controller:
        controller.switch(7)
        controller.all_off()
        assert controller.state().lit == frozenset()
        controller.switch(8)
        controller.switch([])
        assert backend.lit() in (None, frozenset())
    backend.assert_ended_safely()


@exchanges((b"LEVEL 40\n", b"OK LEVEL 40\n"), (b"ON 1\n", b"OK ON 1\n"), (b"STATE\n", b"STATE 1\n"))
def test_set_level_applies_to_lit_lights(backend):
    with backend.open() as controller:
        controller.set_level(40)
        controller.switch(1)
        assert controller.state() == LightState(frozenset({1}), 40)
        if backend.firmware is not None:
            assert backend.firmware.state() == LightState(frozenset({1}), 40)
        if backend.board is not None:  # light 1 is on a PWM pin: it dims
            assert backend.board.light_state() == LightState(frozenset({1}), 40)
    backend.assert_ended_safely()


@exchanges()
def test_invalid_arguments_raise_before_anything_is_sent(backend):
    with backend.open() as controller:
        sent_before = None if backend.firmware is None else len(backend.firmware.commands())
        for bad in (0, LIGHTS + 1, [1, 30], -2, True, "3", 2.0):
            with pytest.raises(RigError, match="light"):
                controller.switch(bad)
        for bad in (256, -1, 3.5):
            with pytest.raises(RigError, match="level"):
                controller.set_level(bad)
        if backend.firmware is not None:
            assert len(backend.firmware.commands()) == sent_before
    backend.assert_ended_safely()


@exchanges((b"ON 4\n", b"OK ON 4\n"))
def test_close_switches_off_once_and_refuses_later_use(backend):
    controller = backend.open()
    controller.switch(4)
    controller.close()
    controller.close()
    assert controller.closed
    with pytest.raises(RigError, match="closed"):
        controller.switch(1)
    backend.assert_ended_safely()


@exchanges((b"ON 2\n", b"OK ON 2\n"))
@pytest.mark.parametrize("error", [ZeroDivisionError, KeyboardInterrupt])
def test_exception_in_block_switches_off_and_propagates(backend, error):
    """Any exception in the ``with`` block, Ctrl-C's included, switches off and propagates."""
    with pytest.raises(error):
        with backend.open() as controller:
            controller.switch(2)
            raise error
    assert controller.closed
    backend.assert_ended_safely()


@exchanges((b"ON 2\n", b"OK ON 2\n"), (b"OFF\n", b"OK OFF\n"))
def test_sigterm_during_session_switches_off_and_restores_handler(backend):
    previous = signal.getsignal(signal.SIGTERM)
    controller = backend.open()
    with pytest.raises(KeyboardInterrupt):
        with controller.session():
            controller.switch(2)
            assert signal.getsignal(signal.SIGTERM) is not previous
            os.kill(os.getpid(), signal.SIGTERM)
            pytest.fail("SIGTERM did not interrupt the session")
    assert signal.getsignal(signal.SIGTERM) is previous
    assert backend.lit() in (None, frozenset())
    assert not controller.closed
    controller.close()
    backend.assert_ended_safely()


@exchanges((b"ON 9\n", b"OK ON 9\n"))
def test_context_in_another_thread_leaves_signal_handlers_alone(backend):
    previous = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    controller = backend.open()
    seen = []

    def work():
        with controller:
            controller.switch(9)
            seen.append((signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)))

    thread = threading.Thread(target=work)
    thread.start()
    thread.join()
    assert seen == [previous]
    backend.assert_ended_safely()


# A wrong identity could be line noise: the driver believes it when the controller says it twice.
@exchanges(*[(b"ID\n", b"ID ps-lab-lights 1 12\n")] * 2, handshake_=False, close=False)
def test_light_count_must_match_the_rig(backend):
    with pytest.raises(RigError, match=r"has 12 lights, expected 24"):
        backend.open(lights=24)
    if backend.firmware is not None:
        assert backend.firmware.commands() == ["ID", "ID"]


@exchanges((b"ON 3\n", b"OK ON 3\n"))
def test_serial_traffic_is_logged_at_debug_level(backend, caplog):
    with caplog.at_level(logging.DEBUG, logger="ps_lab.capture.light_controllers"):
        with backend.open() as controller:
            controller.switch(3)
    assert "-> ON 3" in caplog.text
    assert "<- OK ON 3" in caplog.text
    backend.assert_ended_safely()
