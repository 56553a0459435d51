"""The simulated light controller: protocol v1 "firmware" in Python, with fault injection.

The simulator is a real implementation that a rig file can choose instead of hardware; it is
exposed three ways:

- in-process, as the pyserial URL ``pslabsim://NAME?lights=24&faults=garble@7&seed=1`` (the
  handler lives in ``protocol_pslabsim.py``; :func:`firmware_for` returns the firmware behind a
  name, so the simulated camera can ask what is lit);
- as a real pseudo-terminal served by :class:`PtyServer` (``ps-lab rig serve-sim``), which the
  driver opens through the operating system's serial layer like ``/dev/ttyACM0``;
- across processes, through a JSON state file (:func:`state_file_reader`).

Faults (``drop``, ``garble``, ``delay``, ``reboot``, ``silence``) are tied to the 1-based count of
command lines the controller received since it was created (reboots do not reset the count), or
drawn with a probability from a seeded generator.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import queue
import random
import re
import select
import signal
import threading
import time
import tty
import urllib.parse
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ps_lab.capture.lights import (
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
    "PtyServer",
    "Reply",
    "SimulatedFirmware",
    "firmware_for",
    "firmware_from_url",
    "parse_faults",
    "register_firmware",
    "serve_simulator",
    "state_file_reader",
    "write_state_file",
]

log = logging.getLogger(__name__)

#: What can go wrong, in the controller's words:
#: drop - the command is executed but its reply is lost;
#: garble - the command is executed but one or two bits of its reply are flipped;
#: delay - the command is executed and its reply arrives ``delay_s`` later (past the timeout);
#: reboot - the controller resets instead of executing: sends READY, forgets lights/level/watchdog;
#: silence - the controller hangs: it ignores this and every later command and never answers
#: again; its watchdog still switches the lights off (on the Arduino the AVR hardware watchdog
#: resets a hung sketch, and a reset switches every output off).
FAULT_KINDS = ("drop", "garble", "delay", "reboot", "silence")

#: Largest watchdog period a controller accepts (one hour).
MAX_WATCHDOG_MS = 3_600_000
# Numbers saturate here while parsing so the C++ core can use 32-bit arithmetic; any value this
# large is out of range for every argument.
_NUMBER_CAP = 100_000_000


@dataclass(frozen=True)
class Fault:
    """One injected fault.

    Attributes
    ----------
    kind : str
        One of :data:`FAULT_KINDS`.
    at : int or None
        Fire at this 1-based command count (the N-th command line the controller receives).
    probability : float
        Otherwise, fire at each command with this probability (seeded generator).

    """

    kind: str
    at: int | None = None
    probability: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise RigError(
                f"unknown fault kind {self.kind!r}; choose from {', '.join(FAULT_KINDS)}"
            )
        if self.at is None and not 0.0 < self.probability <= 1.0:
            raise RigError(
                f"fault {self.kind!r} needs 'at' (command number) or 'probability' in (0, 1]"
            )
        if self.at is not None and (
            isinstance(self.at, bool) or not isinstance(self.at, int) or self.at < 1
        ):
            raise RigError(
                f"fault {self.kind!r}: 'at' must be a command number >= 1, got {self.at!r}"
            )

    def __str__(self) -> str:
        return (
            f"{self.kind}@{self.at}"
            if self.at is not None
            else f"{self.kind}@p{self.probability:g}"
        )


_FAULT_TEXT = re.compile(r"^\s*([a-z]+)\s*@\s*(p?)([0-9.eE+-]+)\s*$")


def parse_faults(spec: Any) -> tuple[Fault, ...]:
    """Read a fault specification in any of the forms a rig file, a URL or a CLI gives.

    Parameters
    ----------
    spec : None, str, Fault, mapping, or iterable of those
        ``"garble@7,drop@p0.05"`` (a fault at command 7, a fault with probability 0.05 per
        command), ``{"kind": "garble", "at": 7}``, ``{"kind": "drop", "probability": 0.05}``,
        or a list mixing these.

    Returns
    -------
    tuple of Fault

    """
    if spec is None or spec == "":
        return ()
    if isinstance(spec, Fault):
        return (spec,)
    if isinstance(spec, str):
        faults = []
        for item in filter(None, (part.strip() for part in spec.split(","))):
            match = _FAULT_TEXT.match(item)
            if match is None:
                raise RigError(
                    f"cannot read fault {item!r}: write KIND@N or KIND@pP "
                    "(e.g. garble@7, drop@p0.1)"
                )
            kind, is_probability, number = match.groups()
            try:
                if is_probability:
                    faults.append(Fault(kind, probability=float(number)))
                else:
                    faults.append(Fault(kind, at=int(number)))
            except ValueError:
                raise RigError(f"cannot read fault {item!r}: {number!r} is not a number") from None
        return tuple(faults)
    if isinstance(spec, Mapping):
        unknown = set(spec) - {"kind", "at", "probability"}
        if unknown:
            raise RigError(
                f"unknown key {sorted(unknown)[0]!r} in fault {dict(spec)!r} "
                "(kind, at, probability)"
            )
        if "kind" not in spec:
            raise RigError(f"fault {dict(spec)!r} has no 'kind'")
        probability = spec.get("probability", 0.0)
        if isinstance(probability, bool) or not isinstance(probability, int | float):
            raise RigError(f"fault {dict(spec)!r}: 'probability' must be a number")
        return (Fault(str(spec["kind"]), at=spec.get("at"), probability=float(probability)),)
    if isinstance(spec, Iterable):
        return tuple(itertools.chain.from_iterable(parse_faults(item) for item in spec))
    raise RigError(f"cannot read fault specification {spec!r}")


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


# -- state file (for a simulator in another process) -------------------------------------------


def write_state_file(path: Path | str, state: LightState) -> None:
    """Write ``{"lit": [...], "level": v}`` to ``path`` atomically (temporary file + rename)."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    temporary.write_text(json.dumps({"lit": sorted(state.lit), "level": state.level}))
    os.replace(temporary, path)


def state_file_reader(path: Path | str) -> Callable[[], LightState]:
    """Return a function that reads the simulator's current :class:`LightState` from ``path``.

    Raises :class:`RigError` (when called) if the file is missing or unreadable: the simulator is
    not running, and guessing "all off" would hide it.
    """
    path = Path(path)

    def read() -> LightState:
        try:
            data = json.loads(path.read_text())
            lit = frozenset(int(i) for i in data["lit"])
            level = int(data["level"])
        except FileNotFoundError:
            raise RigError(
                f"light state file {path} does not exist: is `ps-lab rig serve-sim` running?"
            ) from None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise RigError(f"cannot read light state file {path}: {exc}") from None
        return LightState(lit, level)

    return read


# -- pseudo-terminal server --------------------------------------------------------------------


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


class PtyServer:
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
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = None

    def serve_forever(self) -> None:
        """Block until interrupted (Ctrl-C) or until the server thread fails; then stop."""
        try:
            while self._thread is not None and self._thread.is_alive():
                self._thread.join(timeout=0.2)
        finally:
            self.stop()
        if self._error is not None:
            raise RigError(f"simulated controller stopped: {self._error}")

    def __enter__(self) -> PtyServer:
        return self.start() if self._thread is None else self

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

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
                log.info("simulated light controller stopped")
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if state_file is not None:
            Path(state_file).unlink(missing_ok=True)
