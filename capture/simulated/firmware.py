"""The simulated light controller: protocol v1 "firmware" in Python, with fault injection.

The simulator is a real implementation that a rig file can choose instead of hardware; it is
exposed three ways:

- in-process, as the pyserial URL ``pslabsim://NAME?lights=24&faults=garble@7&seed=1`` (the
  handler lives in ``protocol_pslabsim.py``; :func:`firmware_for` returns the firmware behind a
  name, so the simulated camera can ask what is lit);
- as a real pseudo-terminal served by :class:`~ps_lab.capture.simulated.pty_server.PtyServer`
  (``ps-lab rig serve-sim``), which the driver opens through the operating system's serial layer
  like ``/dev/ttyACM0``;
- across processes, through a JSON state file
  (:func:`~ps_lab.capture.simulated.pty_server.state_file_reader`).

Faults (``drop``, ``garble``, ``delay``, ``reboot``, ``silence``) are tied to the 1-based count of
command lines the controller received since it was created (reboots do not reset the count), or
drawn with a probability from a seeded generator.
"""

from __future__ import annotations

import itertools
import logging
import random
import re
import threading
import time
import urllib.parse
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ps_lab.capture.faults import FAULT_KINDS, Fault, parse_faults
from ps_lab.capture.light_controllers import (
    DEFAULT_WATCHDOG_MS,
    MAX_LEVEL,
    MAX_LINE,
    PROTOCOL_NAME,
    PROTOCOL_VERSION,
    LightState,
)
from ps_lab.errors import RigError

__all__ = [
    "FAULT_KINDS",
    "Fault",
    "LightState",
    "LogEntry",
    "ManualClock",
    "Reply",
    "SimulatedFirmware",
    "firmware_for",
    "firmware_from_url",
    "parse_faults",
    "register_firmware",
]

log = logging.getLogger(__name__)


#: Largest watchdog period a controller accepts (one hour).
MAX_WATCHDOG_MS = 3_600_000
# Numbers saturate here while parsing so the C++ core can use 32-bit arithmetic; any value this
# large is out of range for every argument.
_NUMBER_CAP = 100_000_000


@dataclass(frozen=True)
class Reply:
    """What the controller sends back for one received line.

    Attributes
    ----------
    lines : list of str
        Reply lines without terminator (characters 0-255; a garbled reply may hold non-ASCII).
    delay_s : float
        Seconds after which the transport delivers them.

    """

    lines: list[str]
    delay_s: float = 0.0


@dataclass(frozen=True)
class LogEntry:
    """One event in the controller's log.

    ``kind`` is ``"command"`` (executed; ``text`` is the line as received), ``"ignored"`` (received
    while hung), ``"watchdog"`` (the watchdog switched everything off), ``"boot"``, or ``"fault"``
    (``text`` names the fault). ``time_ms`` is the firmware clock.
    """

    kind: str
    text: str
    time_ms: int


class ManualClock:
    """A clock for the watchdog that only moves when told to (tests).

    Call it for the time in seconds, like :func:`time.monotonic`.
    """

    def __init__(self, start_ms: int = 0) -> None:
        self._ms = int(start_ms)
        self._lock = threading.Lock()

    def __call__(self) -> float:
        """Return the time in seconds."""
        with self._lock:
            return self._ms / 1000.0

    def advance(self, seconds: float) -> None:
        """Move the clock forward by ``seconds`` (rounded to whole milliseconds)."""
        self.advance_ms(round(seconds * 1000.0))

    def advance_ms(self, milliseconds: int) -> None:
        """Move the clock forward by ``milliseconds``."""
        if milliseconds < 0:
            raise ValueError("a clock does not run backwards")
        with self._lock:
            self._ms += int(milliseconds)


_WORD_SEPARATOR = re.compile(r"[ \t]+")


def _parse_number(token: str) -> int | None:
    # Decimal digits only (no sign, no spaces); saturates like the C++ core.
    if not token or not all("0" <= ch <= "9" for ch in token):
        return None
    return min(int(token), _NUMBER_CAP)


