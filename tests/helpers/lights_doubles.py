"""Test double for the light controller's port: replay exact byte exchanges (PyMeasure's way).

``expected_protocol([(b"ON 3\\n", b"OK ON 3\\n"), ...])`` yields a pyserial-like port. Each write
must continue the next expected request exactly; when a request is complete its reply becomes
readable. A reply of ``b""`` is a lost reply. Leaving the block with exchanges not consumed, or
after any unexpected byte, fails the test.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

import pytest

# The sketch in rigs/firmware has 12 lights, and the contract suite also runs against it compiled.
LIGHTS = 12


def handshake(
    lights: int = LIGHTS, *, watchdog_ms: int = 10000, level: int = 255
) -> list[tuple[bytes, bytes]]:
    """The exchanges SerialLightController makes on open, answered by a healthy controller."""
    return [
        (b"ID\n", f"ID ps-lab-lights 1 {lights}\n".encode()),
        (f"WATCHDOG {watchdog_ms}\n".encode(), f"OK WATCHDOG {watchdog_ms}\n".encode()),
        (f"LEVEL {level}\n".encode(), f"OK LEVEL {level}\n".encode()),
        (b"OFF\n", b"OK OFF\n"),
    ]


CLOSE = [(b"OFF\n", b"OK OFF\n")]


class ExpectedProtocolPort:
    """A pyserial-like port scripted with exact (request, reply) byte pairs."""

    def __init__(self, exchanges: Iterable[tuple[bytes, bytes]], *, greeting: bytes = b"") -> None:
        self._exchanges = deque(exchanges)
        self._written = bytearray()
        self._readable = bytearray(greeting)
        self.failures: list[str] = []
        self.timeout: float | None = None
        self.is_open = True
        self.port = "expected-protocol"
        self.consumed = 0

    def write(self, data: bytes) -> int:
        if not self.is_open:
            self._fail(f"write {bytes(data)!r} after close")
        self._written += data
        while self._written:
            if not self._exchanges:
                self._fail(f"unexpected write {bytes(self._written)!r}: no exchange left")
            request, reply = self._exchanges[0]
            if not request.startswith(bytes(self._written[: len(request)])):
                self._fail(f"wrote {bytes(self._written)!r}, expected {request!r}")
            if len(self._written) < len(request):
                break
            del self._written[: len(request)]
            self._exchanges.popleft()
            self.consumed += 1
            self._readable += reply
        return len(data)

    def read(self, size: int = 1) -> bytes:
        if not self._readable:
            time.sleep(self.timeout or 0.0)  # a real port blocks until its timeout
            return b""
        data = bytes(self._readable[:size])
        del self._readable[:size]
        return data

    @property
    def in_waiting(self) -> int:
        return len(self._readable)

    def reset_input_buffer(self) -> None:
        self._readable.clear()

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.is_open = False

    def remaining(self) -> list[tuple[bytes, bytes]]:
        return list(self._exchanges)

    def _fail(self, message: str) -> None:
        # The driver may turn exceptions from the port into RigError; keep the real reason.
        self.failures.append(message)
        raise AssertionError(message)


@contextmanager
def expected_protocol(
    exchanges: Iterable[tuple[bytes, bytes]], *, greeting: bytes = b""
) -> Iterator[ExpectedProtocolPort]:
    """Yield a scripted port; fail if a write deviated or an exchange was not consumed."""
    port = ExpectedProtocolPort(exchanges, greeting=greeting)
    yield port
    if port.failures:
        pytest.fail("protocol deviated: " + port.failures[0])
    if port.remaining():
        pytest.fail(f"exchanges not consumed: {port.remaining()!r}")
