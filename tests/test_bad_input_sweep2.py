"""The second hostile sweep (issue 25): the newer commands and the filesystem, as a user runs them.

The promise is the README's "Failure behaviour", as in ``tests/test_bad_input.py`` (whose runner
and checks this reuses): exit code 2 (130 for a signal), exactly one line on stderr, starting
with ``error:``, naming the file or option, no traceback; nothing created or changed in the
case's folder, so an earlier result and every file the user owns stay as they were, and no
temporary folder is left (``TMPDIR`` points into the case's home, checked empty).

Groups: ``s1-`` integrate into folders that are not its own, ``s3-`` names that are not UTF-8,
``s4-`` links and read-only results, ``s5-`` normals, albedo and options integrate cannot use,
``s6-`` lines that were wrong (libpng, batch, serve-firmware, calibrate); the full-disk cases
(``s2``) mount a small tmpfs in a private mount namespace (``unshare``) and skip where that is
not allowed; the signal cases come last.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from helpers.hostile import (  # noqa: E402 - the sweeps' runner
    IS_ROOT,
    PS_LAB,
    Result,
    assert_one_error_line,
    assert_quiet,
    environment,
    finish as _finish,
    run as _run,
    snapshot,
    start,
    temporary_leftovers,
    wait_until,
)
from test_bad_input import SMALL_RIG, png_chunk  # noqa: E402 - the first sweep's rig


def run(args: list[str], cwd: Path, home: Path, timeout: float = 120) -> Result:
    """Every CLI run of the sweep: no numpy warning or traceback, whatever the exit code."""
    result = _run(args, cwd, home, timeout)
    assert_quiet(result)
    return result


def finish(proc, out: Path, err: Path, timeout: float = 120) -> Result:
    """:func:`helpers.hostile.finish`, and nothing noisy on the terminal (as :func:`run`)."""
    result = _finish(proc, out, err, timeout)
    assert_quiet(result)
    return result


NOT_UTF8 = os.fsdecode(b"caf\xe9")  # Latin-1 "café": not UTF-8


# --- templates --------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def made(tmp_path_factory) -> dict[str, Path]:
    """A 16x16 dataset, its result, and a small capture run (made once)."""
    root = tmp_path_factory.mktemp("sweep2")
    home = tmp_path_factory.mktemp("sweep2-home")
    ds = root / "png"
    assert run(["simulate", str(ds), "--size", "16", "--lights", "8"], root, home).code == 0
    result = root / "result"
    done = run(["reconstruct", str(ds), "--method", "ls", "--out", str(result)], root, home)
    assert done.code == 0, done.stderr
    rig = root / "rig.toml"
    rig.write_text(SMALL_RIG)
    captured = run(["capture", "--rig", str(rig), "--out", str(root / "run"), "-q"], root, home)
    assert captured.code == 0, captured.stderr
    near = root / "near.toml"
    near.write_text(NEAR_RIG_ONE_SPHERE_MISSING)
    captured = run(["capture", "--rig", str(near), "--out", str(root / "near"), "-q"], root, home)
    assert captured.code == 0, captured.stderr
    return {"png": ds, "result": result, "run": root / "run", "near": root / "near"}


# A near rig whose file lists two chrome spheres, the second of which is not on the table.
NEAR_RIG_ONE_SPHERE_MISSING = """
name = "near-small"
[controller]
driver = "simulated"
lights = 6
watchdog_ms = 5000
timeout_s = 0.3
anisotropy = 1.0
[camera]
driver = "simulated"
exposure_s = 0.05
timeout_s = 2.0
retries = 1
seed = 2015
[[calibration.chrome_spheres]]
center = [30.0, 30.0]
radius = 26.0
[[calibration.chrome_spheres]]
center = [130.0, 90.0]
radius = 26.0
[scene]
width = 160
height = 120
[scene.lights]
seed = 11
max_zenith_deg = 50.0
dome_radius = 300.0
[[scene.objects]]
kind = "chrome"
center = [30.0, 30.0]
radius = 26.0
albedo = [0.9, 0.9, 0.9]
[[scene.objects]]
kind = "relief"
center = [80.0, 70.0]
radius = 30.0
albedo = [0.75, 0.65, 0.55]
seed = 3
"""


@dataclass
class W:
    """One case's folder (``root``, snapshotted) and home (cache, TMPDIR)."""

    root: Path
    home: Path
    made: dict[str, Path]
    notes: dict = field(default_factory=dict)

    def copy(self, name: str, as_name: str | None = None) -> Path:
        target = self.root / (as_name or name)
        shutil.copytree(self.made[name], target, symlinks=True)
        return target


