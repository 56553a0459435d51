"""What every simulator served to another program shares: started, served until Ctrl-C or
until it ends by itself, stopped (idempotent), and usable as a context manager.

`PtyServer` (a controller on a pseudo-terminal), `PtpIpCamera` (a PTP/IP camera on a socket)
and `EmulatedFirmware` (the compiled sketch in simavr) each say how they start, stop, whether
they are serving and how to wait for their end; the rest is written here once.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Self


class ServedSimulator(ABC):
    """A simulator serving in the background (a thread or a process) until stopped."""

    @abstractmethod
    def start(self) -> Self:
        """Start serving in the background; return self."""

    @abstractmethod
    def stop(self) -> None:
        """Stop serving and release everything (idempotent)."""

    @property
    @abstractmethod
    def serving(self) -> bool:
        """Whether :meth:`start` has run and :meth:`stop` has not."""

    @abstractmethod
    def _wait(self) -> None:
        """Block until the background work ends by itself (raise where that is a failure)."""

    def serve_forever(self) -> None:
        """Block until interrupted (Ctrl-C) or until the simulator ends; then stop."""
        try:
            self._wait()
        finally:
            self.stop()

    def __enter__(self) -> Self:
        return self if self.serving else self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()


def join_thread(thread) -> None:
    """Wait for ``thread`` (None: nothing) in short joins, so that Ctrl-C interrupts the wait."""
    while thread is not None and thread.is_alive():
        thread.join(timeout=0.2)
