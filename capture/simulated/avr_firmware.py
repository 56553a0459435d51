"""The real firmware in the loop: the compiled Arduino sketch runs in simavr behind a pty.

The sketch in ``rigs/firmware/ps_lab_lights`` is built for an Uno with Debian's arduino-mk; the C
harness in ``rigs/firmware/simavr`` loads its ELF into simavr (an ATmega328P at 16 MHz, in step
with the wall clock), puts UART0 on a pseudo-terminal and reports the level of every light pin.
The driver opens the pty through the operating system's serial layer exactly as it opens
``/dev/ttyACM0``; opening it resets the MCU, as the DTR line resets an Uno.

Light *i* is the pin ``pins[i - 1]`` -- the rig's wiring. The harness publishes which lights'
pins are driven (a JSON state file in the format of ``ps-lab rig serve-sim --state-file``, plus
per-light ``levels`` and ``duty``), so a simulated camera renders what the pins say, and a pin
table in the sketch that disagrees with the wiring shows up in the images.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import select
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from ps_lab.capture.light_controllers import LightState
from ps_lab.capture.simulated.pty_server import read_state_file, serve_until_interrupted
from ps_lab.capture.simulated.serving import ServedSimulator
from ps_lab.errors import RigError
from ps_lab.io.files import staged_folder

__all__ = [
    "FIRMWARE_DIR",
    "FIRMWARE_PACKAGES",
    "EmulatedFirmware",
    "FirmwareToolchainMissing",
    "PinState",
    "build_harness",
    "build_sketch",
    "check_avr_elf",
    "firmware_build_dir",
    "missing_packages",
    "parse_pins",
    "require_toolchain",
    "serve_firmware",
    "sketch_pins",
]

log = logging.getLogger(__name__)

#: rigs/firmware of this checkout (the sketch and the harness are built from the source tree).
FIRMWARE_DIR = Path(__file__).resolve().parents[2] / "rigs" / "firmware"

#: The Debian packages this needs, each with a file or command that proves it is installed
#: (``libsimavr-dev`` brings ``libsimavr2`` and ``libsimavrparts1``).
FIRMWARE_PACKAGES = {
    "arduino-mk": "/usr/share/arduino/Arduino.mk",
    "arduino-core-avr": "/usr/share/arduino/hardware/arduino/avr/cores/arduino/Arduino.h",
    "libsimavr-dev": "/usr/include/simavr/parts/uart_pty.h",
    "gcc": "cc",
    "make": "make",
}
#: Needed only to build the sketch (not to run a given ELF).
_SKETCH_PACKAGES = ("arduino-mk", "arduino-core-avr")


class FirmwareToolchainMissing(RigError):
    """The Arduino toolchain or simavr is not installed (names the Debian packages)."""


def missing_packages(*, sketch: bool = True) -> list[str]:
    """Return the Debian packages of :data:`FIRMWARE_PACKAGES` that are not installed.

    With ``sketch=False``, only those needed to run an ELF built elsewhere.
    """
    missing = []
    for package, proof in FIRMWARE_PACKAGES.items():
        if not sketch and package in _SKETCH_PACKAGES:
            continue
        found = Path(proof).exists() if proof.startswith("/") else shutil.which(proof)
        if not found:
            missing.append(package)
    return missing


def require_toolchain(*, sketch: bool = True) -> None:
    """Raise :class:`FirmwareToolchainMissing` naming what to install, if anything is missing."""
    missing = " ".join(missing_packages(sketch=sketch))
    if missing:
        raise FirmwareToolchainMissing(
            f"the emulated firmware needs Debian packages that are not installed: {missing} "
            f"(sudo apt-get install {missing})"
        )


_PIN_TABLE = re.compile(r"kLightPins\s*\[\s*\]\s*=\s*\{([^}]*)\}")


def sketch_pins(sketch_dir: Path | str | None = None) -> tuple[int, ...]:
    """Read the light pin table ``kLightPins`` from a sketch's ``.ino`` file.

    Parameters
    ----------
    sketch_dir : path, optional
        The sketch folder (default ``rigs/firmware/ps_lab_lights``).

    Returns
    -------
    tuple of int
        Arduino pin of light 1, 2, ...

    """
    folder = Path(sketch_dir) if sketch_dir is not None else FIRMWARE_DIR / "ps_lab_lights"
    sources = sorted(folder.glob("*.ino"))
    for source in sources:
        match = _PIN_TABLE.search(source.read_text(errors="replace"))
        if match:
            try:
                return tuple(int(p) for p in match.group(1).replace(" ", "").split(",") if p)
            except ValueError:
                break
    raise RigError(
        f"cannot read the pin table kLightPins[] = {{...}} of the sketch in {folder}: "
        "give the wiring with --pins"
    )


def firmware_build_dir() -> Path:
    """Where builds are cached: ``$PS_LAB_CACHE`` or ``~/.cache/ps-lab``, then ``firmware``."""
    root = os.environ.get("PS_LAB_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "ps-lab"
    )
    return Path(root) / "firmware"


def _digest(paths: Sequence[Path], extra: str = "") -> str:
    h = hashlib.sha256(extra.encode())
    for path in sorted(paths):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def _run_make(args: list[str], what: str) -> None:
    try:
        result = subprocess.run(
            ["make", "-s", *args], capture_output=True, text=True, timeout=600, check=False
        )
    except FileNotFoundError:
        require_toolchain()
        raise
    if result.returncode != 0:
        tail = "\n".join((result.stdout + result.stderr).strip().splitlines()[-15:])
        raise RigError(f"building {what} failed:\n{tail}")


def build_sketch(
    sketch_dir: Path | str | None = None,
    build_dir: Path | str | None = None,
    *,
    defines: str = "",
) -> Path:
    """Build the sketch for an Uno with arduino-mk, unless a build of the same sources exists.

    Parameters
    ----------
    sketch_dir : path, optional
        The sketch folder with its Makefile (default ``rigs/firmware/ps_lab_lights``).
    build_dir : path, optional
        Cache folder (default :func:`firmware_build_dir`); the build goes into a subfolder named
        after a hash of the sources, so an edited sketch is rebuilt.
    defines : str
        Extra compiler flags (``PS_LAB_DEFINES``), e.g. ``-DPS_LAB_HARDWARE_WATCHDOG=0``.

    Returns
    -------
    Path
        The ELF file.

    """
    require_toolchain()
    folder = Path(sketch_dir) if sketch_dir is not None else FIRMWARE_DIR / "ps_lab_lights"
    sources = [p for p in folder.iterdir() if p.suffix in (".ino", ".cpp", ".h", ".c")]
    if not sources or not (folder / "Makefile").exists():
        raise RigError(f"{folder} is not a sketch folder with a Makefile (arduino-mk)")
    digest = _digest([*sources, folder / "Makefile"], defines)
    out = Path(build_dir or firmware_build_dir()) / f"sketch-{digest}"
    if not sorted(out.glob("*.elf")):
        with staged_folder(out, error=RigError) as staging:
            _run_make(
                ["-C", str(folder), f"OBJDIR={staging.resolve()}", f"PS_LAB_DEFINES={defines}"],
                f"the sketch {folder}",
            )
            if not list(staging.glob("*.elf")):
                raise RigError(f"building the sketch {folder} produced no .elf file")
    return sorted(out.glob("*.elf"))[0]


def build_harness(build_dir: Path | str | None = None) -> Path:
    """Build the simavr harness ``rigs/firmware/simavr`` (cached by source hash); return it."""
    require_toolchain(sketch=False)
    source = FIRMWARE_DIR / "simavr"
    inputs = [source / "ps_lab_avr.c", source / "Makefile"]
    out = Path(build_dir or firmware_build_dir()) / f"harness-{_digest(inputs)}"
    binary = out / "ps_lab_avr"
    if not binary.exists():
        with staged_folder(out, error=RigError) as staging:
            _run_make(["-C", str(source), f"BUILD={staging.resolve()}"], "the simavr harness")
    return binary


@dataclass(frozen=True)
class PinState:
    """What the emulated MCU drives on the light pins.

    Attributes
    ----------
    lit : frozenset of int
        Lights (1-based, in wiring order) whose pin drives a level above 0.
    levels : tuple of int
        Per light, 0-255: 255/0 for a digital pin, the PWM compare value for a dimmed one.
    duty : tuple of float
        Per light, the fraction of time the pin is high.

    """

    lit: frozenset[int]
    levels: tuple[int, ...]
    duty: tuple[float, ...]

    def light_state(self) -> LightState:
        """As a :class:`LightState`: the lit lights and the level of the brightest one."""
        return LightState(self.lit, max((self.levels[i - 1] for i in self.lit), default=0))


def _read_pin_state(path: Path) -> PinState:
    return read_state_file(
        path,
        lambda data: PinState(
            frozenset(int(i) for i in data["lit"]),
            tuple(int(v) for v in data["levels"]),
            tuple(float(v) for v in data["duty"]),
        ),
        "pin state file",
        "the emulated firmware",
    )


class EmulatedFirmware(ServedSimulator):
    """The compiled sketch running in simavr on a pty (the simavr harness as a child process).

    Parameters
    ----------
    elf : path, optional
        The sketch's ELF (default: build ``sketch_dir`` with :func:`build_sketch`).
    pins : sequence of int, optional
        Wiring: the Arduino pin of light 1, 2, ... (default: the sketch's own pin table).
    sketch_dir : path, optional
        Sketch to build when ``elf`` is not given, and whose pin table is the default wiring.
    state_file : path, optional
        Where the harness publishes the pins (default: a private temporary file).
    boot_ms : int
        How long the MCU stays in reset after the port is opened (the bootloader's time).
    reset_on_open : bool
        Reset when the port is opened, as an Uno does (DTR).
    build_dir : path, optional
        Build cache (default :func:`firmware_build_dir`).

    Examples
    --------
    >>> with EmulatedFirmware() as board:                       # doctest: +SKIP
    ...     with SerialLightController(board.path, lights=12) as controller:
    ...         controller.switch(3)
    ...         board.pin_state().lit
    frozenset({3})

    """

    def __init__(
        self,
        elf: Path | str | None = None,
        *,
        pins: Sequence[int] | None = None,
        sketch_dir: Path | str | None = None,
        state_file: Path | str | None = None,
        boot_ms: int = 250,
        reset_on_open: bool = True,
        build_dir: Path | str | None = None,
    ) -> None:
        self.elf = Path(elf) if elf is not None else None
        self.sketch_dir = Path(sketch_dir) if sketch_dir is not None else None
        self.pins = tuple(int(p) for p in pins) if pins is not None else None
        self.boot_ms = int(boot_ms)
        self.reset_on_open = bool(reset_on_open)
        self.build_dir = build_dir
        self._own_state_dir: str | None = None
        self.state_file = Path(state_file) if state_file is not None else None
        self.path: str | None = None
        self._process: subprocess.Popen[str] | None = None
        self._reader: threading.Thread | None = None

    @property
    def lights(self) -> int:
        """Number of light pins watched."""
        return len(self.pins or ())

    def start(self) -> EmulatedFirmware:
        """Build what is missing, start the harness and wait for its device path; return self."""
        if self._process is not None:
            raise RigError("the emulated firmware is already running")
        if self.elf is not None:
            check_avr_elf(self.elf)
        require_toolchain(sketch=self.elf is None)
        if self.elf is None:
            self.elf = build_sketch(self.sketch_dir, self.build_dir)
        if self.pins is None:
            self.pins = sketch_pins(self.sketch_dir)
        harness = build_harness(self.build_dir)
        try:
            return self._start_harness(harness)
        except BaseException:
            self.stop()  # the private state folder too: nothing is left behind
            raise

    def _start_harness(self, harness: Path) -> EmulatedFirmware:
        assert self.elf is not None and self.pins is not None
        if self.state_file is None:
            self._own_state_dir = tempfile.mkdtemp(prefix="ps-lab-firmware-")
            self.state_file = Path(self._own_state_dir) / "pins.json"
        command = [
            str(harness),
            "--pins",
            ",".join(map(str, self.pins)),
            "--state-file",
            str(self.state_file),
            "--boot-ms",
            str(self.boot_ms),
            *([] if self.reset_on_open else ["--no-reset-on-open"]),
            str(self.elf),
        ]
        log.debug("starting %s", " ".join(command))
        self._process = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1
        )
        assert self._process.stdout is not None
        ready, _, _ = select.select([self._process.stdout], [], [], 30.0)
        first = self._process.stdout.readline().strip() if ready else ""
        if not first.startswith("/"):
            self._process.terminate()
            _, errors = self._process.communicate(timeout=10)
            self._process = None
            reason = (errors or first).strip().splitlines()
            raise RigError(
                f"{self.elf}: the simavr harness did not start with this firmware: "
                f"{reason[-1] if reason else 'no device path'}"
            )
        self.path = first
        self._reader = threading.Thread(target=self._drain, name="ps-lab-avr-pins", daemon=True)
        self._reader.start()
        deadline = time.monotonic() + 10.0
        while not self.state_file.exists() and time.monotonic() < deadline:
            time.sleep(0.005)
        log.info("emulated firmware %s (%d lights) on %s", self.elf, self.lights, self.path)
        return self

    def _drain(self) -> None:
        # One JSON line per pin change; read so the pipe never fills and stalls the MCU.
        assert self._process is not None and self._process.stdout is not None
        for line in self._process.stdout:
            log.debug("pins: %s", line.strip())

    def pin_state(self) -> PinState:
        """What the MCU drives on the light pins now."""
        if self.state_file is None:
            raise RigError("the emulated firmware is not running")
        return _read_pin_state(self.state_file)

    def light_state(self) -> LightState:
        """The lights whose pins are driven, as a :class:`LightState` (for a simulated camera)."""
        return self.pin_state().light_state()

    def reset(self) -> None:
        """Reset the MCU between commands, as a brown-out does (it announces READY again)."""
        if self._process is None:
            raise RigError("the emulated firmware is not running")
        self._process.send_signal(signal.SIGUSR1)

    def stop(self) -> None:
        """Stop the harness (idempotent)."""
        process, self._process = self._process, None
        if process is not None:
            if process.poll() is None:
                process.terminate()
                try:
                    process.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()
            if process.stderr is not None:
                errors = process.stderr.read().strip()
                if errors:
                    log.debug("simavr harness: %s", errors)
                process.stderr.close()
        if self._reader is not None:
            self._reader.join(timeout=5)
            self._reader = None
        if process is not None and process.stdout is not None:
            process.stdout.close()
        if self._own_state_dir is not None:
            shutil.rmtree(self._own_state_dir, ignore_errors=True)
            self._own_state_dir = None
            self.state_file = None

    @property
    def serving(self) -> bool:
        return self._process is not None

    def _wait(self) -> None:
        """Until the harness ends; a non-zero status is a failure."""
        assert self._process is not None
        status = self._process.wait()
        if status != 0:
            raise RigError(f"the simavr harness stopped with status {status}")


#: ``e_machine`` of an Atmel AVR ELF file (the Uno's ATmega328P).
EM_AVR = 83


def check_avr_elf(path: Path) -> None:
    """Refuse, naming the file, what is not a complete 32-bit little-endian AVR ELF file.

    Checked before simavr is started: simavr's own messages on an empty, cut or foreign file
    name nothing, and a foreign architecture would only show as "no device path".
    """
    path = Path(path)
    if not path.is_file():
        raise RigError(f"firmware ELF {path} does not exist (or is not a file)")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise RigError(f"{path}: cannot read the firmware ELF ({exc.strerror})") from None
    if not data:
        raise RigError(f"{path}: empty file, not a firmware ELF for the Uno (avr-gcc's .elf)")
    if data[:4] != b"\x7fELF":
        raise RigError(f"{path}: not an ELF file (avr-gcc's .elf for the Uno is needed)")
    if len(data) < 52:
        raise RigError(f"{path}: truncated ELF ({len(data)} bytes, its header needs 52)")
    if data[4] != 1 or data[5] != 1:
        raise RigError(f"{path}: a 64-bit or big-endian ELF, not firmware for the Uno's AVR")

    def word(at: int, size: int) -> int:
        return int.from_bytes(data[at : at + size], "little")

    machine = word(18, 2)
    if machine != EM_AVR:
        raise RigError(
            f"{path}: an ELF for another processor (e_machine {machine}), not for the Uno's "
            f"AVR ({EM_AVR}): build the sketch for an Uno"
        )
    table, entry_size, entries = word(28, 4), word(42, 2), word(44, 2)
    needed = table + entry_size * entries
    for k in range(entries if needed <= len(data) else 0):
        at = table + k * entry_size
        needed = max(needed, word(at + 4, 4) + word(at + 16, 4))  # p_offset + p_filesz
    if entries == 0 or entry_size < 32 or needed > len(data):
        raise RigError(
            f"{path}: truncated ELF ({len(data)} bytes, its program needs {needed}); rebuild "
            "or copy it again"
        )


def parse_pins(text: str) -> tuple[int, ...]:
    """Read a wiring such as ``"3,5,6,9"`` (Arduino pin of light 1, 2, ...)."""
    try:
        pins = tuple(int(p) for p in text.replace(" ", "").split(","))
    except ValueError:
        raise RigError(
            f"pins must be Arduino pin numbers separated by commas, not {text!r}"
        ) from None
    if any(not 2 <= p <= 19 for p in pins) or len(set(pins)) != len(pins):
        raise RigError(f"each light needs its own Uno pin 2-19, not {text!r}")
    return pins


def serve_firmware(
    *,
    elf: Path | str | None = None,
    state_file: Path | str | None = None,
    pins: str | Sequence[int] | None = None,
    on_ready: Callable[[EmulatedFirmware], None] | None = None,
) -> None:
    """Serve the emulated firmware on a pty until Ctrl-C or SIGTERM (``ps-lab rig serve-firmware``).

    ``pins`` is the wiring (a sequence, or text for :func:`parse_pins`; default: the sketch's
    table). ``on_ready(board)`` is called once the device path exists (to print it). The state
    file, if any, is gone when this returns.
    """
    if isinstance(pins, str):
        pins = parse_pins(pins)
    board = EmulatedFirmware(elf, pins=pins, state_file=state_file)
    serve_until_interrupted(board, on_ready, "emulated firmware")
