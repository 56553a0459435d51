"""Light controllers: the abstract base and the protocol-v1 serial driver (docs/rig-protocol.md)."""

from __future__ import annotations

import logging
import numbers
import re
import signal
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import serial

from ps_lab.capture._serial_link import POLL_S, SerialLink
from ps_lab.errors import RigError

__all__ = [
    "DEFAULT_WATCHDOG_MS",
    "PROTOCOL_NAME",
    "PROTOCOL_VERSION",
    "LightController",
    "LightState",
    "SerialLightController",
    "walk_lights",
]

PROTOCOL_NAME = "ps-lab-lights"
PROTOCOL_VERSION = 1
DEFAULT_WATCHDOG_MS = 10000
MAX_LEVEL = 255
#: Longest command line (without its terminator) a controller must accept.
MAX_LINE = 200

# pyserial finds a ``scheme://`` handler by importing ``protocol_<scheme>`` from these packages;
# this makes ``pslabsim://`` (capture/simulated/protocol_pslabsim.py) available to every
# serial_for_url call. Only the package name is registered: pyserial imports the simulator when a
# ``pslabsim://`` URL is opened, never otherwise.
if "ps_lab.capture.simulated" not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append("ps_lab.capture.simulated")


@dataclass(frozen=True)
class LightState:
    """What a light controller reports as lit.

    Attributes
    ----------
    lit : frozenset of int
        Lit lights, numbered 1..N.
    level : int
        PWM brightness of lit lights, 0-255.

    """

    lit: frozenset[int]
    level: int


log = logging.getLogger(__name__)

_ID_REPLY = re.compile(r"^(?:ID|READY) ([!-~]+) ([0-9]+) ([0-9]+)$")
_STATE_REPLY = re.compile(r"^STATE (?:NONE|\d+(?: \d+)*)$")


# Ctrl-C, `kill`/`timeout`/batch schedulers, and a closed terminal all unwind with the lights off.
_INTERRUPTS = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)


