"""The byte level of the light-controller protocol: line framing over a pyserial port.

Private: :class:`ps_lab.capture.light_controllers.SerialLightController` owns one
:class:`SerialLink` and speaks in lights; everything that touches bytes is here. All traffic is
logged at debug level (``ps-lab -vv``).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from ps_lab.errors import RigError

log = logging.getLogger("ps_lab.capture.light_controllers")

#: How long one ``read`` call on the port may block; short, so a reply deadline is kept precisely.
POLL_S = 0.01
#: A reply line longer than this is noise, not a reply.
MAX_REPLY = 1024


class SerialLink:
    """One command line out, reply lines back, over a pyserial-like port.

    Parameters
    ----------
    port : serial.SerialBase or compatible
        Needs ``write``, ``read``, ``in_waiting``, ``reset_input_buffer``, ``close`` and a
        writable ``timeout``.
    name : str
        How to name the port in messages.

    Notes
    -----
    ``lock`` serialises whole exchanges (the driver holds it from send to reply); it is
    re-entrant so a re-handshake can run inside an exchange.

    """

    def __init__(self, port: Any, name: str) -> None:
        self.port = port
        self.name = name
        self.lock = threading.RLock()
        self._received = bytearray()
        try:
            port.timeout = POLL_S
        except Exception as exc:  # pyserial reconfigures the OS port here
            raise self._lost(exc) from exc

    def send(self, line: str) -> None:
        """Write ``line`` and a line feed."""
        log.debug("%s -> %s", self.name, line)
        try:
            self.port.write(line.encode("ascii") + b"\n")
        except Exception as exc:
            raise self._lost(exc) from exc

    def read_line(self, timeout: float) -> str | None:
        """Return the next reply line (no terminator), or None if none ends within ``timeout`` s.

        Bytes that are not ASCII (line noise) are decoded as U+FFFD, so they never match a reply.
        """
        deadline = time.monotonic() + timeout
        while True:
            end = self._received.find(b"\n")
            if end >= 0:
                raw = bytes(self._received[:end])
                del self._received[: end + 1]
                line = raw.replace(b"\r", b"").decode("ascii", errors="replace")
                log.debug("%s <- %s", self.name, line)
                return line
            if len(self._received) > MAX_REPLY:
                log.debug(
                    "%s <- (noise, %d bytes without a line end)", self.name, len(self._received)
                )
                self._received.clear()
            if time.monotonic() >= deadline:
                if self._received:
                    log.debug("%s <- (partial) %r", self.name, bytes(self._received))
                return None
            try:
                waiting = self.port.in_waiting
                chunk = self.port.read(max(1, min(waiting, 4096)))
            except Exception as exc:
                raise self._lost(exc) from exc
            self._received += chunk

    def drain(self) -> list[str]:
        """Discard the complete lines received but not read; return them (stale or noise).

        A partial line at the end is kept: it may be the start of a line still arriving (a
        ``READY`` from a board that just reset), and cutting it would hide that line.
        """
        try:
            while (waiting := self.port.in_waiting) > 0:
                self._received += self.port.read(min(waiting, 4096))
        except Exception as exc:
            raise self._lost(exc) from exc
        end = self._received.rfind(b"\n")
        if end < 0:
            return []
        stale = bytes(self._received[: end + 1])
        del self._received[: end + 1]
        log.debug("%s drained %r", self.name, stale)
        lines = stale.replace(b"\r", b"").decode("ascii", errors="replace").split("\n")
        return lines[:-1]

    def close(self) -> None:
        """Close the port (errors while closing are logged, not raised)."""
        try:
            self.port.close()
        except Exception as exc:
            log.warning("closing %s: %s", self.name, exc)

    def _lost(self, exc: BaseException) -> RigError:
        return RigError(f"light controller at {self.name}: serial port failed: {exc}")