@dataclass
class Case:
    id: str
    build: Callable[[W], list[str]]
    names: Callable[[W], tuple[str, ...]]
    code: int = 2
    check: Callable[[W, Result], None] | None = None
    root_ok: bool = True
    timeout: float = 120


CASES: list[Case] = []


def case(id, names, *, code=2, check=None, root_ok=True, timeout=120):
    def register(build):
        CASES.append(
            Case(id, build, names if callable(names) else (lambda w, n=names: tuple(n)), code,
                 check, root_ok, timeout)
        )
        return build

    return register


# s1: integrate writes only into its own folders -------------------------------------------------


@case("s1-integrate-into-a-user-folder", lambda w: (str(w.root / "mine"),))
def _(w):
    mine = w.root / "mine"
    mine.mkdir()
    (mine / "depth.png").write_bytes(b"the user's own picture")
    return ["integrate", str(w.copy("result")), "--out", str(mine)]


@case("s1-integrate-metrics-not-json", lambda w: (str(w.root / "other" / "metrics.json"),))
def _(w):
    other = w.copy("result", "other")
    (other / "metrics.json").write_text("{ not json")
    return ["integrate", str(w.copy("result")), "--out", str(other)]


@case("s1-integrate-result-metrics-not-json", lambda w: (str(w.root / "result"),))
def _(w):
    result = w.copy("result")
    (result / "metrics.json").write_text("[1, 2")
    return ["integrate", str(result)]


@case("s1-integrate-out-is-a-file", lambda w: (str(w.root / "taken"),))
def _(w):
    (w.root / "taken").write_text("mine")
    return ["integrate", str(w.copy("result")), "--out", str(w.root / "taken")]


# s3: names that are not UTF-8 work (no crash in OpenCV or OpenEXR) ------------------------------


def _worked(w: W, result: Result) -> None:
    assert result.code == 0, result.stderr
    assert "Traceback" not in result.stderr
    assert not [p for p in w.root.rglob(".*") if ".partial-" in p.name], "staging left behind"


@case("s3-reconstruct-out-not-utf8", (), code=0, check=_worked)
def _(w):
    return ["reconstruct", str(w.copy("png")), "--out", str(w.root / NOT_UTF8), "--depth",
            "poisson"]


@case("s3-dataset-not-utf8", (), code=0, check=_worked)
def _(w):
    return ["reconstruct", str(w.copy("png", NOT_UTF8)), "--out", str(w.root / "out")]


@case("s3-simulate-not-utf8", (), code=0, check=_worked)
def _(w):
    return ["simulate", str(w.root / NOT_UTF8), "--size", "16", "--lights", "8"]


@case("s3-calibrate-run-not-utf8", (), code=0, check=_worked)
def _(w):
    return ["calibrate", str(w.copy("run", NOT_UTF8))]


@case("s3-integrate-out-not-utf8", (), code=0, check=_worked)
def _(w):
    return ["integrate", str(w.copy("result")), "--out", str(w.root / NOT_UTF8)]


@case("s3-batch-not-utf8", (), code=0, check=_worked)
def _(w):
    return ["batch", str(w.copy("png", NOT_UTF8)), "--out-root", str(w.root / NOT_UTF8 / "x"),
            "--workers", "1"]


# s4: links and read-only results ----------------------------------------------------------------


def _link_followed(w: W, result: Result) -> None:
    assert result.code == 0, result.stderr
    link, target = w.root / "link", w.root / "earlier"
    assert link.is_symlink() and os.readlink(link) == "earlier"
    assert json.loads((target / "metrics.json").read_text())["method"] == "l1"
    hidden = sorted(p.name for p in w.root.iterdir() if p.name.startswith("."))
    assert not hidden, hidden


@case("s4-out-is-a-link-to-an-earlier-result", (), code=0, check=_link_followed)
def _(w):
    w.copy("result", "earlier")
    (w.root / "link").symlink_to("earlier")
    return ["reconstruct", str(w.copy("png")), "--method", "l1", "--out", str(w.root / "link")]