@contextmanager
def _interrupts_raise() -> Iterator[None]:
    """While active (main thread only), SIGINT and SIGTERM raise KeyboardInterrupt; then restore.

    SIGTERM would otherwise end the process without unwinding, leaving a light on.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt(signal.Signals(signum).name)

    previous = {sig: signal.signal(sig, interrupt) for sig in _INTERRUPTS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@contextmanager
def _interrupts_deferred() -> Iterator[None]:
    """Ignore SIGINT/SIGTERM (main thread only) while the lights are being switched off."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.signal(sig, signal.SIG_IGN) for sig in _INTERRUPTS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class LightController(ABC):
    """A light rig's controller: lights numbered 1..``count``, one lit set at a time.

    Public methods validate their arguments and log; subclasses implement the ``_do_*`` hooks.
    Use it as a context manager: the lights are switched off (and the controller closed) when the
    block ends, by an exception, by Ctrl-C or by SIGTERM.

    Parameters
    ----------
    count : int
        Number of lights.

    """

    def __init__(self, count: int) -> None:
        if isinstance(count, bool) or not isinstance(count, numbers.Integral) or count < 1:
            raise RigError(f"a light controller needs at least one light, not {count!r}")
        self._count = int(count)
        self._closed = False
        # Lights that may be lit: those of a switch not yet followed by a confirmed OFF.
        self._maybe_lit: frozenset[int] = frozenset()

    @property
    def count(self) -> int:
        """Number of lights."""
        return self._count

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    def switch(self, lights: int | Iterable[int]) -> None:
        """Light exactly ``lights`` (one number or a set, 1-based); every other light goes off.

        An empty set switches everything off.
        """
        chosen = self._validate_lights(lights)
        self._check_open()
        log.info("lights on: %s", " ".join(map(str, sorted(chosen))) or "none")
        self._maybe_lit = self._maybe_lit | chosen
        if chosen:
            self._do_switch(chosen)
        else:
            self._do_all_off()
        self._maybe_lit = chosen

    def all_off(self) -> None:
        """Switch every light off."""
        self._check_open()
        log.info("lights off")
        self._do_all_off()
        self._maybe_lit = frozenset()

    def set_level(self, level: int) -> None:
        """Set the PWM brightness (0-255) of lit lights."""
        if (
            isinstance(level, bool)
            or not isinstance(level, numbers.Integral)
            or not 0 <= level <= MAX_LEVEL
        ):
            raise RigError(f"light level must be 0-{MAX_LEVEL}, not {level!r}")
        self._check_open()
        log.info("light level %d", level)
        self._do_set_level(int(level))

    def state(self) -> LightState:
        """Ask the controller what is lit."""
        self._check_open()
        return self._do_state()

    def close(self) -> None:
        """Switch everything off and release the controller (idempotent).

        Raises
        ------
        RigError
            If switching off could not be confirmed (the port is closed all the same).

        """
        if self._closed:
            return
        self._closed = True
        with _interrupts_deferred():
            try:
                self._do_all_off()
                self._maybe_lit = frozenset()
            finally:
                self._do_close()

    def lit_note(self) -> str:
        """``"lights off"``, or which lights may still be lit and what switches them off."""
        if not self._maybe_lit:
            return "lights off"
        lights = sorted(self._maybe_lit)
        which = f"light {lights[0]}" if len(lights) == 1 else "lights " + " ".join(map(str, lights))
        watchdog_ms = getattr(self, "_watchdog_ms", 0)
        if watchdog_ms:
            return (
                f"{which} may still be lit: the controller's watchdog switches "
                f"{'it' if len(lights) == 1 else 'them'} off within {watchdog_ms / 1000:g} s"
            )
        return f"{which} may still be lit and the watchdog is off: check the rig"

    @contextmanager
    def session(self) -> Iterator[LightController]:
        """Use the controller in a block that always ends with the lights off (not closed).

        While the block runs in the main thread, SIGINT and SIGTERM raise KeyboardInterrupt so
        that the block unwinds; the previous handlers come back afterwards.
        """
        self._check_open()
        try:
            with _interrupts_raise():
                yield self
        except BaseException:
            self._off_quietly()
            raise
        with _interrupts_deferred():
            self._do_all_off()
            self._maybe_lit = frozenset()

    def __enter__(self) -> LightController:
        self._check_open()
        self._interrupt_guard = _interrupts_raise()
        self._interrupt_guard.__enter__()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object
    ) -> None:
        guard = getattr(self, "_interrupt_guard", None)
        if guard is not None:
            self._interrupt_guard = None
            guard.__exit__(None, None, None)
        if exc_type is None:
            self.close()
            return
        try:
            self.close()
        except (
            Exception
        ) as close_error:  # the original exception matters more; keep both in the log
            log.error("while handling %s: %s", exc_type.__name__, close_error)

    def _off_quietly(self) -> None:
        with _interrupts_deferred():
            try:
                self._do_all_off()
                self._maybe_lit = frozenset()
            except Exception as exc:
                log.error("could not switch the lights off: %s", exc)

    def _check_open(self) -> None:
        if self._closed:
            raise RigError("the light controller is closed")

    def _validate_lights(self, lights: int | Iterable[int]) -> frozenset[int]:
        if isinstance(lights, numbers.Integral):
            items = [lights]
        elif isinstance(lights, Iterable) and not isinstance(lights, str | bytes):
            items = list(lights)
        else:
            raise RigError(
                f"lights are numbered 1-{self._count}; {lights!r} is not a light number or a set"
            )
        chosen = set()
        for light in items:
            if isinstance(light, bool) or not isinstance(light, numbers.Integral):
                raise RigError(
                    f"lights are numbered 1-{self._count}; {light!r} is not a light number"
                )
            if not 1 <= light <= self._count:
                raise RigError(
                    f"light {light} is out of range: this rig has lights 1-{self._count}"
                )
            chosen.add(int(light))
        return frozenset(chosen)

    @abstractmethod
    def _do_switch(self, lights: frozenset[int]) -> None:
        """Light exactly ``lights`` (validated, non-empty)."""

    @abstractmethod
    def _do_all_off(self) -> None:
        """Switch everything off."""

    @abstractmethod
    def _do_set_level(self, level: int) -> None:
        """Set the PWM level (validated)."""

    @abstractmethod
    def _do_state(self) -> LightState:
        """Return what is lit."""

    @abstractmethod
    def _do_close(self) -> None:
        """Release the transport (lights are already off, or could not be switched off)."""


