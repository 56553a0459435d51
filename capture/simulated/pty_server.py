"""The simulated controller served on a pseudo-terminal (``ps-lab rig serve-sim``).

Also the JSON state file through which a simulated camera in another process sees what is lit.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import select
import signal
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ps_lab.capture.light_controllers import LightState
from ps_lab.capture.simulated.firmware import LineAssembler, Reply, SimulatedFirmware, _Outbox
from ps_lab.capture.simulated.serving import ThreadServedSimulator
from ps_lab.errors import RigError

log = logging.getLogger("ps_lab.capture.simulated.firmware")

__all__ = [
    "PtyServer",
    "serve_simulator",
    "serve_until_interrupted",
    "state_file_reader",
    "write_state_file",
]


# -- state file (for a simulator in another process) -------------------------------------------


def write_state_file(path: Path | str, state: LightState) -> None:
    """Write ``{"lit": [...], "level": v}`` to ``path`` atomically (temporary file + rename)."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    temporary.write_text(json.dumps({"lit": sorted(state.lit), "level": state.level}))
    os.replace(temporary, path)


def read_state_file(path: Path, parse: Callable[[Any], Any], what: str, writer: str) -> Any:
    """``parse`` of the JSON in a simulator's state file ``path`` (``what``, written by ``writer``).

    Raises :class:`RigError` naming the file: missing (is ``writer`` running?), unreadable, or
    not what ``parse`` expects (a ``ValueError``, ``KeyError`` or ``TypeError``).
    """
    try:
        return parse(json.loads(path.read_text()))
    except FileNotFoundError:
        raise RigError(f"{what} {path} does not exist: is {writer} running?") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise RigError(f"cannot read {what} {path}: {exc}") from None


def state_file_reader(path: Path | str) -> Callable[[], LightState]:
    """Return a function that reads the simulator's current :class:`LightState` from ``path``.

    Raises :class:`RigError` (when called) if the file is missing or unreadable: the simulator is
    not running, and guessing "all off" would hide it.
    """
    path = Path(path)

    def read() -> LightState:
        return read_state_file(
            path,
            lambda data: LightState(frozenset(int(i) for i in data["lit"]), int(data["level"])),
            "light state file",
            "`ps-lab rig serve-sim`",
        )

    return read


class PtyServer(ThreadServedSimulator):
    """Serve a simulated controller on a pseudo-terminal, so drivers open it as a serial device.

    Parameters
    ----------
    firmware : SimulatedFirmware, optional
        The controller to serve (default: a new one from ``lights``, ``faults``, ``seed``,
        ``delay_s``).
    state_file : path, optional
        Publish the light state there (atomically) on every change, for a camera in another process.

    Examples
    --------
    >>> with PtyServer(lights=24) as server:          # doctest: +SKIP
    ...     controller = SerialLightController(server.path, lights=24)

    """

    def __init__(
        self,
        firmware: SimulatedFirmware | None = None,
        *,
        lights: int = 24,
        faults: Any = (),
        seed: int = 0,
        delay_s: float = 1.0,
        state_file: Path | str | None = None,
    ) -> None:
        self.firmware = (
            firmware
            if firmware is not None
            else SimulatedFirmware(lights, faults=faults, seed=seed, delay_s=delay_s)
        )
        self.state_file = Path(state_file) if state_file is not None else None
        self.path: str | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._unsolicited: queue.SimpleQueue[str] = queue.SimpleQueue()
        self._detach: Callable[[], None] | None = None

    def start(self) -> PtyServer:
        """Open the pty pair, announce READY and serve in a background thread; return self."""
        if self._thread is not None:
            raise RigError("the simulated controller is already being served")
        master, slave = os.openpty()
        # Raw mode on the device side: no echo, no line editing, no CR/LF translation.
        tty.setraw(slave)
        self._master, self._slave = master, slave
        self.path = os.ttyname(slave)
        if self.state_file is not None:
            target = self.state_file
            self.firmware.add_listener(lambda state: write_state_file(target, state))
        self._stop.clear()
        outbox = _Outbox()
        outbox.add(Reply([self.firmware.reboot()]))
        self._detach = self.firmware.add_output(self._unsolicited.put)
        self._thread = threading.Thread(
            target=self._serve, args=(outbox,), name="ps-lab-pty-sim", daemon=True
        )
        self._thread.start()
        log.info("simulated light controller (%d lights) on %s", self.firmware.lights, self.path)
        return self

    def stop(self) -> None:
        """Stop serving and close the pty pair (idempotent)."""
        self._stop.set()
        if self._detach is not None:
            self._detach()
            self._detach = None
        self._end_thread()
        for fd in (self._master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = None

    def serve_forever(self) -> None:
        """Block until interrupted (Ctrl-C) or until the server thread fails; then stop."""
        super().serve_forever()
        if self._error is not None:
            raise RigError(f"simulated controller stopped: {self._error}")

    def _serve(self, outbox: _Outbox) -> None:
        assert self._master is not None
        master = self._master
        assembler = LineAssembler()
        try:
            while not self._stop.is_set():
                wait = 0.02
                next_due = outbox.next_due()
                if next_due is not None:
                    wait = max(0.0, min(wait, next_due - time.monotonic()))
                readable, _, _ = select.select([master], [], [], wait)
                if readable:
                    try:
                        data = os.read(master, 4096)
                    except OSError:  # no client side open at this instant
                        data = b""
                    for line in assembler.feed(data):
                        outbox.add(self.firmware.respond(line))
                self.firmware.poll()
                while not self._unsolicited.empty():
                    outbox.add(Reply([self._unsolicited.get()]))
                data = outbox.due()
                if data:
                    os.write(master, data)
        except BaseException as exc:  # surfaced by serve_forever
            self._error = exc
            log.exception("simulated light controller failed")


def serve_simulator(
    *,
    lights: int = 24,
    faults: Any = (),
    seed: int = 0,
    delay_s: float = 1.0,
    state_file: Path | str | None = None,
    on_ready: Callable[[PtyServer], None] | None = None,
) -> None:
    """Serve a simulated controller on a pty until Ctrl-C or SIGTERM, then stop cleanly.

    ``on_ready(server)`` is called once the device path exists (to print it). The state file, if
    any, is removed at the end, so a reader learns that the simulator is gone.
    """
    server = PtyServer(
        lights=lights, faults=faults, seed=seed, delay_s=delay_s, state_file=state_file
    )
    try:
        serve_until_interrupted(server, on_ready, "simulated light controller")
    finally:
        if state_file is not None:
            Path(state_file).unlink(missing_ok=True)


def serve_until_interrupted(server: Any, on_ready: Callable[[Any], None] | None, what: str) -> None:
    """Start ``server``, call ``on_ready(server)``, serve until Ctrl-C or SIGTERM, then stop it.

    ``server`` is a context manager that starts on entry, stops on exit and has
    ``serve_forever()`` (:class:`PtyServer`, the emulated firmware). SIGTERM raises
    KeyboardInterrupt meanwhile (main thread only), so both end the same clean way.
    """

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    previous = (
        signal.signal(signal.SIGTERM, interrupt)
        if threading.current_thread() is threading.main_thread()
        else None
    )
    try:
        with server:
            if on_ready is not None:
                on_ready(server)
            try:
                server.serve_forever()
            except KeyboardInterrupt:
                log.info("%s stopped", what)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
