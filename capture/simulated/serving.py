"""What every simulator served to another program shares: started, served until Ctrl-C or
until it ends by itself, stopped (idempotent), and usable as a context manager.

`PtyServer` (a controller on a pseudo-terminal), `PtpIpCamera` (a PTP/IP camera on a socket)
and `EmulatedFirmware` (the compiled sketch in simavr) each say how they start, stop, whether
they are serving and how to wait for their end; the rest is written here once, and for the two
served by one background thread (`ThreadServedSimulator`) also whether they serve and the wait.
"""

from __future__ import annotations

import threading
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


class ThreadServedSimulator(ServedSimulator):
    """A simulator served by one background thread, ``_thread`` (None until started, and again
    once stopped)."""

    _thread: threading.Thread | None = None

    @property
    def serving(self) -> bool:
        return self._thread is not None

    def _wait(self) -> None:
        """Wait for the thread in short joins, so that Ctrl-C interrupts the wait."""
        while self._thread is not None and self._thread.is_alive():
            self._thread.join(timeout=0.2)

    def _end_thread(self) -> None:
        """Join the thread (told to stop already) for at most 5 s and forget it."""
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
