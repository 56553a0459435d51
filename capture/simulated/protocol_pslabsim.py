"""pyserial URL handler for ``pslabsim://``: a simulated light controller inside this process.

pyserial resolves ``scheme://`` URLs by importing ``protocol_<scheme>`` from the packages listed in
``serial.protocol_handler_packages``; importing :mod:`ps_lab.capture.light_controllers` adds
``ps_lab.capture.simulated`` to that list. URL options are described in
:func:`ps_lab.capture.simulated.firmware.firmware_from_url`.

Opening the port behaves like opening an Arduino's USB serial port: the board resets and
announces ``READY``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from serial.serialutil import PortNotOpenError, SerialBase, SerialException, SerialTimeoutException

from ps_lab.capture.simulated.firmware import (
    LineAssembler,
    Reply,
    SimulatedFirmware,
    _Outbox,
    firmware_from_url,
)
from ps_lab.errors import RigError


class Serial(SerialBase):
    """A serial port whose other end is a :class:`SimulatedFirmware`."""

    BAUDRATES = (9600, 19200, 38400, 57600, 115200, 230400)

    def __init__(self, *args: object, **kwargs: object) -> None:
        self.firmware: SimulatedFirmware | None = None
        self.name: str | None = None
        self._lock = threading.Lock()
        self._received = bytearray()
        self._outbox = _Outbox()
        self._assembler = LineAssembler()
        self._detach: Callable[[], None] | None = None
        super().__init__(*args, **kwargs)

    # -- opening -----------------------------------------------------------------------------

    def open(self) -> None:
        """Attach to (or create) the simulated controller the URL names, which then reboots."""
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise SerialException("Port is already open.")
        self.from_url(self.portstr)
        self._received.clear()
        self._outbox = _Outbox()
        self._assembler = LineAssembler()
        self.is_open = True
        assert self.firmware is not None
        self._outbox.add(Reply([self.firmware.reboot()]))
        self._detach = self.firmware.add_output(self._unsolicited)

    def from_url(self, url: str) -> None:
        """Read the URL's options (see ``firmware_from_url``)."""
        try:
            self.name, self.firmware = firmware_from_url(url)
        except RigError as exc:
            raise SerialException(str(exc)) from None

    def close(self) -> None:
        """Detach; the simulated controller keeps its state (a real board stays powered)."""
        if self._detach is not None:
            self._detach()
            self._detach = None
        self.is_open = False

    def _unsolicited(self, line: str) -> None:
        with self._lock:
            self._outbox.add(Reply([line]))

    def _reconfigure_port(self) -> None:
        # Baud rate, parity, etc. mean nothing in-process.
        pass

    # -- data --------------------------------------------------------------------------------

    def _pump(self) -> None:
        # Deliver replies whose time has come and let the watchdog run.
        assert self.firmware is not None
        self.firmware.poll()
        self._received += self._outbox.due()

    @property
    def in_waiting(self) -> int:
        """Bytes ready to read."""
        if not self.is_open:
            raise PortNotOpenError()
        with self._lock:
            self._pump()
            return len(self._received)

    def read(self, size: int = 1) -> bytes:
        """Read up to ``size`` bytes, waiting at most ``timeout`` seconds (None: forever)."""
        if not self.is_open:
            raise PortNotOpenError()
        deadline = None if self._timeout is None else time.monotonic() + self._timeout
        while True:
            with self._lock:
                self._pump()
                if len(self._received) >= size or (
                    deadline is not None and time.monotonic() >= deadline
                ):
                    data = bytes(self._received[:size])
                    del self._received[:size]
                    return data
                next_due = self._outbox.next_due()
            pause = 0.002 if next_due is None else max(0.0, min(0.002, next_due - time.monotonic()))
            time.sleep(pause)

    def write(self, data: bytes) -> int:
        """Send bytes to the controller; each complete line is processed at once."""
        if not self.is_open:
            raise PortNotOpenError()
        data = bytes(data)
        assert self.firmware is not None
        with self._lock:
            for line in self._assembler.feed(data):
                self._outbox.add(self.firmware.respond(line))
        return len(data)

    def reset_input_buffer(self) -> None:
        """Discard received bytes not yet read (replies still in flight stay in flight)."""
        if not self.is_open:
            raise PortNotOpenError()
        with self._lock:
            self._pump()
            self._received.clear()

    def reset_output_buffer(self) -> None:
        """Nothing is ever buffered on the way out."""
        if not self.is_open:
            raise PortNotOpenError()

    @property
    def out_waiting(self) -> int:
        """Always 0: writes are delivered immediately."""
        return 0

    def flush(self) -> None:
        """Do nothing: writes are delivered immediately."""

    def _update_break_state(self) -> None:
        pass

    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        """Clear To Send: always asserted."""
        return True

    @property
    def dsr(self) -> bool:
        """Data Set Ready: always asserted."""
        return True

    @property
    def ri(self) -> bool:
        """Ring Indicator: never."""
        return False

    @property
    def cd(self) -> bool:
        """Carrier Detect: always asserted."""
        return True


__all__ = ["Serial", "SerialTimeoutException"]