class SerialLightController(LightController):
    """A protocol-v1 light controller on a serial port (docs/rig-protocol.md).

    Parameters
    ----------
    port : str or serial.SerialBase
        Anything ``serial.serial_for_url`` opens (``/dev/ttyACM0``, ``/dev/pts/5``,
        ``socket://host:port``, ``pslabsim://rig?lights=24``), or an open port object.
    lights : int
        Number of lights the rig file lists; the controller must report the same.
    level : int
        PWM level set on open (0-255).
    watchdog_ms : int
        The controller switches everything off after this long without a command (0 = never).
        Choose it longer than the longest exposure plus camera download.
    reply_timeout : float
        Seconds to wait for each reply.
    retries : int
        Extra attempts after a lost or garbled reply before giving up.
    boot_timeout : float
        Seconds to wait on open for the board to boot (most Arduinos reset when the port
        opens and announce ``READY`` after ~1.5 s).
    baudrate : int
        115200 for protocol v1.

    Raises
    ------
    RigError
        The port cannot be opened, nothing answers, or it is not a protocol-v1 controller with
        ``lights`` lights.

    """

    #: Reboots tolerated within one exchange (each costs a re-handshake).
    MAX_REBOOTS = 3

    def __init__(
        self,
        port: str | Any,
        lights: int,
        *,
        level: int = MAX_LEVEL,
        watchdog_ms: int = DEFAULT_WATCHDOG_MS,
        reply_timeout: float = 0.5,
        retries: int = 3,
        boot_timeout: float = 2.5,
        baudrate: int = 115200,
    ) -> None:
        super().__init__(lights)
        if isinstance(level, bool) or not isinstance(level, int) or not 0 <= level <= MAX_LEVEL:
            raise RigError(f"light level must be 0-{MAX_LEVEL}, not {level!r}")
        if (
            isinstance(watchdog_ms, bool)
            or not isinstance(watchdog_ms, int)
            or not 0 <= watchdog_ms <= 3_600_000
        ):
            raise RigError(f"watchdog must be 0-3600000 ms, not {watchdog_ms!r}")
        if reply_timeout <= 0 or retries < 0 or boot_timeout < 0:
            raise RigError("reply_timeout must be > 0, retries and boot_timeout >= 0")
        self._level = level
        self._watchdog_ms = watchdog_ms
        self._reply_timeout = float(reply_timeout)
        self._retries = int(retries)
        self._boot_timeout = float(boot_timeout)
        self._wanted: frozenset[int] = frozenset()
        self._reboots = 0  # in a row, within the current exchange
        self._reboots_seen = 0
        if isinstance(port, str):
            name = port
            try:
                port = serial.serial_for_url(
                    port, baudrate=baudrate, timeout=POLL_S, exclusive=True
                )
            except (serial.SerialException, OSError, ValueError) as exc:
                raise RigError(f"cannot open light controller port {name}: {exc}") from None
        else:
            name = str(
                getattr(port, "portstr", None) or getattr(port, "port", None) or type(port).__name__
            )
        self.port_name = name
        self._link = SerialLink(port, name)
        try:
            with self._link.lock:
                self._handshake()
        except BaseException:
            self._closed = True
            self._link.close()
            raise

    @property
    def reboots_seen(self) -> int:
        """How many times the controller rebooted since it was opened (each was recovered).

        The driver restores the lit lights after a reboot, so ``state()`` cannot tell that an
        exposure ran in the dark; compare this count before and after the exposure.
        """
        return self._reboots_seen

    # -- hooks -------------------------------------------------------------------------------

    def _do_switch(self, lights: frozenset[int]) -> None:
        command = "ON " + " ".join(str(i) for i in sorted(lights))
        if len(command) > MAX_LINE:
            raise RigError(
                f"cannot light {len(lights)} lights at once: the command exceeds {MAX_LINE} "
                "characters"
            )
        self._wanted = lights
        self._command(command)

    def _do_all_off(self) -> None:
        self._wanted = frozenset()
        self._command("OFF")

    def _do_set_level(self, level: int) -> None:
        self._level = level
        self._command(f"LEVEL {level}")

    def _do_state(self) -> LightState:
        reply = self._command("STATE")
        numbers_ = reply.split()[1:]
        lit = frozenset() if numbers_ == ["NONE"] else frozenset(int(i) for i in numbers_)
        return LightState(lit, self._level)

    def _do_close(self) -> None:
        self._link.close()

    # -- protocol ----------------------------------------------------------------------------

    def _command(self, command: str) -> str:
        """Run one exchange; on failure try to switch off, then raise RigError."""
        try:
            return self._exchange(command)
        except RigError:
            if command != "OFF":
                self._emergency_off()
            raise

    def _emergency_off(self) -> None:
        # One best-effort OFF after a failure; the watchdog covers the case where it is lost too.
        with self._link.lock:
            try:
                self._link.drain()
                self._link.send("OFF")
                reply = self._link.read_line(self._reply_timeout)
                if reply != "OK OFF":
                    log.warning(
                        "%s: OFF after a failure not confirmed (received %r)", self.port_name, reply
                    )
            except RigError as exc:
                log.warning("%s: OFF after a failure failed: %s", self.port_name, exc)

    def _exchange(self, command: str) -> str:
        """Send ``command``, return its checked reply; retry bad replies, survive reboots."""
        with self._link.lock:
            received: list[str] = []
            attempts = 0
            while True:
                attempts += 1
                # A READY among stale input: the board reset since the last exchange (power
                # glitch, hardware watchdog) and forgot the level, the watchdog and what was lit.
                ready = [line for line in self._link.drain() if line.startswith("READY ")]
                if ready:
                    self._recover_from_reboot(ready[-1], command)
                self._link.send(command)
                reply = self._link.read_line(self._reply_timeout)
                if reply is not None and reply.startswith("READY "):
                    # The board reset instead of answering; re-send after recovering.
                    self._recover_from_reboot(reply, command)
                    attempts -= 1
                    continue
                if reply is not None and self._reply_matches(command, reply):
                    self._reboots = 0
                    return reply
                received.append("nothing" if reply is None else repr(reply))
                # A validated command is refused only if the line was corrupted on its way (an
                # ERR then is spurious, and the command idempotent) or the controller is wrong.
                refused = reply is not None and reply.startswith("ERR ") and reply[4:5].isdigit()
                if attempts > self._retries and refused:
                    raise RigError(
                        f"light controller at {self.port_name} refused {command!r} "
                        f"{attempts} times: {reply}"
                    )
                if attempts > self._retries:
                    raise RigError(
                        f"light controller at {self.port_name}: no valid reply to {command!r} "
                        f"after "
                        f"{attempts} attempts (received: {', '.join(received)})"
                    )
                log.info("%s: retrying %r (received %s)", self.port_name, command, received[-1])

    def _recover_from_reboot(self, ready_line: str, command: str) -> None:
        """Handshake again after a ``READY`` and restore the level, watchdog and lit lights."""
        self._reboots += 1
        self._reboots_seen += 1
        if self._reboots > self.MAX_REBOOTS:
            raise RigError(
                f"light controller at {self.port_name} keeps rebooting "
                f"({self._reboots} times while sending {command!r})"
            )
        log.warning("%s: controller rebooted (%r); handshaking again", self.port_name, ready_line)
        self._check_identity(ready_line)
        self._configure()
        if self._wanted and command.split()[0] not in ("ON", "OFF"):
            self._exchange("ON " + " ".join(str(i) for i in sorted(self._wanted)))

    def _reply_matches(self, command: str, reply: str) -> bool:
        name = command.split()[0]
        if name == "ID":
            return _ID_REPLY.match(reply) is not None and reply.startswith("ID ")
        if name == "STATE":
            return _STATE_REPLY.match(reply) is not None and all(
                1 <= int(i) <= self._count for i in reply.split()[1:] if i != "NONE"
            )
        return reply == "OK " + command

    def _check_identity(self, reply: str) -> None:
        match = _ID_REPLY.match(reply)
        if match is None:
            raise RigError(f"{self.port_name} is not a ps-lab light controller (it said {reply!r})")
        name, version, count = match.group(1), int(match.group(2)), int(match.group(3))
        if name != PROTOCOL_NAME:
            raise RigError(
                f"{self.port_name} is not a ps-lab light controller (it says it is {name!r})"
            )
        if version != PROTOCOL_VERSION:
            raise RigError(
                f"light controller at {self.port_name} speaks protocol version {version}; "
                f"this ps-lab speaks version {PROTOCOL_VERSION}: update the firmware or ps-lab"
            )
        if count != self._count:
            raise RigError(
                f"light controller at {self.port_name} has {count} lights, expected {self._count} "
                "(rig file or --lights)"
            )

    def _configure(self) -> None:
        self._exchange(f"WATCHDOG {self._watchdog_ms}")
        self._exchange(f"LEVEL {self._level}")

    def _handshake(self) -> None:
        # Ask at once: a board that does not reset on open (or a pty) answers ID now; one that
        # resets loses the ID in its bootloader and announces READY when its sketch starts.
        self._link.send("ID")
        deadline = time.monotonic() + max(self._boot_timeout, self._reply_timeout)
        identity = None
        while (remaining := deadline - time.monotonic()) > 0:
            line = self._link.read_line(remaining)
            if line is None:
                break
            if line.startswith("ID "):
                identity = line
                break
            if line.startswith("READY "):
                identity = line
                # The answer to our ID may follow, or the bootloader swallowed it.
                deadline = min(deadline, time.monotonic() + self._reply_timeout)
            else:
                log.debug("%s: ignoring %r while waiting for the controller", self.port_name, line)
        if identity is None:
            try:
                identity = self._exchange("ID")
            except RigError as exc:
                raise RigError(
                    f"no ps-lab light controller answers at {self.port_name} "
                    f"(is it the right port, flashed with rigs/firmware?): {exc}"
                ) from None
        # A garbled identity and a different controller look alike in one reply: believe a wrong
        # identity only when the controller says it twice.
        for attempt in range(self._retries + 1):
            try:
                self._check_identity(identity)
                break
            except RigError:
                if attempt == self._retries:
                    raise
                again = self._exchange("ID")
                if again.split()[1:] == identity.split()[1:]:
                    raise
                identity = again
        self._configure()
        self._exchange("OFF")


def walk_lights(
    controller: LightController,
    *,
    dwell_s: float = 0.0,
    progress: Callable[[int], None] | None = None,
) -> None:
    """Light each light alone, check that the controller reports exactly it, then switch off.

    Parameters
    ----------
    controller : LightController
        An open controller.
    dwell_s : float
        Seconds each light stays on (time for a person to look at the rig).
    progress : callable, optional
        Called with 1 after each light.

    Raises
    ------
    RigError
        When the controller reports other lights than the one switched on.

    """
    for light in range(1, controller.count + 1):
        controller.switch(light)
        reported = controller.state().lit
        if reported != {light}:
            controller.all_off()
            shown = " ".join(map(str, sorted(reported))) or "none"
            raise RigError(f"switched on light {light} but the controller reports lights {shown}")
        if dwell_s > 0:
            time.sleep(dwell_s)
        if progress is not None:
            progress(1)
    controller.all_off()