@case("s4-out-is-a-dangling-link", lambda w: (str(w.root / "link"),))
def _(w):
    (w.root / "link").symlink_to("nowhere")
    return ["reconstruct", str(w.copy("png")), "--out", str(w.root / "link")]


@case("s4-earlier-result-read-only", lambda w: (str(w.root / "locked"),), root_ok=False)
def _(w):
    locked = w.copy("result", "locked")
    locked.chmod(0o555)
    return ["reconstruct", str(w.copy("png")), "--out", str(locked)]


# s5: what integrate cannot use, in one line naming it -------------------------------------------


def _result_with(w: W, normals=None, albedo=None) -> Path:
    result = w.copy("result")
    if normals is not None:
        np.save(result / "normals.npy", normals(np.load(result / "normals.npy")))
    if albedo is not None:
        np.save(result / "albedo.npy", albedo(np.load(result / "albedo.npy")), allow_pickle=True)
    return result


def _pixels(pattern: str) -> Callable[[np.ndarray], np.ndarray]:
    def make(normals: np.ndarray) -> np.ndarray:
        out = np.zeros_like(normals)
        rows, cols = np.indices(normals.shape[:2])
        chosen = {
            "one": (rows == 5) & (cols == 5),
            "diagonal": ((rows == 5) & (cols == 5)) | ((rows == 6) & (cols == 6)),
            "checkerboard": (rows + cols) % 2 == 0,
        }[pattern]
        out[chosen] = (0.0, 0.0, 1.0)
        return out

    return make


def _normals_case(id: str, normals, names=("normals.npy",), extra=()):
    @case(id, lambda w: tuple(str(w.root / "result" / n) for n in names))
    def _(w):
        return ["integrate", str(_result_with(w, normals=normals)), *extra]


_normals_case("s5-normals-complex", lambda n: n.astype(np.complex128))
_normals_case("s5-normals-strings", lambda n: n.astype(str))
_normals_case("s5-mask-one-pixel", _pixels("one"))
_normals_case("s5-mask-two-diagonal-pixels", _pixels("diagonal"))
_normals_case("s5-mask-checkerboard", _pixels("checkerboard"))
_normals_case("s5-normals-all-nan", lambda n: np.full_like(n, np.nan))
_normals_case("s5-normals-all-zero", np.zeros_like)
_normals_case("s5-normals-back-facing", lambda n: np.broadcast_to([0, 0, -1.0], n.shape).copy())


@case("s5-albedo-other-size", lambda w: (str(w.root / "result" / "albedo.npy"),))
def _(w):
    return ["integrate", str(_result_with(w, albedo=lambda a: a[:5, :7]))]


@case("s5-albedo-pickled", lambda w: (str(w.root / "result" / "albedo.npy"),),
      check=lambda w, r: _not_in(r.lines[0], "normals.npy"))
def _(w):
    return ["integrate", str(_result_with(w, albedo=lambda a: np.array([{"a": 1}] * 4)))]


def _not_in(line: str, word: str) -> None:
    assert word not in line, line


for _option, _value in (
    ("--focal-length", "1e300"),
    ("--focal-length", "1e-6"),
    ("--pixel-size", "1e300"),
):

    @case(f"s5-integrate{_option}-{_value}", (_option,))
    def _(w, option=_option, value=_value):
        return ["integrate", str(w.copy("result")), option, value, "--out", str(w.root / "new")]


@case("s5-reconstruct-depth-two-diagonal-pixels", ("--depth",))
def _(w):
    ds = w.copy("png")
    mask = np.zeros((16, 16), np.uint8)
    mask[7, 7] = mask[8, 8] = 255
    cv2.imwrite(str(ds / "mask.png"), mask)
    return ["reconstruct", str(ds), "--method", "ls", "--depth", "poisson"]


# s6: lines that were wrong or not one -----------------------------------------------------------