class SimulatedFirmware:
    """Protocol v1 state machine of a light controller with ``lights`` LEDs, plus fault injection.

    Parameters
    ----------
    lights : int
        Number of lights N (numbered 1..N).
    faults : fault specification, optional
        See :func:`parse_faults`.
    seed : int
        Seeds probabilistic faults and the bits a garbled reply flips.
    delay_s : float
        How late a ``delay`` fault delivers its reply (seconds; longer than the driver's timeout).
    clock : callable returning seconds
        Drives the watchdog (default :func:`time.monotonic`; :class:`ManualClock` in tests).

    Notes
    -----
    Thread-safe. :meth:`handle_line` is the pure protocol (fault injection applied, delays not);
    transports call :meth:`respond`, which also says how late to deliver the reply.

    """

    def __init__(
        self,
        lights: int = 24,
        *,
        faults: Any = (),
        seed: int = 0,
        delay_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if isinstance(lights, bool) or not isinstance(lights, int) or not 1 <= lights <= 255:
            raise RigError(f"a simulated controller has 1-255 lights, not {lights!r}")
        self.lights = lights
        self.faults = parse_faults(faults)
        self.delay_s = float(delay_s)
        self.clock = clock
        self.log: list[LogEntry] = []
        self.command_count = 0
        self.boots = 0
        self.hung = False
        self._rng = random.Random(seed)
        self._lock = threading.RLock()
        self._listeners: list[Callable[[LightState], None]] = []
        self._outputs: list[Callable[[str], None]] = []
        self._lit: frozenset[int] = frozenset()
        self._level = MAX_LEVEL
        self._watchdog_ms = DEFAULT_WATCHDOG_MS
        self._last_command_ms = self._now_ms()
        self._watchdog_fired = False

    # -- observation -------------------------------------------------------------------------

    def state(self) -> LightState:
        """Return what is lit now (after letting the watchdog act)."""
        with self._lock:
            self.poll()
            return LightState(self._lit, self._level)

    @property
    def watchdog_ms(self) -> int:
        """Current watchdog period in ms (0 = off)."""
        return self._watchdog_ms

    def add_listener(self, listener: Callable[[LightState], None]) -> None:
        """Call ``listener(state)`` after every change of the lit lights or the level."""
        with self._lock:
            self._listeners.append(listener)
            listener(LightState(self._lit, self._level))

    def commands(self) -> list[str]:
        """Return the executed command lines, oldest first."""
        return [entry.text for entry in self.log if entry.kind == "command"]

    def ended_safely(self) -> bool:
        """Return whether nothing is lit and the last event was an ``OFF`` or the watchdog.

        This is the safety property every driver path must leave behind.
        """
        with self._lock:
            self.poll()
            if self._lit:
                return False
            for entry in reversed(self.log):
                if entry.kind == "watchdog":
                    return True
                if entry.kind == "command":
                    return entry.text.split()[:1] == ["OFF"] and len(entry.text.split()) == 1
            return False

    # -- lifecycle ---------------------------------------------------------------------------

    def ready_line(self) -> str:
        """Return the boot announcement ``READY ps-lab-lights 1 <N>``."""
        return f"READY {PROTOCOL_NAME} {PROTOCOL_VERSION} {self.lights}"

    def reboot(self) -> str:
        """Reset as after power-up (all off, level 255, default watchdog); return the READY line."""
        with self._lock:
            self.boots += 1
            self.hung = False
            self._watchdog_ms = DEFAULT_WATCHDOG_MS
            self._last_command_ms = self._now_ms()
            self._watchdog_fired = False
            self._log("boot", self.ready_line())
            self._set(frozenset(), MAX_LEVEL)
            return self.ready_line()

    def add_output(self, sink: Callable[[str], None]) -> Callable[[], None]:
        """Attach a transport for unsolicited lines (a ``READY`` after :meth:`power_cycle`).

        Returns the function that detaches it.
        """
        with self._lock:
            self._outputs.append(sink)

        def remove() -> None:
            with self._lock:
                if sink in self._outputs:
                    self._outputs.remove(sink)

        return remove

    def power_cycle(self) -> None:
        """Reset between commands, as a brown-out would, and announce ``READY`` unasked."""
        with self._lock:
            line = self.reboot()
            for sink in list(self._outputs):
                sink(line)

    def poll(self) -> bool:
        """Let the watchdog act; return True if it switched the lights off just now."""
        with self._lock:
            if self._watchdog_ms == 0 or self._watchdog_fired:
                return False
            if self._now_ms() - self._last_command_ms < self._watchdog_ms:
                return False
            self._watchdog_fired = True
            self._log("watchdog", f"no command for {self._watchdog_ms} ms")
            self._set(frozenset(), self._level)
            return True

    # -- protocol ----------------------------------------------------------------------------

    def handle_line(self, line: str) -> list[str]:
        """Process one received line (terminator optional); return the reply lines."""
        return self.respond(line).lines

    def respond(self, line: str) -> Reply:
        """Process one received line with fault injection; return the reply and its delay."""
        line = line.replace("\r", "").rstrip("\n")
        if not line.strip(" \t"):
            return Reply([])  # a blank line is not a command
        with self._lock:
            self.poll()
            if self.hung:
                self._log("ignored", line)
                return Reply([])
            self.command_count += 1
            chosen = self._fault_for(self.command_count)
            fault = None if chosen is None else chosen.kind
            if chosen is not None:
                self._log("fault", f"{chosen} at command {self.command_count}: {line}")
            if fault == "silence":
                self.hung = True
                self._log("ignored", line)
                return Reply([])
            if fault == "reboot":
                return Reply([self.reboot()])
            reply = self._execute(line)
            if fault == "drop":
                return Reply([])
            if fault == "garble":
                return Reply([self._garble(reply)])
            if fault == "delay":
                return Reply([reply], delay_s=self.delay_s)
            return Reply([reply])

    def _execute(self, line: str) -> str:
        self._log("command", line)
        self._last_command_ms = self._now_ms()
        self._watchdog_fired = False
        if len(line) > MAX_LINE:
            return "ERR 2 bad argument"
        # Only spaces and tabs separate words, and only ASCII letters fold case, as in the C++ core.
        tokens = _WORD_SEPARATOR.split(line.strip(" \t"))
        name, args = (tokens[0].upper() if tokens[0].isascii() else tokens[0]), tokens[1:]
        if name in ("ID", "OFF", "STATE"):
            if args:
                return "ERR 2 bad argument"
            if name == "ID":
                return f"ID {PROTOCOL_NAME} {PROTOCOL_VERSION} {self.lights}"
            if name == "OFF":
                self._set(frozenset(), self._level)
                return "OK OFF"
            if not self._lit:
                return "STATE NONE"
            return "STATE " + " ".join(str(i) for i in sorted(self._lit))
        if name == "ON":
            if not args:
                return "ERR 2 bad argument"
            numbers = []
            for token in args:
                value = _parse_number(token)
                if value is None:
                    return "ERR 2 bad argument"
                if not 1 <= value <= self.lights:
                    return "ERR 3 light out of range"
                numbers.append(value)
            self._set(frozenset(numbers), self._level)
            return "OK ON " + " ".join(str(i) for i in numbers)
        if name in ("LEVEL", "WATCHDOG"):
            limit = MAX_LEVEL if name == "LEVEL" else MAX_WATCHDOG_MS
            value = _parse_number(args[0]) if len(args) == 1 else None
            if value is None or value > limit:
                return "ERR 2 bad argument"
            if name == "LEVEL":
                self._set(self._lit, value)
            else:
                self._watchdog_ms = value
            return f"OK {name} {value}"
        return "ERR 1 unknown command"

    # -- internals ---------------------------------------------------------------------------

    def _now_ms(self) -> int:
        return round(self.clock() * 1000.0)

    def _log(self, kind: str, text: str) -> None:
        self.log.append(LogEntry(kind, text, self._now_ms()))

    def _set(self, lit: frozenset[int], level: int) -> None:
        changed = (lit, level) != (self._lit, self._level)
        self._lit, self._level = lit, level
        if changed:
            state = LightState(lit, level)
            for listener in self._listeners:
                listener(state)

    def _fault_for(self, count: int) -> Fault | None:
        chosen = None
        for fault in self.faults:
            if fault.at is not None:
                hit = fault.at == count
            else:
                hit = self._rng.random() < fault.probability  # draw for every fault: reproducible
            if hit and chosen is None:
                chosen = fault
        return chosen

    def _garble(self, reply: str) -> str:
        # Flip one or two bits, as line noise does; never create a line break (that would be two
        # replies, a different fault) and never leave the reply intact.
        data = bytearray(reply.encode("latin-1"))
        for _ in range(1 + self._rng.randrange(2)):
            while True:
                position = self._rng.randrange(len(data))
                flipped = data[position] ^ (1 << self._rng.randrange(8))
                if flipped not in (0x0A, 0x0D):
                    data[position] = flipped
                    break
        text = data.decode("latin-1")
        return text if text != reply else text + "?"


# -- in-process registry (for the pslabsim:// URL handler) -------------------------------------

_registry: dict[str, SimulatedFirmware] = {}
_registry_lock = threading.Lock()
_anonymous = itertools.count(1)
_URL_OPTIONS = ("lights", "faults", "seed", "name", "delay", "clock")


def register_firmware(name: str, firmware: SimulatedFirmware) -> None:
    """Make ``firmware`` the controller behind ``pslabsim://NAME`` (replacing any earlier one)."""
    with _registry_lock:
        _registry[name] = firmware


def firmware_for(name: str) -> SimulatedFirmware:
    """Return the simulated controller behind ``pslabsim://NAME``; RigError if there is none."""
    with _registry_lock:
        try:
            return _registry[name]
        except KeyError:
            raise RigError(f"no simulated light controller named {name!r} is running") from None


def firmware_from_url(url: str) -> tuple[str, SimulatedFirmware]:
    """Find or create the controller a ``pslabsim://`` URL names; return ``(name, firmware)``.

    ``pslabsim://NAME?lights=24&faults=garble@7,drop@p0.1&seed=1&delay=1.0&clock=manual``.
    A URL naming a registered controller reuses it (the lab's board stays the same across
    opens); other options must then be absent or agree. Without a name a new, unnamed
    controller is created. ``clock=manual`` gives it a :class:`ManualClock`.
    """
    parts = urllib.parse.urlsplit(url)
    if parts.scheme.lower() != "pslabsim":
        raise RigError(f"not a simulated-controller URL: {url!r} (expected pslabsim://...)")
    options: dict[str, str] = {}
    for key, value in urllib.parse.parse_qsl(parts.query, keep_blank_values=True):
        if key not in _URL_OPTIONS:
            raise RigError(f"unknown option {key!r} in {url!r} (known: {', '.join(_URL_OPTIONS)})")
        options[key] = value
    name = (parts.netloc or "").strip() or options.get("name", "").strip()
    try:
        lights = int(options["lights"]) if "lights" in options else None
        seed = int(options.get("seed", "0"))
        delay_s = float(options.get("delay", "1.0"))
    except ValueError as exc:
        raise RigError(f"bad number in {url!r}: {exc}") from None
    clock_name = options.get("clock", "real")
    if clock_name not in ("real", "manual"):
        raise RigError(f"clock must be 'real' or 'manual' in {url!r}")
    with _registry_lock:
        existing = _registry.get(name) if name else None
        if existing is not None:
            if lights is not None and lights != existing.lights:
                raise RigError(
                    f"simulated controller {name!r} has {existing.lights} lights, "
                    f"the URL asks for {lights}"
                )
            return name, existing
        firmware = SimulatedFirmware(
            24 if lights is None else lights,
            faults=options.get("faults"),
            seed=seed,
            delay_s=delay_s,
            clock=ManualClock() if clock_name == "manual" else time.monotonic,
        )
        name = name or f"anonymous-{next(_anonymous)}"
        _registry[name] = firmware
        return name, firmware


# -- line handling shared by the URL handler and the pty server ------------------------------


@dataclass
class _Outbox:
    # Replies waiting for their delivery time (delay faults), in order.
    pending: list[tuple[float, bytes]] = field(default_factory=list)

    def add(self, reply: Reply) -> None:
        due = time.monotonic() + reply.delay_s
        for line in reply.lines:
            self.pending.append((due, line.encode("latin-1") + b"\n"))

    def due(self) -> bytes:
        now = time.monotonic()
        ready = [data for when, data in self.pending if when <= now]
        self.pending = [(when, data) for when, data in self.pending if when > now]
        return b"".join(ready)

    def next_due(self) -> float | None:
        return min((when for when, _ in self.pending), default=None)


class LineAssembler:
    """Split a byte stream into lines for the firmware (bounded: endless lines eat no memory)."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[str]:
        """Add received bytes; return the complete lines (without line feeds)."""
        # Carriage returns are ignored wherever they are; a line is cut at MAX_LINE + 1
        # characters, which is enough to know it is too long.
        self._buffer += data.replace(b"\r", b"")
        *lines, rest = self._buffer.split(b"\n")
        self._buffer = bytearray(rest[: MAX_LINE + 1])
        return [line[: MAX_LINE + 1].decode("latin-1") for line in lines]
