"""The shared protocol vectors pass on the Python simulator and on the host-compiled C++ core."""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

from ps_lab.capture.simulated.firmware import LineAssembler, ManualClock, SimulatedFirmware

FIRMWARE = Path(__file__).resolve().parents[1] / "rigs" / "firmware"
VECTORS = FIRMWARE / "protocol-vectors.txt"
CORE = FIRMWARE / "ps_lab_lights"


@dataclass(frozen=True)
class Vector:
    line: int
    command: bytes  # or "@lights N" / "@advance MS"
    reply: bytes | None  # None: no reply expected


def _unescape(text: str) -> bytes:
    out = bytearray()
    i = 0
    while i < len(text):
        if text[i] != "\\":
            out += text[i].encode("ascii")
            i += 1
            continue
        code = text[i + 1]
        if code in "rnt\\":
            out += {"r": b"\r", "n": b"\n", "t": b"\t", "\\": b"\\"}[code]
            i += 2
        elif code == "x":
            out.append(int(text[i + 2 : i + 4], 16))
            i += 4
        else:
            raise ValueError(f"bad escape in {text!r}")
    return bytes(out)


def load_vectors(path: Path = VECTORS) -> list[Vector]:
    vectors = []
    for number, raw in enumerate(path.read_text(encoding="ascii").splitlines(), start=1):
        text = raw.strip(" \t")
        if not text or text.startswith("#"):
            continue
        left, arrow, right = text.partition("=>")
        right = right.strip(" \t")
        reply = None if not arrow or right == "(none)" else _unescape(right)
        vectors.append(Vector(number, _unescape(left.strip(" \t")), reply))
    return vectors


def run_python_simulator(vectors: list[Vector]) -> list[str]:
    """Return one message per failing vector."""
    failures = []
    firmware = clock = assembler = None
    for vector in vectors:
        if vector.command.startswith(b"@advance"):
            clock.advance_ms(int(vector.command.split()[1]))
            continue
        if vector.command.startswith(b"@lights"):
            clock = ManualClock()
            firmware = SimulatedFirmware(int(vector.command.split()[1]), clock=clock)
            assembler = LineAssembler()
            replies = [firmware.reboot().encode("latin-1")]
        else:
            replies = [
                reply.encode("latin-1")
                for line in assembler.feed(vector.command + b"\n")
                for reply in firmware.handle_line(line)
            ]
        expected = [] if vector.reply is None else [vector.reply]
        if replies != expected:
            failures.append(
                f"line {vector.line}: sent {vector.command!r}, expected {expected}, got {replies}"
            )
    return failures


def test_vectors_cover_every_command_and_error():
    vectors = load_vectors()
    commands = {v.command.split()[0].upper() for v in vectors if v.command.strip() and v.reply}
    assert {b"ID", b"ON", b"OFF", b"LEVEL", b"STATE", b"WATCHDOG", b"@LIGHTS"} <= commands
    replies = b"\n".join(v.reply for v in vectors if v.reply)
    for code in (1, 2, 3):
        assert f"ERR {code} ".encode() in replies
    assert any(v.command.startswith(b"@advance") for v in vectors)
    assert any(v.reply is None for v in vectors)
    assert len(vectors) > 60


def test_python_simulator_passes_the_vectors():
    failures = run_python_simulator(load_vectors())
    assert failures == []


def test_python_runner_catches_a_wrong_vector(tmp_path):
    # Guard against a runner that passes anything: one wrong expectation must fail.
    wrong = tmp_path / "vectors.txt"
    wrong.write_text(VECTORS.read_text().replace("ON 3 => OK ON 3", "ON 3 => OK ON 4", 1))
    failures = run_python_simulator(load_vectors(wrong))
    assert len(failures) == 1 and "OK ON 4" in failures[0]


@pytest.fixture(scope="module")
def host_runner(tmp_path_factory) -> Path:
    compiler = shutil.which("g++")
    if compiler is None:
        pytest.skip("g++ is not installed: cannot build the firmware core for the host")
    binary = tmp_path_factory.mktemp("firmware") / "host_test"
    build = subprocess.run(
        [
            compiler,
            "-std=c++11",
            "-Wall",
            "-Wextra",
            "-Werror",
            "-pedantic",
            f"-I{CORE}",
            str(CORE / "protocol_core.cpp"),
            str(FIRMWARE / "host" / "host_test.cpp"),
            "-o",
            str(binary),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert build.returncode == 0, build.stderr
    return binary


def test_cpp_core_passes_the_vectors(host_runner):
    result = subprocess.run([host_runner, VECTORS], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr
    passed = int(re.search(r"(\d+) vectors passed, 0 failed", result.stdout).group(1))
    assert passed == sum(1 for v in load_vectors() if not v.command.startswith(b"@advance"))


def test_cpp_runner_catches_a_wrong_vector(host_runner, tmp_path):
    wrong = tmp_path / "vectors.txt"
    wrong.write_text(VECTORS.read_text().replace("ON 3 => OK ON 3", "ON 3 => OK ON 4", 1))
    result = subprocess.run([host_runner, wrong], capture_output=True, text=True, timeout=60)
    assert result.returncode == 1
    assert "1 failed" in result.stdout and "OK ON 4" in result.stdout


def test_core_has_no_arduino_dependency():
    for name in ("protocol_core.h", "protocol_core.cpp"):
        source = (CORE / name).read_text()
        includes = re.findall(r'#include [<"]([^>"]+)[>"]', source)
        assert includes and set(includes) <= {"stddef.h", "stdint.h", "string.h", "protocol_core.h"}