def _cut_idat(path: Path) -> None:
    """Halve the compressed stream of a PNG, keeping every chunk's CRC valid and IEND."""
    raw = path.read_bytes()
    out, at = raw[:8], 8
    while at < len(raw):
        (length,) = struct.unpack(">I", raw[at : at + 4])
        kind, data = raw[at + 4 : at + 8], raw[at + 8 : at + 8 + length]
        out += png_chunk(kind, data[: len(data) // 2] if kind == b"IDAT" else data)
        at += 12 + length
    path.write_bytes(out)


@case("s6-png16-stream-cut-short", ("003.png",),
      check=lambda w, r: _not_in(r.stderr, "libpng error"))
def _(w):
    ds = w.copy("png")
    _cut_idat(ds / "003.png")
    return ["reconstruct", str(ds)]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _quick(seconds: float) -> Callable[[W, Result], None]:
    def check(w: W, result: Result) -> None:
        assert w.notes["seconds"] < seconds, f"took {w.notes['seconds']:.1f} s"

    return check


@case("s6-batch-scheduler-port-not-a-number", ("--scheduler",), check=_quick(15), timeout=60)
def _(w):
    return ["batch", str(w.copy("png")), "--out-root", str(w.root / "results"),
            "--scheduler", "tcp://127.0.0.1:notaport"]


@case("s6-batch-scheduler-unreachable", ("--scheduler",), check=_quick(15), timeout=60)
def _(w):
    return ["batch", str(w.copy("png")), "--out-root", str(w.root / "results"),
            "--scheduler", f"tcp://127.0.0.1:{_free_port()}"]


@case("s6-batch-out-root-is-a-file", lambda w: ("--out-root",),
      check=lambda w, r: _has(r.lines[0], str(w.root / "taken")))
def _(w):
    (w.root / "taken").write_text("mine")
    return ["batch", str(w.copy("png")), "--out-root", str(w.root / "taken"), "--workers", "1"]


def _has(line: str, word: str) -> None:
    assert word in line, line


def _failed_dataset_named(w: W, result: Result) -> None:
    _has(result.lines[0], str(w.root / "broken" / "003.png"))
    results = w.root / "results"
    assert sorted(p.name for p in results.iterdir()) == ["png"]  # nothing of "broken"
    assert (results / "png" / "metrics.json").is_file()
    shutil.rmtree(results)  # the good dataset's result is expected: not part of the snapshot


@case("s6-batch-names-the-failing-dataset", ("broken",), check=_failed_dataset_named)
def _(w):
    broken = w.copy("png", "broken")
    (broken / "003.png").write_bytes(b"not a png")
    return ["batch", str(w.copy("png")), str(broken), "--out-root", str(w.root / "results"),
            "--workers", "1"]


def _elf32(machine: int, *, cut: int | None = None) -> bytes:
    """A minimal 32-bit little-endian ELF executable for ``machine`` (one loadable segment)."""
    code = bytes(64)
    header = b"\x7fELF" + bytes([1, 1, 1]) + bytes(9)
    header += struct.pack("<HHIIIIIHHHHHH", 2, machine, 1, 0, 52, 0, 0, 52, 32, 1, 40, 0, 0)
    segment = struct.pack("<IIIIIIII", 1, 84, 0, 0, len(code), len(code), 5, 2)
    data = header + segment + code
    return data if cut is None else data[:cut]


for _label, _content in (
    ("empty", b""),
    ("not-elf", b"#!/bin/sh\necho firmware\n"),
    ("header-cut", _elf32(83, cut=40)),
    ("program-cut", _elf32(83, cut=100)),
    ("arm", _elf32(40)),
    ("x86-64", b"\x7fELF\x02\x01\x01" + bytes(57)),
):

    @case(f"s6-serve-firmware-elf-{_label}", lambda w: (str(w.root / "sketch.elf"),),
          check=lambda w, r: _no_temporary(w), timeout=60)
    def _(w, content=_content):
        (w.root / "sketch.elf").write_bytes(content)
        return ["rig", "serve-firmware", "--elf", str(w.root / "sketch.elf")]


def _no_temporary(w: W) -> None:
    assert not temporary_leftovers(w.home), temporary_leftovers(w.home)


@case("s6-calibrate-near-rig-second-sphere-absent", ("manifest.json",),
      check=lambda w, r: _has(r.lines[0], "sphere 2"))
def _(w):
    return ["calibrate", str(w.copy("near"))]


@case("s6-calibrate-sphere-on-bare-table", ("--sphere",),
      check=lambda w, r: _not_in(r.lines[0], "light 2"))
def _(w):
    return ["calibrate", str(w.copy("run")), "--sphere", "20,100,15"]


#: Cases ``make test`` runs; ``pytest -m slow`` runs the rest.
CI_CASES = {
    "s1-integrate-into-a-user-folder",
    "s1-integrate-metrics-not-json",
    "s3-reconstruct-out-not-utf8",
    "s3-calibrate-run-not-utf8",
    "s4-out-is-a-link-to-an-earlier-result",
    "s4-earlier-result-read-only",
    "s5-normals-complex",
    "s5-mask-checkerboard",
    "s5-normals-back-facing",
    "s5-albedo-pickled",
    "s5-integrate--focal-length-1e300",
    "s5-integrate--pixel-size-1e300",
    "s5-reconstruct-depth-two-diagonal-pixels",
    "s6-png16-stream-cut-short",
    "s6-batch-scheduler-port-not-a-number",
    "s6-batch-scheduler-unreachable",
    "s6-batch-out-root-is-a-file",
    "s6-serve-firmware-elf-empty",
    "s6-serve-firmware-elf-arm",
    "s6-calibrate-near-rig-second-sphere-absent",
    "s6-calibrate-sphere-on-bare-table",
}


def _params() -> list:
    unknown = CI_CASES - {c.id for c in CASES}
    assert not unknown, unknown
    return [pytest.param(c, id=c.id, marks=() if c.id in CI_CASES else pytest.mark.slow)
            for c in CASES]


@dataclass
class Outcome:
    w: W
    result: Result | None = None
    before: dict | None = None
    after: dict | None = None
    error: BaseException | None = None


def _run_case(c: Case, w: W) -> Outcome:
    outcome = Outcome(w)
    try:
        args = c.build(w)
        outcome.before = snapshot(w.root)
        started = time.monotonic()
        outcome.result = run(args, w.root, w.home, timeout=c.timeout)
        w.notes["seconds"] = time.monotonic() - started
        outcome.after = snapshot(w.root)
    except Exception as exc:  # noqa: BLE001 - reported by the case's own test
        outcome.error = exc
    return outcome


@pytest.fixture(scope="session")
def table(request, made, tmp_path_factory) -> dict[str, Outcome]:
    """Run the selected cases, two at a time (each is a separate ``ps-lab`` process)."""
    chosen = [
        item.callspec.params["c"]
        for item in request.session.items
        if getattr(item, "originalname", "") == "test_sweep2"
        and not item.get_closest_marker("skip")
    ]
    chosen = [c for c in chosen if c.root_ok or not IS_ROOT]
    spaces = []
    for c in chosen:
        folder = tmp_path_factory.mktemp(c.id)
        (folder / "home").mkdir()
        (folder / "case").mkdir()
        spaces.append(W(folder / "case", folder / "home", made))
    with ThreadPoolExecutor(max_workers=2) as pool:
        outcomes = list(pool.map(_run_case, chosen, spaces))
    return {c.id: o for c, o in zip(chosen, outcomes, strict=True)}


@pytest.mark.parametrize("c", _params())
def test_sweep2(c: Case, table: dict[str, Outcome]) -> None:
    if IS_ROOT and not c.root_ok:
        pytest.skip("file permissions do not bind root")
    outcome = table[c.id]
    if outcome.error is not None:
        raise outcome.error
    assert outcome.result is not None
    if c.code == 0:
        assert c.check is not None
        c.check(outcome.w, outcome.result)
        return
    assert_one_error_line(outcome.result, c.names(outcome.w), c.code)
    if c.check is not None:
        c.check(outcome.w, outcome.result)
    assert snapshot(outcome.w.root) == outcome.before, "files created or changed"
    assert not temporary_leftovers(outcome.w.home), "temporary files left behind"


# --- a full disk: a 256 KiB tmpfs in a private mount namespace -----------------------------------


def _tmpfs_prefix(mountpoint: Path) -> tuple[str, ...] | None:
    """``unshare`` arguments that run a command with a 256 KiB tmpfs on ``mountpoint``."""
    unshare = shutil.which("unshare")
    if unshare is None:
        return None
    mountpoint.mkdir(exist_ok=True)
    script = 'mount -t tmpfs -o size=256k tmpfs "$0" && exec "$@"'
    probe = subprocess.run(
        [unshare, "-rm", "sh", "-c", script, str(mountpoint), "true"], capture_output=True,
        check=False,
    )
    if probe.returncode != 0:
        return None
    return (unshare, "-rm", "sh", "-c", script, str(mountpoint))


DISK_FILLERS = {
    # A 128 x 128 result (normals.npy alone is 192 KiB) after a 16 x 16 one that fits.
    "reconstruct": lambda w, full: ["reconstruct", str(w.root / "big"), "--out", str(full / "r")],
    "calibrate": lambda w, full: ["calibrate", str(w.root / "run"), "--out", str(full / "cal")],
    "integrate": lambda w, full: ["integrate", str(w.root / "bigresult"), "--out",
                                  str(full / "depth")],
}


@pytest.fixture(scope="session")
def big(made, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("big")
    home = tmp_path_factory.mktemp("big-home")
    assert run(["simulate", str(root / "big"), "--size", "128", "--lights", "8"], root,
               home).code == 0
    done = run(["reconstruct", str(root / "big"), "--method", "ls", "--out",
                str(root / "bigresult")], root, home)
    assert done.code == 0, done.stderr
    return {"big": root / "big", "bigresult": root / "bigresult"}


@pytest.mark.parametrize(
    "command",
    ["reconstruct", pytest.param("calibrate", marks=pytest.mark.slow),
     pytest.param("integrate", marks=pytest.mark.slow)],
)
def test_full_disk_is_one_line_and_leaves_nothing(command, made, big, tmp_path) -> None:
    w = W(tmp_path / "case", tmp_path / "home", {**made, **big})
    w.root.mkdir()
    w.home.mkdir()
    full = w.root / "full"
    prefix = _tmpfs_prefix(full)
    if prefix is None:
        pytest.skip("cannot mount a tmpfs here (unshare -rm not allowed): full disk not tested")
    for name in ("png", "run", "big", "bigresult"):
        w.copy(name)
    # One command in the namespace: an earlier result that fits, a file filling all but 8 KiB,
    # the command that does not fit, and the listing of what is left (the tmpfs goes with the
    # namespace).
    listing = w.home / "listing.json"
    fill = DISK_FILLERS[command](w, full)
    script = (
        f"import json, os, subprocess, sys\n"
        f"full = {str(full)!r}\n"
        f"first = subprocess.run([{PS_LAB!r}, 'reconstruct', {str(w.root / 'png')!r}, '--out',"
        f" os.path.join(full, 'r')], capture_output=True)\n"
        f"assert first.returncode == 0, first.stderr\n"
        f"space = os.statvfs(full)\n"
        f"with open(os.path.join(full, 'filler'), 'wb') as filler:\n"
        f"    filler.write(bytes(max(0, space.f_bavail * space.f_frsize - 8192)))\n"
        f"def tree():\n"
        f"    return sorted((os.path.relpath(os.path.join(d, n), full), os.path.getsize("
        f"os.path.join(d, n))) for d, ds, fs in os.walk(full) for n in ds + fs)\n"
        f"before = tree()\n"
        f"second = subprocess.run([{PS_LAB!r}, *{fill!r}], capture_output=True)\n"
        f"json.dump({{'before': before, 'after': tree(), 'code': second.returncode,"
        f" 'stderr': second.stderr.decode('utf-8', 'replace')}}, open({str(listing)!r}, 'w'))\n"
    )
    finished = subprocess.run(
        [*prefix, sys.executable, "-c", script], env=environment(w.home), capture_output=True,
        timeout=240, check=False,
    )
    assert finished.returncode == 0, finished.stderr.decode(errors="replace")
    record = json.loads(listing.read_text())
    result = Result(record["code"], "", record["stderr"], 0)
    line = assert_one_error_line(result, (str(full),))
    assert "space" in line, line
    assert record["after"] == record["before"], "the earlier result changed or staging was left"
    assert not temporary_leftovers(w.home)


# --- signals ------------------------------------------------------------------------------------


def _sphere_result(folder: Path, size: int) -> None:
    """A result folder of a hemisphere's normals, size x size (slow enough to interrupt)."""
    folder.mkdir()
    rows, cols = np.indices((size, size))
    x = (cols - size / 2) / (0.45 * size)
    y = (size / 2 - rows) / (0.45 * size)
    inside = x * x + y * y < 1
    normals = np.zeros((size, size, 3), np.float32)
    normals[inside, 0], normals[inside, 1] = x[inside], y[inside]
    normals[inside, 2] = np.sqrt(1 - x[inside] ** 2 - y[inside] ** 2)
    np.save(folder / "normals.npy", normals)
    (folder / "metrics.json").write_text(json.dumps({"format": "ps-lab-reconstruction"}))


def test_ctrl_c_during_integrate_leaves_no_new_folder(tmp_path) -> None:
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        pytest.skip("SIGINT is ignored in this (background) session and so in the command")
    home, root = tmp_path / "home", tmp_path / "case"
    home.mkdir()
    root.mkdir()
    _sphere_result(root / "result", 1200)
    new = root / "new"
    before = snapshot(root)
    proc, out, err = start(["integrate", str(root / "result"), "--method", "bilateral", "--out",
                            str(new)], root, home)
    wait_until(lambda: new.is_dir() and any(new.iterdir()), proc)
    time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    result = finish(proc, out, err, timeout=60)
    assert_one_error_line(result, ("interrupted",), code=130)
    assert not new.exists(), "an empty output folder was left"
    assert snapshot(root) == before


def test_sigterm_during_batch_counts_the_finished_datasets(made, tmp_path) -> None:
    home, root = tmp_path / "home", tmp_path / "case"
    home.mkdir()
    root.mkdir()
    datasets = []
    for k in range(4):
        shutil.copytree(made["png"], root / f"ds{k}")
        datasets.append(str(root / f"ds{k}"))
    results = root / "results"
    proc, out, err = start(["batch", *datasets, "--out-root", str(results), "--workers", "1",
                            "--method", "sbl", "--refine-lights", "30"], root, home)
    wait_until(lambda: (results / "ds0" / "metrics.json").exists(), proc, timeout=120)
    proc.send_signal(signal.SIGTERM)
    result = finish(proc, out, err, timeout=120)
    line = assert_one_error_line(result, ("interrupted",), code=130)
    finished = [p.name for p in results.iterdir() if (p / "metrics.json").is_file()]
    assert f"{len(finished)} of 4 datasets finished" in line, (line, finished)
    hidden = [p.name for p in results.iterdir() if p.name.startswith(".")]
    assert not hidden, hidden  # the stopped worker's staging removed by the cluster's shutdown


def test_serve_firmware_refused_by_simavr_leaves_no_temporary_folder(tmp_path) -> None:
    """An AVR ELF simavr cannot load: one line naming it, and the state folder is gone."""
    from ps_lab.capture.simulated.avr_firmware import missing_packages

    missing = missing_packages(sketch=False)
    if missing:
        pytest.skip(f"simavr harness not buildable here: {' '.join(missing)} missing")
    home, root = tmp_path / "home", tmp_path / "case"
    home.mkdir()
    root.mkdir()
    elf = root / "blank.elf"
    elf.write_bytes(_elf32(83))  # a sound header, and nothing simavr can load
    result = run(["rig", "serve-firmware", "--elf", str(elf), "--pins", "3,5,6"], root, home)
    assert_one_error_line(result, (str(elf),))
    assert not temporary_leftovers(home), temporary_leftovers(home)


def test_a_service_that_is_not_a_scheduler_is_one_line_within_seconds(made, tmp_path) -> None:
    """A TCP port that accepts but never speaks Dask (Dask's client alone would wait forever)."""
    home, root = tmp_path / "home", tmp_path / "case"
    home.mkdir()
    root.mkdir()
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(4)  # the kernel accepts; nobody ever sends a byte
        address = f"tcp://127.0.0.1:{silent.getsockname()[1]}"
        started = time.monotonic()
        result = run(["batch", str(made["png"]), "--out-root", str(root / "results"),
                      "--scheduler", address], root, home, timeout=90)
        seconds = time.monotonic() - started
    line = assert_one_error_line(result, ("--scheduler",))
    assert "not a Dask scheduler" in line, line
    assert seconds < 20, f"took {seconds:.1f} s"
    assert not any(root.iterdir()) and not temporary_leftovers(home)
