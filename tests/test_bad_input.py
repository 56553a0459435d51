"""Malformed inputs and signals, through the ``ps-lab`` command as a user runs it.

Every case runs a real subprocess of the ``ps-lab`` entry point next to the running interpreter
(or ``$PS_LAB_EXE``) and asserts the README's promise: exit code 2 (130 for a signal), exactly one
line on stderr, starting with ``error:``, that names the offending file or option, no traceback,
and no file created or changed in the case's folder (dataset and output; names, sizes, mtimes).

The table has one group per kind of failure (ids ``g1-`` ... ``g7-`` follow issue 13, ``x-`` are
inputs it did not list). CI runs a subset of every group (:data:`CI_CASES`), ``pytest -m slow``
the rest, and ``pytest -m "slow or not device"`` all of it. The datasets are tiny (16x16, 8
lights) and made once per session; the table's commands run a few at a time.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import struct
import subprocess
import sys
import time
import zlib
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from helpers.hostile import (  # noqa: E402 - the sweeps' runner
    IS_ROOT,
    PS_LAB,
    Result,
    _alive,
    assert_one_error_line,
    assert_quiet,
    environment,
    finish as _finish,
    run as _run,
    snapshot,
    start,
    wait_until,
)


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


MiB = 1 << 20


# --- making datasets ---------------------------------------------------------------------------


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def forge_png_size(path: Path, width: int, height: int) -> None:
    """Rewrite the IHDR of a PNG to claim ``width`` x ``height`` (valid CRC, same pixel data)."""
    raw = path.read_bytes()
    ihdr = bytearray(raw[16:29])
    ihdr[0:8] = struct.pack(">II", width, height)
    path.write_bytes(raw[:8] + png_chunk(b"IHDR", bytes(ihdr)) + raw[33:])


def write_png16(path: Path, image: np.ndarray) -> None:
    assert cv2.imwrite(str(path), np.asarray(image, dtype=np.uint16))


def write_lines(path: Path, rows) -> None:
    path.write_text("".join(" ".join(str(v) for v in row) + "\n" for row in rows))


def read_rows(path: Path) -> np.ndarray:
    return np.loadtxt(path, ndmin=2)


def image_files(ds: Path) -> list[Path]:
    return [ds / name for name in (ds / "filenames.txt").read_text().split()]


@dataclass
class Case:
    """One malformed input: ``build(w)`` prepares w.root and returns the arguments."""

    id: str
    build: Callable[[Workspace], list[str]]
    names: Callable[[Workspace], tuple[str, ...]]
    code: int = 2
    check: Callable[[Workspace, Result, str], None] | None = None
    root_ok: bool = True  # False: needs a non-root user (file permissions)
    timeout: float = 120
    keeps_run: bool = False  # capture: complete frames stay in --out for --resume


@dataclass
class Workspace:
    root: Path
    home: Path
    templates: dict[str, Path]
    notes: dict = field(default_factory=dict)

    def copy(self, template: str, name: str | None = None) -> Path:
        target = self.root / (name or template)
        shutil.copytree(self.templates[template], target, symlinks=True)
        return target

    @property
    def ds(self) -> Path:
        return self.root / "png"

    def png(self) -> Path:
        return self.copy("png")


# --- templates (one session: small and fast) ----------------------------------------------------

SMALL_RIG = """
name = "small"
[controller]
driver = "simulated"
lights = 6
watchdog_ms = 5000
timeout_s = 0.3
[camera]
driver = "simulated"
exposure_s = 0.05
timeout_s = 2.0
retries = 1
seed = 2012
[calibration.chrome_sphere]
center = [40.0, 40.0]
radius = 32.0
[scene]
width = 160
height = 120
[scene.lights]
seed = 7
max_zenith_deg = 50.0
[[scene.objects]]
kind = "chrome"
center = [40.0, 40.0]
radius = 32.0
albedo = [0.9, 0.9, 0.9]
[[scene.objects]]
kind = "relief"
center = [108.0, 62.0]
radius = 50.0
albedo = [0.75, 0.65, 0.55]
seed = 3
"""


@pytest.fixture(scope="session")
def templates(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("templates")
    home = tmp_path_factory.mktemp("home")
    made: dict[str, Path] = {}
    for name, fmt in (("png", "png16"), ("npy", "npy"), ("tiff", "tiff32")):
        result = run(
            ["simulate", str(root / name), "--size", "16", "--lights", "8", "--format", fmt],
            root,
            home,
        )
        assert result.code == 0, result.stderr
        made[name] = root / name
    rig = root / "rig" / "small.toml"
    rig.parent.mkdir()
    rig.write_text(SMALL_RIG)
    made["rig"] = rig.parent
    result = run(["capture", "--rig", str(rig), "--out", str(root / "run"), "-q"], root, home)
    assert result.code == 0, result.stderr
    made["run"] = root / "run"
    return made


@pytest.fixture
def workspace(tmp_path, templates) -> Workspace:
    home = tmp_path / "home"
    home.mkdir()
    root = tmp_path / "case"
    root.mkdir()
    return Workspace(root, home, templates)


# --- the table ---------------------------------------------------------------------------------

CASES: list[Case] = []


def case(
    id: str, names, *, code: int = 2, check=None, root_ok: bool = True, timeout=120, keeps_run=False
):
    def register(build):
        CASES.append(
            Case(
                id,
                build,
                names if callable(names) else (lambda w, n=names: tuple(n)),
                code,
                check,
                root_ok,
                timeout,
                keeps_run,
            )
        )
        return build

    return register


def ds_name(w: Workspace) -> tuple[str, ...]:
    return (str(w.ds),)


def fill_images(ds: Path, value_of: Callable[[np.ndarray], np.ndarray]) -> None:
    for file in image_files(ds):
        if file.suffix == ".png":
            image = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
            write_png16(file, value_of(image))
        elif file.suffix == ".npy":
            np.save(file, value_of(np.load(file)))
        else:
            tifffile.imwrite(file, value_of(tifffile.imread(file)))


# Group 1: bad input accepted silently -----------------------------------------------------------


@case("g1-all-zero-png", ds_name)
def _(w):
    fill_images(w.png(), np.zeros_like)
    return ["reconstruct", str(w.ds)]


@case("g1-nan-npy", lambda w: (str(w.root / "npy"),))
def _(w):
    fill_images(w.copy("npy"), lambda a: np.full_like(a, np.nan))
    return ["reconstruct", str(w.root / "npy")]


@case("g1-nan-float-tiff", lambda w: (str(w.root / "tiff"),))
def _(w):
    fill_images(w.copy("tiff"), lambda a: np.full_like(a, np.nan))
    return ["reconstruct", str(w.root / "tiff")]


@case("g1-shadow-threshold-nan", ("--shadow-threshold",))
def _(w):
    return ["reconstruct", str(w.png()), "--shadow-threshold", "nan"]


@case("g1-shadow-threshold-inf", ("--shadow-threshold",))
def _(w):
    return ["reconstruct", str(w.png()), "--shadow-threshold", "inf"]


@case("g1-shadow-threshold-above-every-value", lambda w: (str(w.ds), "--shadow-threshold"))
def _(w):
    return ["reconstruct", str(w.png()), "--shadow-threshold", "50"]


@case("g1-all-saturated", ds_name)
def _(w):
    fill_images(w.png(), lambda a: np.full_like(a, 65535))
    return ["reconstruct", str(w.ds), "--method", "ls"]


@case("g1-mask-on-black-background", lambda w: (str(w.ds), "mask.png"))
def _(w):
    ds = w.png()
    mask = np.zeros((16, 16), np.uint8)
    mask[0, 0] = 255  # a corner of the background: every image is black there
    cv2.imwrite(str(ds / "mask.png"), mask)
    return ["reconstruct", str(ds)]


# Group 2: numbers that reach the maths unchecked ----------------------------------------------


def calibrate_case(id: str, option: str, value: str, extra: tuple[str, ...] = ()):
    @case(id, (option,))
    def _(w):
        return ["calibrate", str(w.copy("run")), option, value, *extra]


calibrate_case("g2-sphere-negative-radius", "--sphere", "100,100,-5")
calibrate_case("g2-sphere-zero-radius", "--sphere", "40,40,0")
calibrate_case("g2-sphere-nan", "--sphere", "nan,40,30")
calibrate_case("g2-sphere-inf-radius", "--sphere", "40,40,inf")
calibrate_case("g2-sphere-outside-image", "--sphere", "1e9,1e9,30")
calibrate_case("g2-sphere-two-numbers", "--sphere", "40,40")
calibrate_case("g2-roi-negative-width", "--roi", "0,0,-10,50")
calibrate_case("g2-roi-zero", "--roi", "0,0,0,0")
calibrate_case("g2-roi-nan", "--roi", "nan,0,50,50")
calibrate_case("g2-roi-outside-image", "--roi", "5000,5000,50,50")
calibrate_case("g2-matte-negative-radius", "--matte", "40,90,-3")
calibrate_case("g2-focal-length-zero", "--focal-length", "0", ("--pixel-pitch", "4"))
calibrate_case("g2-pixel-pitch-zero", "--pixel-pitch", "0", ("--focal-length", "50"))
calibrate_case("g2-focal-length-negative", "--focal-length", "-50", ("--pixel-pitch", "4"))
calibrate_case("g2-focal-length-nan", "--focal-length", "nan", ("--pixel-pitch", "4"))
calibrate_case("g2-safe-radius-nan", "--safe-radius", "nan")


def option_case(id: str, command: list[str], option: str, value: str, where: str = "png"):
    @case(id, (option,))
    def _(w):
        target = [str(w.copy(where))] if where else []
        return [*command, *target, option, value]


for _value, _label in (
    ("0", "zero"),
    ("-1GB", "negative"),
    ("nan", "nan"),
    ("inf", "inf"),
    ("lots", "word"),
    ("0.0000001", "rounds-to-zero"),
):
    option_case(f"g2-memory-budget-{_label}", ["reconstruct"], "--memory-budget", _value)


def capture_case(id: str, option: str, value: str):
    @case(id, (option,))
    def _(w):
        out = w.root / "out"
        return [
            "capture",
            "--rig",
            str(w.copy("rig") / "small.toml"),
            "--out",
            str(out),
            option,
            value,
            "-q",
        ]


capture_case("g2-exposure-negative", "--exposure", "-1")
capture_case("g2-exposure-zero", "--exposure", "0")
capture_case("g2-exposure-nan", "--exposure", "nan")
capture_case("g2-exposure-inf", "--exposure", "inf")
capture_case("g2-lights-zero", "--lights", "0")
capture_case("g2-lights-beyond-rig", "--lights", "1-99")
capture_case("g2-lights-backwards", "--lights", "5-2")
capture_case("g2-lights-word", "--lights", "all")
capture_case("g2-repeat-huge", "--repeat", "1000000000")

for _option, _value in (
    ("--max-zenith", "nan"),
    ("--max-zenith", "120"),
    ("--max-zenith", "-5"),
    ("--noise-sigma", "nan"),
    ("--roughness", "inf"),
    ("--specular", "nan"),
    ("--noise-fraction", "nan"),
    ("--size", "100000"),
):

    @case(f"g2-simulate{_option}-{_value}", (_option,))
    def _(w, option=_option, value=_value):
        return ["simulate", str(w.root / "new"), "--lights", "8", "--size", "16", option, value]


for _option, _value in (
    ("--timeout", "nan"),
    ("--dwell", "nan"),
    ("--dwell", "inf"),
    ("--timeout", "inf"),
):

    @case(f"g2-rig-check{_option}-{_value}", (_option,), timeout=30)
    def _(w, option=_option, value=_value):
        return ["rig", "check", "--port", "pslabsim://", "--lights", "24", option, value]


@case("g2-serve-sim-delay-nan", ("--delay",), timeout=30)
def _(w):
    return ["rig", "serve-sim", "--lights", "4", "--delay", "nan"]


@case("g2-bench-unknown-table", ("--tables",))
def _(w):
    return ["bench", "paper", "--quick", "--tables", "9"]


@case("g2-bench-size-huge", ("--size",))
def _(w):
    return ["bench", "paper", "--quick", "--size", "1000000"]


# Group 4: the right file named, early ----------------------------------------------------------


def light_table_case(id: str, rows_of: Callable[[np.ndarray], np.ndarray], also_corrupt=True):
    @case(
        id,
        lambda w: ("light_directions.txt",),
        check=lambda w, r, line: _not_named(line, "003.png"),
    )
    def _(w):
        ds = w.png()
        write_lines(ds / "light_directions.txt", rows_of(read_rows(ds / "light_directions.txt")))
        if also_corrupt:  # the lights must be refused before any frame is read
            (ds / "003.png").write_bytes(b"not a png")
        return ["reconstruct", str(ds)]


def _not_named(line: str, name: str) -> None:
    assert name not in line, line


def _coplanar(rows):
    rows = rows.copy()
    rows[:, 1] = 0.0  # every light in the x-z plane through the origin
    return rows


light_table_case("g4-lights-coplanar", _coplanar)
light_table_case("g4-lights-identical", lambda rows: np.repeat(rows[:1], len(rows), axis=0))
light_table_case("g4-lights-antiparallel", lambda rows: np.array([[0, 0, 1], [0, 0, -1]] * 4))


def _lp_instead_of_light_directions(ds: Path, rows: np.ndarray, names: list[str]) -> Path:
    """Replace light_directions.txt and filenames.txt by a RelightLab ``dirs.lp``."""
    (ds / "light_directions.txt").unlink()
    (ds / "filenames.txt").unlink()
    lp = ds / "dirs.lp"
    lines = [f"{n} {x} {y} {z}\n" for n, (x, y, z) in zip(names, rows, strict=True)]
    lp.write_text(f"{len(names)}\n" + "".join(lines))
    return lp


@case("x-lp-lists-more-images-than-the-folder", ("dirs.lp", "009.png", "010.png"))
def _(w):
    ds = w.png()
    rows = read_rows(ds / "light_directions.txt")
    names = [f.name for f in image_files(ds)] + ["009.png", "010.png"]
    _lp_instead_of_light_directions(ds, np.vstack([rows, rows[:2]]), names)
    return ["reconstruct", str(ds)]


@case("x-lp-coplanar", ("dirs.lp", "one plane"), check=lambda w, r, line: _not_named(line, "003"))
def _(w):
    ds = w.png()
    rows = _coplanar(read_rows(ds / "light_directions.txt"))
    _lp_instead_of_light_directions(ds, rows, [f.name for f in image_files(ds)])
    (ds / "003.png").write_bytes(b"not a png")  # refused before any frame is read
    return ["reconstruct", str(ds)]


@case("x-view-not-a-result", lambda w: (str(w.ds), "normals.npy"))
def _(w):
    return ["view", str(w.png()), "--no-browser"]


@case("g4-two-lights-two-images", ("light_directions.txt",))
def _(w):
    ds = w.png()
    write_lines(ds / "light_directions.txt", read_rows(ds / "light_directions.txt")[:2])
    write_lines(ds / "light_intensities.txt", read_rows(ds / "light_intensities.txt")[:2])
    (ds / "filenames.txt").write_text("001.png\n002.png\n")
    return ["reconstruct", str(ds)]


@case(
    "g4-first-image-wrong-size", ("001.png",), check=lambda w, r, line: _not_named(line, "mask.png")
)
def _(w):
    ds = w.png()
    write_png16(ds / "001.png", np.full((20, 20), 1000))
    return ["reconstruct", str(ds)]


@case(
    "g4-first-image-forged-header",
    ("001.png",),
    check=lambda w, r, line: _not_named(line, "mask.png"),
)
def _(w):
    ds = w.png()
    forge_png_size(ds / "001.png", 20, 16)
    return ["reconstruct", str(ds)]


@case("g4-no-chrome-sphere", ds_name)
def _(w):
    return ["calibrate", str(w.png())]


@case(
    "g4-dark-frame-wrong-size", ("dark.png",), check=lambda w, r, line: _not_named(line, "001.png")
)
def _(w):
    ds = w.png()
    write_png16(ds / "dark.png", np.zeros((12, 12)))
    return ["reconstruct", str(ds)]


@case(
    "g4-image-is-a-folder",
    ("005.png",),
    check=lambda w, r, line: _not_named(line, "does not exist"),
)
def _(w):
    ds = w.png()
    (ds / "005.png").unlink()
    (ds / "005.png").mkdir()
    return ["reconstruct", str(ds)]


@case("g4-truncated-png", ("003.png",))
def _(w):
    ds = w.png()
    raw = (ds / "003.png").read_bytes()
    (ds / "003.png").write_bytes(raw[: len(raw) // 2])
    return ["reconstruct", str(ds)]


# Group 5: typer's own rejections as one line ---------------------------------------------------


@case(
    "g5-unknown-method",
    ("--method",),
    check=lambda w, r, line: _equals(
        line, "error: --method: 'foo' is not one of auto, ls, l1, sbl, plls, plsbl, rpca"
    ),
)
def _(w):
    return ["reconstruct", str(w.png()), "--method", "foo"]


def _equals(line: str, expected: str) -> None:
    assert line == expected, line


option_case("g5-unknown-channel", ["reconstruct"], "--channel", "x")
option_case("g5-threads-negative", ["reconstruct"], "--threads", "-1")
option_case("g5-threads-zero", ["reconstruct"], "--threads", "0")
option_case("g5-threads-word", ["reconstruct"], "--threads", "many")
option_case("g5-refine-lights-negative", ["reconstruct"], "--refine-lights", "-1")
option_case("g5-shadow-threshold-word", ["reconstruct"], "--shadow-threshold", "dark")
option_case("g5-safe-radius-above-max", ["calibrate"], "--safe-radius", "2", where="run")
option_case("g5-simulate-unknown-scene", ["simulate"], "--scene", "cube", where="")
option_case("g5-simulate-unknown-format", ["simulate"], "--format", "jpg", where="")
option_case("g5-serve-sim-zero-lights", ["rig", "serve-sim"], "--lights", "0", where="")
capture_case("g5-repeat-zero", "--repeat", "0")


@case("g5-unknown-option", ("--frobnicate",))
def _(w):
    return ["reconstruct", str(w.png()), "--frobnicate"]


@case("g5-extra-argument", ("surplus",))
def _(w):
    return ["reconstruct", str(w.png()), "surplus"]


@case("g5-missing-dataset-argument", ("DATASET", "dataset"))
def _(w):
    return ["reconstruct"]


@case("g5-capture-without-rig", ("--rig",))
def _(w):
    return ["capture", "--out", str(w.root / "out")]


@case("g5-rig-check-without-port", ("--port",))
def _(w):
    return ["rig", "check", "--lights", "4"]


@case("g5-unknown-command", ("recontruct",))
def _(w):
    return ["recontruct", "x"]


@case("g5-unreadable-dataset-folder", ds_name, root_ok=False)
def _(w):
    w.png().chmod(0)
    return ["reconstruct", str(w.ds)]


# Group 6: one line, carrying what the user must know --------------------------------------------


FAULTY_CAMERA = (
    '\n[faults]\ncamera = [{ kind = "timeout", at = 3 }, { kind = "timeout", at = 4 }]\n'
)


@case(
    "g6-camera-fails-after-retry",
    lambda w: (str(w.root / "out"),),
    keeps_run=True,
    check=lambda w, r, line: _has(line, "lights off", "--resume"),
)
def _(w):
    rig = w.copy("rig") / "small.toml"
    rig.write_text(rig.read_text().replace("timeout_s = 2.0", "timeout_s = 0.3") + FAULTY_CAMERA)
    return ["capture", "--rig", str(rig), "--out", str(w.root / "out")]


def _has(line: str, *words: str) -> None:
    for word in words:
        assert word in line, line


@case(
    "g6-controller-silent",
    ("small.toml", "controller", "out"),
    keeps_run=True,
    check=lambda w, r, line: _has(line, "watchdog", "--resume"),
)
def _(w):
    rig = w.copy("rig") / "small.toml"
    rig.write_text(rig.read_text() + '\n[faults]\ncontroller = [{ kind = "silence", at = 6 }]\n')
    return ["capture", "--rig", str(rig), "--out", str(w.root / "out")]


@case("g6-calibrate-fails-after-progress-bar", lambda w: (str(w.root / "png"),))
def _(w):
    ds = w.png()
    return ["calibrate", str(ds), "--roi", "0,0,16,16"]


# Group 7: sizes claimed by headers -------------------------------------------------------------

HUGE = 40000


def _small_rss(w, result, line) -> None:
    assert result.max_rss < 600 * MiB, f"peak RSS {result.max_rss / MiB:.0f} MiB"


@case("g7-png-header-40000-all", ("001.png",), check=_small_rss)
def _(w):
    ds = w.png()
    for file in image_files(ds):
        forge_png_size(file, HUGE, HUGE)
    forge_png_size(ds / "mask.png", HUGE, HUGE)
    (ds / "normal_gt.npy").unlink()
    return ["reconstruct", str(ds)]


@case("g7-png-header-40000-third", ("003.png",), check=_small_rss)
def _(w):
    ds = w.png()
    forge_png_size(ds / "003.png", HUGE, HUGE)
    return ["reconstruct", str(ds)]


@case("g7-mask-header-40000", ("mask.png",), check=_small_rss)
def _(w):
    ds = w.png()
    forge_png_size(ds / "mask.png", HUGE, HUGE)
    return ["reconstruct", str(ds)]


@case("g7-npy-header-40000", ("001.npy",), check=_small_rss)
def _(w):
    ds = w.copy("npy")
    header = {"descr": "<f4", "fortran_order": False, "shape": (HUGE, HUGE)}
    with (ds / "001.npy").open("wb") as stream:
        np.lib.format.write_array_header_1_0(stream, header)
        stream.write(b"\0" * 1024)
    return ["reconstruct", str(ds)]


@case("g7-tiff-header-40000", ("001.tif", "001.tiff"), check=_small_rss)
def _(w):
    ds = w.copy("tiff")
    first = image_files(ds)[0]
    with tifffile.TiffFile(first, mode="r+b") as tif:  # claim 40000x40000, keep 16x16 data
        tif.pages[0].tags["ImageWidth"].overwrite(HUGE)
        tif.pages[0].tags["ImageLength"].overwrite(HUGE)
    return ["reconstruct", str(ds)]


@case("g7-pfm-header-40000", ("001.pfm",), check=_small_rss)
def _(w):
    ds = w.png()
    (ds / "001.pfm").write_bytes(b"Pf\n40000 40000\n-1.0\n" + b"\0" * 4096)
    names = (ds / "filenames.txt").read_text().replace("001.png", "001.pfm")
    (ds / "filenames.txt").write_text(names)
    return ["reconstruct", str(ds)]


@case("g7-normal-gt-header-huge", ("normal_gt.npy",), check=_small_rss)
def _(w):
    ds = w.png()
    header = {"descr": "<f4", "fortran_order": False, "shape": (HUGE, HUGE, 3)}
    with (ds / "normal_gt.npy").open("wb") as stream:
        np.lib.format.write_array_header_1_0(stream, header)
    return ["reconstruct", str(ds)]


# Inputs the issue did not list -----------------------------------------------------------------


@case("x-empty-folder", lambda w: (str(w.root / "empty"),))
def _(w):
    (w.root / "empty").mkdir()
    return ["reconstruct", str(w.root / "empty")]


@case("x-missing-folder", lambda w: (str(w.root / "nowhere"),))
def _(w):
    return ["reconstruct", str(w.root / "nowhere")]


@case("x-dataset-is-a-file", lambda w: (str(w.ds / "001.png"),))
def _(w):
    return ["reconstruct", str(w.png() / "001.png")]


@case("x-only-light-directions", lambda w: (str(w.root / "lonely"),))
def _(w):
    (w.root / "lonely").mkdir()
    (w.root / "lonely" / "light_directions.txt").write_text("0 0 1\n")
    return ["reconstruct", str(w.root / "lonely")]


@case("x-symlink-loop-image", ("001.png",))
def _(w):
    ds = w.png()
    (ds / "001.png").unlink()
    os.symlink("001.png", ds / "001.png")
    return ["reconstruct", str(ds)]


@case("x-symlink-loop-dataset", lambda w: (str(w.root / "loop"),))
def _(w):
    os.symlink("loop", w.root / "loop")
    return ["reconstruct", str(w.root / "loop")]


for _name in ("light_directions.txt", "mask.png", "filenames.txt", "light_intensities.txt"):

    @case(f"x-folder-instead-of-{_name}", (_name,))
    def _(w, name=_name):
        ds = w.png()
        (ds / name).unlink()
        (ds / name).mkdir()
        return ["reconstruct", str(ds)]


@case("x-mask-wrong-size", ("mask.png",))
def _(w):
    ds = w.png()
    cv2.imwrite(str(ds / "mask.png"), np.full((8, 8), 255, np.uint8))
    return ["reconstruct", str(ds)]


@case("x-mask-empty", ("mask.png",))
def _(w):
    ds = w.png()
    cv2.imwrite(str(ds / "mask.png"), np.zeros((16, 16), np.uint8))
    return ["reconstruct", str(ds)]


@case("x-mask-garbage", ("mask.png",))
def _(w):
    ds = w.png()
    (ds / "mask.png").write_bytes(b"\x89PNG\r\n\x1a\n" + os.urandom(64))
    return ["reconstruct", str(ds)]


def text_case(id: str, name: str, content: bytes | Callable[[bytes], bytes]):
    @case(id, (name,))
    def _(w):
        ds = w.png()
        path = ds / name
        path.write_bytes(content(path.read_bytes()) if callable(content) else content)
        return ["reconstruct", str(ds)]


text_case("x-lights-row-nan", "light_directions.txt", lambda b: b"nan 0 1\n" + b.split(b"\n", 1)[1])
text_case("x-lights-row-inf", "light_directions.txt", lambda b: b"inf 0 1\n" + b.split(b"\n", 1)[1])
text_case("x-lights-two-columns", "light_directions.txt", b"0 1\n" * 8)
text_case("x-lights-four-columns", "light_directions.txt", b"0 0 1 1\n" * 8)
text_case("x-lights-empty", "light_directions.txt", b"")
text_case("x-lights-words", "light_directions.txt", b"left up front\n" * 8)
text_case("x-lights-not-utf8", "light_directions.txt", b"\xff\xfe\x00 0 1\n" * 8)
text_case("x-lights-zero-row", "light_directions.txt", lambda b: b"0 0 0\n" + b.split(b"\n", 1)[1])
text_case("x-lights-40-rows", "light_directions.txt", lambda b: b * 5)
text_case("x-lights-7-rows", "light_directions.txt", lambda b: b"\n".join(b.split(b"\n")[1:]))
text_case(
    "x-intensities-zero", "light_intensities.txt", lambda b: b"0 0 0\n" + b.split(b"\n", 1)[1]
)
text_case(
    "x-intensities-negative",
    "light_intensities.txt",
    lambda b: b"-1 -1 -1\n" + b.split(b"\n", 1)[1],
)
text_case(
    "x-intensities-nan", "light_intensities.txt", lambda b: b"nan 1 1\n" + b.split(b"\n", 1)[1]
)
text_case("x-intensities-wrong-count", "light_intensities.txt", b"1 1 1\n" * 3)
text_case("x-filenames-missing-file", "filenames.txt", lambda b: b.replace(b"004.png", b"404.png"))
text_case("x-filenames-duplicate", "filenames.txt", lambda b: b.replace(b"004.png", b"003.png"))
text_case("x-filenames-not-utf8", "filenames.txt", b"\xff\xfe001.png\n")
text_case("x-filenames-empty", "filenames.txt", b"\n\n")
text_case("x-filenames-names-mask", "filenames.txt", lambda b: b.replace(b"004.png", b"mask.png"))
text_case(
    "x-filenames-escapes-folder",
    "filenames.txt",
    lambda b: b.replace(b"004.png", b"../../etc/passwd"),
)


@case("x-rig-not-utf8", ("small.toml",))
def _(w):
    rig = w.copy("rig") / "small.toml"
    rig.write_bytes(rig.read_bytes() + b"\n# caf\xe9\n")
    return ["capture", "--rig", str(rig), "--out", str(w.root / "out"), "-q"]


@case("x-nine-images-eight-lights", ("light_directions.txt", "filenames.txt", "009.png"))
def _(w):
    ds = w.png()
    shutil.copy(ds / "008.png", ds / "009.png")
    (ds / "filenames.txt").write_text((ds / "filenames.txt").read_text() + "009.png\n")
    return ["reconstruct", str(ds)]


@case("x-tiff-five-channels", ("001.tif", "001.tiff"))
def _(w):
    ds = w.copy("tiff")
    tifffile.imwrite(
        image_files(ds)[0],
        np.ones((16, 16, 5), np.float32),
        photometric="minisblack",
        planarconfig="contig",
    )
    return ["reconstruct", str(ds)]


@case("x-8-and-16-bit-mixed", ("002.png",))
def _(w):
    ds = w.png()
    image = cv2.imread(str(ds / "002.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(ds / "002.png"), (image // 257).astype(np.uint8))
    return ["reconstruct", str(ds)]


@case("x-colour-and-grey-mixed", ("002.png",))
def _(w):
    ds = w.png()
    image = cv2.imread(str(ds / "002.png"), cv2.IMREAD_UNCHANGED)
    write_png16(ds / "002.png", np.dstack([image] * 3))
    return ["reconstruct", str(ds)]


@case("x-images-of-mixed-sizes", ("004.png",))
def _(w):
    ds = w.png()
    write_png16(ds / "004.png", np.full((16, 17), 1000))
    return ["reconstruct", str(ds)]


@case("x-out-is-a-file", lambda w: (str(w.root / "taken"),))
def _(w):
    (w.root / "taken").write_text("mine\n")
    return ["reconstruct", str(w.png()), "--out", str(w.root / "taken")]


@case("x-out-is-the-dataset", ds_name)
def _(w):
    return ["reconstruct", str(w.png()), "--out", str(w.ds)]


@case("x-out-is-an-image-of-the-dataset", lambda w: (str(w.ds / "001.png"),))
def _(w):
    return ["reconstruct", str(w.png()), "--out", str(w.ds / "001.png")]


@case("x-out-under-a-file", lambda w: (str(w.root / "taken"),))
def _(w):
    (w.root / "taken").write_text("mine\n")
    return ["reconstruct", str(w.png()), "--out", str(w.root / "taken" / "recon")]


@case("x-out-read-only-folder", lambda w: (str(w.root / "locked"),), root_ok=False)
def _(w):
    (w.root / "locked").mkdir()
    (w.root / "locked").chmod(0o500)
    return ["reconstruct", str(w.png()), "--out", str(w.root / "locked" / "recon")]


@case("x-out-unwritable-place", ("/proc/self/recon",))
def _(w):
    return ["reconstruct", str(w.png()), "--out", "/proc/self/recon"]


@case("x-unreadable-image", ("003.png",), root_ok=False)
def _(w):
    ds = w.png()
    (ds / "003.png").chmod(0)
    return ["reconstruct", str(ds)]


@case("x-normal-gt-wrong-shape", ("normal_gt.npy",))
def _(w):
    ds = w.png()
    np.save(ds / "normal_gt.npy", np.zeros((8, 8, 3), np.float32))
    return ["reconstruct", str(ds)]


@case("x-normal-gt-nan", ("normal_gt.npy",))
def _(w):
    ds = w.png()
    np.save(ds / "normal_gt.npy", np.full((16, 16, 3), np.nan, np.float32))
    return ["reconstruct", str(ds)]


@case("x-manifest-not-json", ("manifest.json",))
def _(w):
    run_dir = w.copy("run")
    (run_dir / "manifest.json").write_text("{ not json")
    return ["calibrate", str(run_dir)]


@case("x-run-frame-missing", ("frames",))
def _(w):
    run_dir = w.copy("run")
    frame = sorted((run_dir / "frames").iterdir())[-1]
    frame.unlink()
    return ["calibrate", str(run_dir)]


@case("x-run-not-calibrated", ("calibrate", "light_directions.txt"))
def _(w):
    return ["reconstruct", str(w.copy("run"))]


@case("x-calibrate-one-image", ("light", "image", "frame"))
def _(w):
    ds = w.root / "one"
    ds.mkdir()
    shutil.copy(w.templates["png"] / "001.png", ds / "001.png")
    return ["calibrate", str(ds)]


def rig_case(id: str, names, text: Callable[[str], str] | str, extra=()):
    @case(id, names)
    def _(w):
        rig = w.copy("rig") / "small.toml"
        rig.write_text(text(rig.read_text()) if callable(text) else text)
        return ["capture", "--rig", str(rig), "--out", str(w.root / "out"), "-q", *extra]


rig_case(
    "x-rig-lights-a-word",
    ("lights", "small.toml"),
    lambda t: t.replace("lights = 6", 'lights = "many"'),
)
rig_case(
    "x-rig-lights-negative",
    ("lights", "small.toml"),
    lambda t: t.replace("lights = 6", "lights = -3"),
)
rig_case(
    "x-rig-exposure-nan",
    ("exposure_s", "small.toml"),
    lambda t: t.replace("exposure_s = 0.05", "exposure_s = nan"),
)
rig_case(
    "x-rig-exposure-inf",
    ("exposure_s", "small.toml"),
    lambda t: t.replace("exposure_s = 0.05", "exposure_s = inf"),
)
rig_case(
    "x-rig-timeout-zero",
    ("timeout_s", "small.toml"),
    lambda t: t.replace("timeout_s = 0.3", "timeout_s = 0"),
)
rig_case(
    "x-rig-radius-nan",
    ("radius", "small.toml"),
    lambda t: t.replace("radius = 32.0", "radius = nan", 1),
)
rig_case(
    "x-rig-unknown-key",
    ("colour", "small.toml"),
    lambda t: t.replace("[camera]", "[camera]\ncolour = 1"),
)
rig_case("x-rig-not-toml", ("small.toml",), "this is = = not toml [")
rig_case(
    "x-rig-scene-huge",
    ("width", "small.toml"),
    lambda t: t.replace("width = 160", "width = 400000").replace("height = 120", "height = 300000"),
)


@case("x-rig-file-missing", lambda w: (str(w.root / "nope.toml"),))
def _(w):
    return ["capture", "--rig", str(w.root / "nope.toml"), "--out", str(w.root / "out")]


@case("x-rig-file-is-a-folder", lambda w: (str(w.root / "rig"),))
def _(w):
    return ["capture", "--rig", str(w.copy("rig")), "--out", str(w.root / "out")]


@case("x-capture-out-is-a-file", lambda w: (str(w.root / "taken"),))
def _(w):
    (w.root / "taken").write_text("mine\n")
    return ["capture", "--rig", str(w.copy("rig") / "small.toml"), "--out", str(w.root / "taken")]


@case("x-capture-out-is-a-dataset", lambda w: (str(w.ds),))
def _(w):
    return ["capture", "--rig", str(w.copy("rig") / "small.toml"), "--out", str(w.png())]


SERIAL_RIG_LINES = ('driver = "simulated"        # protocol',)


def _serial_rig(w) -> Path:
    rig = w.copy("rig") / "small.toml"
    text = rig.read_text().replace(
        'driver = "simulated"\nlights', 'driver = "serial"\nport = "/dev/null"\nlights', 1
    )
    text = text.replace("seed = 2012", f'seed = 2012\nlight_state_file = "{w.root / "state.json"}"')
    rig.write_text(text)
    return rig


def _port(w: Workspace, port: str) -> str:
    """``port`` itself, or a regular file (``@file``) or a folder (``@folder``) made for it."""
    if port == "@file":
        port = str(w.root / "port.txt")
        Path(port).write_text("not a tty\n")
    elif port == "@folder":
        port = str(w.root)
    w.notes["port"] = port
    return port


def _named_port(w: Workspace) -> tuple[str, ...]:
    return ("--port", w.notes.get("port", ""))


for _port_label, _port_text in (
    ("dev-null", "/dev/null"),
    ("missing", "/nonexistent/ttyACM9"),
    ("regular-file", "@file"),
    ("folder", "@folder"),
):

    @case(f"x-capture-port-{_port_label}", _named_port, timeout=60)
    def _(w, port=_port_text):
        rig = str(_serial_rig(w))
        return [
            "capture",
            "--rig",
            rig,
            "--out",
            str(w.root / "out"),
            "--port",
            _port(w, port),
            "-q",
        ]

    @case(f"x-rig-check-port-{_port_label}", _named_port, timeout=60)
    def _(w, port=_port_text):
        return ["rig", "check", "--port", _port(w, port), "--lights", "4"]


@case("x-simulate-seed-negative", ("--seed",))
def _(w):
    return ["simulate", str(w.root / "new"), "--size", "16", "--lights", "8", "--seed", "-1"]


@case("x-bench-seed-negative", ("--seed",))
def _(w):
    return ["bench", "paper", "--quick", "--seed", "-1"]


@case("x-simulate-into-dataset", lambda w: (str(w.ds),))
def _(w):
    return ["simulate", str(w.png()), "--size", "16", "--lights", "8"]


@case("x-simulate-two-lights", ("--lights",))
def _(w):
    return ["simulate", str(w.root / "new"), "--size", "16", "--lights", "2"]


@case("x-capture-resume-nothing", lambda w: (str(w.root / "out"),))
def _(w):
    return [
        "capture",
        "--rig",
        str(w.copy("rig") / "small.toml"),
        "--out",
        str(w.root / "out"),
        "--resume",
    ]


#: The cases CI runs (several per group); ``pytest -m slow`` runs every case of the table.
CI_CASES = {
    # 1: accepted silently
    "g1-all-zero-png",
    "g1-nan-npy",
    "g1-nan-float-tiff",
    "g1-shadow-threshold-nan",
    "g1-shadow-threshold-above-every-value",
    # 2: numbers reaching the maths unchecked
    "g2-sphere-negative-radius",
    "g2-sphere-nan",
    "g2-roi-nan",
    "g2-focal-length-zero",
    "g2-memory-budget-nan",
    "g2-memory-budget-word",
    "g2-exposure-nan",
    "g2-lights-beyond-rig",
    "g2-simulate--max-zenith-nan",
    "g2-simulate--size-100000",
    "g2-rig-check--dwell-inf",
    "g2-bench-unknown-table",
    # 4: the right file, named early
    "g4-lights-coplanar",
    "g4-lights-identical",
    "g4-two-lights-two-images",
    "g4-first-image-wrong-size",
    "g4-first-image-forged-header",
    "g4-no-chrome-sphere",
    "g4-dark-frame-wrong-size",
    "g4-image-is-a-folder",
    "g4-truncated-png",
    # 5: typer's rejections
    "g5-unknown-method",
    "g5-unknown-channel",
    "g5-threads-negative",
    "g5-refine-lights-negative",
    "g5-repeat-zero",
    "g5-unknown-option",
    "g5-missing-dataset-argument",
    "g5-unknown-command",
    # 6: one line only
    "g6-camera-fails-after-retry",
    "g6-controller-silent",
    "g6-calibrate-fails-after-progress-bar",
    # 7: sizes claimed by headers
    "g7-png-header-40000-all",
    "g7-png-header-40000-third",
    "g7-mask-header-40000",
    "g7-npy-header-40000",
    "g7-tiff-header-40000",
    # not in the issue
    "x-empty-folder",
    "x-symlink-loop-image",
    "x-folder-instead-of-mask.png",
    "x-lights-row-nan",
    "x-lights-not-utf8",
    "x-intensities-zero",
    "x-filenames-duplicate",
    "x-8-and-16-bit-mixed",
    "x-images-of-mixed-sizes",
    "x-out-is-a-file",
    "x-out-is-the-dataset",
    "x-rig-exposure-nan",
    "x-rig-unknown-key",
    "x-capture-port-dev-null",
    "x-rig-check-port-regular-file",
    "x-tiff-five-channels",
    "x-simulate-seed-negative",
    "x-lp-lists-more-images-than-the-folder",
    "x-lp-coplanar",
    "x-view-not-a-result",
}


def _params() -> list:
    unknown = CI_CASES - {c.id for c in CASES}
    assert not unknown, unknown
    return [
        pytest.param(c, id=c.id, marks=() if c.id in CI_CASES else pytest.mark.slow) for c in CASES
    ]


@dataclass
class Outcome:
    workspace: Workspace
    result: Result | None = None
    before: dict | None = None
    after: dict | None = None
    error: BaseException | None = None


def _run_case(case: Case, workspace: Workspace) -> Outcome:
    outcome = Outcome(workspace)
    try:
        args = case.build(workspace)
        outcome.before = snapshot(workspace.root)
        outcome.result = run(args, workspace.root, workspace.home, timeout=case.timeout)
        outcome.after = snapshot(workspace.root)
    except Exception as exc:  # noqa: BLE001 - reported by the case's own test
        outcome.error = exc
    return outcome


@pytest.fixture(scope="session")
def table(request, templates, tmp_path_factory) -> dict[str, Outcome]:
    """Run every selected case of the table at once, a few commands in parallel.

    Each command is a separate process that mostly imports and reads; running them side by side
    keeps the table's wall time near its CPU time divided by the cores.
    """
    chosen = [
        item.callspec.params["case"]
        for item in request.session.items
        if getattr(item, "originalname", "") == "test_bad_input"
        and Path(str(item.fspath)) == Path(__file__)
        and not item.get_closest_marker("skip")
    ]
    chosen = [c for c in chosen if c.root_ok or not IS_ROOT]
    workspaces = []
    for c in chosen:
        folder = tmp_path_factory.mktemp(c.id)
        (folder / "home").mkdir()
        (folder / "case").mkdir()
        workspaces.append(Workspace(folder / "case", folder / "home", templates))
    with ThreadPoolExecutor(max_workers=max(2, os.cpu_count() or 2)) as pool:
        outcomes = list(pool.map(_run_case, chosen, workspaces))
    return {c.id: o for c, o in zip(chosen, outcomes, strict=True)}


@pytest.mark.parametrize("case", _params())
def test_bad_input(case: Case, table: dict[str, Outcome]) -> None:
    if IS_ROOT and not case.root_ok:
        pytest.skip("file permissions do not bind root")
    outcome = table[case.id]
    if outcome.error is not None:
        raise outcome.error
    assert outcome.result is not None and outcome.before is not None
    line = assert_one_error_line(outcome.result, case.names(outcome.workspace), case.code)
    if case.check is not None:
        case.check(outcome.workspace, outcome.result, line)
    after = outcome.after
    if case.keeps_run:  # a failed capture keeps its complete frames for --resume
        after = {k: v for k, v in after.items() if k != "out" and not k.startswith("out/")}
    assert after == outcome.before, "files created or changed"


# --- signals -------------------------------------------------------------------------------------


def staging_folders(folder: Path) -> list[Path]:
    return [
        p for p in folder.rglob(".*") if ".partial-" in p.name or p.name.startswith(".calibrate-")
    ]


@pytest.fixture(scope="session")
def slow_dataset(tmp_path_factory) -> Path:
    """A dataset whose SBL solve with light refinement takes several seconds."""
    root = tmp_path_factory.mktemp("slow")
    result = run(["simulate", str(root / "slow"), "--size", "64", "--lights", "40"], root, root)
    assert result.code == 0, result.stderr
    return root / "slow"


SLOW_RECONSTRUCT = ["--method", "sbl", "--refine-lights", "200", "--threads", "1"]


@pytest.mark.parametrize(
    "sig",
    [
        signal.SIGTERM,
        pytest.param(signal.SIGHUP, marks=pytest.mark.slow),
        pytest.param(signal.SIGINT, marks=pytest.mark.slow),
    ],
    ids=lambda s: s.name,
)
def test_signal_during_reconstruct(sig, workspace, slow_dataset) -> None:
    if sig == signal.SIGINT and signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        pytest.skip("SIGINT is ignored in this (background) session and so in the command")
    ds = workspace.root / "slow"
    shutil.copytree(slow_dataset, ds)
    before = snapshot(workspace.root)
    proc, out, err = start(
        ["reconstruct", str(ds), *SLOW_RECONSTRUCT], workspace.root, workspace.home
    )
    wait_until(lambda: bool(staging_folders(ds)), proc)
    time.sleep(0.3)
    proc.send_signal(sig)
    result = finish(proc, out, err, timeout=60)
    line = assert_one_error_line(result, ("interrupted",), code=130)
    assert "no output" in line, line
    assert snapshot(workspace.root) == before, "staging or output left behind"


def _capture_args(w: Workspace) -> list[str]:
    rig = w.copy("rig") / "small.toml"
    rig.write_text(rig.read_text().replace("lights = 6", "lights = 12"))
    return ["capture", "--rig", str(rig), "--out", str(w.root / "out")]


@pytest.mark.parametrize(
    "sig",
    [signal.SIGHUP, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)],
    ids=lambda s: s.name,
)
def test_signal_during_capture(sig, workspace) -> None:
    args = _capture_args(workspace)
    frames = workspace.root / "out" / "frames"
    proc, out, err = start(args, workspace.root, workspace.home)
    wait_until(lambda: frames.is_dir() and len(list(frames.glob("*.dng"))) >= 2, proc)
    proc.send_signal(sig)
    result = finish(proc, out, err, timeout=60)
    line = assert_one_error_line(result, ("interrupted",), code=130)
    assert "lights off" in line and "--resume" in line, line
    resumed = run([*args, "--resume", "-q"], workspace.root, workspace.home)
    assert resumed.code == 0, resumed.stderr
    manifest = json.loads((workspace.root / "out" / "manifest.json").read_text())
    assert len(manifest["frames"]) == 13


@pytest.mark.parametrize(
    "sig",
    [signal.SIGTERM, pytest.param(signal.SIGHUP, marks=pytest.mark.slow)],
    ids=lambda s: s.name,
)
def test_signal_during_calibrate(sig, workspace) -> None:
    # The small run's frames can all be read between two 5 ms polls; a calibration that ends
    # (successfully) before the signal is sent is run again on a fresh copy, up to 5 times.
    for attempt in range(5):
        run_dir = workspace.copy("run", f"run{attempt}")
        before = snapshot(workspace.root)
        proc, out, err = start(["calibrate", str(run_dir)], workspace.root, workspace.home)

        def reading_frames(proc=proc, run_dir=run_dir) -> bool:
            try:
                return any(
                    str(run_dir) in os.readlink(fd)
                    for fd in Path(f"/proc/{proc.pid}/fd").iterdir()
                )
            except OSError:
                return False

        deadline = time.monotonic() + 90
        while not reading_frames() and _alive(proc.pid):
            assert time.monotonic() < deadline, "timed out waiting for the command to get going"
            time.sleep(0.005)
        if not _alive(proc.pid):
            done = finish(proc, out, err, timeout=60)
            assert done.code == 0, done.stderr  # ended before the signal: only by finishing
            continue
        proc.send_signal(sig)
        result = finish(proc, out, err, timeout=60)
        assert_one_error_line(result, ("interrupted",), code=130)
        assert snapshot(workspace.root) == before
        return
    pytest.fail("calibrate finished before the signal could be sent, 5 times")


@contextmanager
def simulated_controller(workspace: Workspace, *faults: str) -> Iterator[str]:
    """Serve a 4-light simulated controller (``ps-lab rig serve-sim``); yield its port."""
    server, sout, serr = start(
        ["rig", "serve-sim", "--lights", "4", *faults], workspace.root, workspace.home
    )
    try:
        wait_until(lambda: sout.stat().st_size > 0, server)
        yield sout.read_text().split()[0]
    finally:
        server.send_signal(signal.SIGINT)
        finish(server, sout, serr, timeout=30)


def _check_home(workspace: Workspace) -> Path:
    home = workspace.root / "h2"
    home.mkdir()
    return home


def test_signal_during_rig_check(workspace) -> None:
    with simulated_controller(workspace) as port:
        proc, out, err = start(
            ["rig", "check", "--port", port, "--lights", "4", "--dwell", "5"],
            workspace.root,
            _check_home(workspace),
        )
        time.sleep(3)
        proc.send_signal(signal.SIGTERM)
        result = finish(proc, out, err, timeout=30)
    line = assert_one_error_line(result, ("interrupted",), code=130)
    assert "lights off" in line or "lit" in line, line


def test_rig_check_names_the_light_left_lit(workspace) -> None:
    """A controller that falls silent mid-check: the one line says which light may be lit."""
    with simulated_controller(workspace, "--fault", "silence@6") as port:
        result = run(
            ["rig", "check", "--port", port, "--lights", "4"],
            workspace.root,
            _check_home(workspace),
        )
    line = assert_one_error_line(result, (port,))
    assert re.search(r"light \d may still be lit: .*watchdog", line), line


def test_sigkill_staging_removed_by_next_run(workspace, slow_dataset) -> None:
    ds = workspace.root / "slow"
    shutil.copytree(slow_dataset, ds)
    out = workspace.root / "result"
    proc, o, e = start(
        ["reconstruct", str(ds), *SLOW_RECONSTRUCT, "--out", str(out)],
        workspace.root,
        workspace.home,
    )
    wait_until(lambda: bool(staging_folders(workspace.root)), proc)
    proc.kill()
    finish(proc, o, e)
    assert staging_folders(workspace.root), "SIGKILL should leave the staging folder"
    again = run(
        ["reconstruct", str(ds), "--method", "ls", "--out", str(out)],
        workspace.root,
        workspace.home,
    )
    assert again.code == 0, again.stderr
    assert not staging_folders(workspace.root)
    assert (out / "normals.npy").is_file()


def test_many_unsolved_pixels_warn_once(workspace) -> None:
    ds = workspace.png()
    mask = cv2.imread(str(ds / "mask.png"), cv2.IMREAD_UNCHANGED)
    mask[:] = 255  # the whole frame: the black background cannot be solved
    cv2.imwrite(str(ds / "mask.png"), mask)
    result = run(["reconstruct", str(ds), "--method", "ls"], workspace.root, workspace.home)
    assert result.code == 0, result.stderr
    assert len(result.lines) == 1 and result.lines[0].startswith("warning:"), result.stderr
    assert "%" in result.lines[0]


BUG = (
    "import sys\n"
    "import ps_lab.render.simulate as simulate\n"
    "def broken(*args, **kwargs):\n"
    "    raise ZeroDivisionError('injected bug')\n"
    "simulate.write_simulated_dataset = broken\n"
    "import ps_lab.commands.simulate as command\n"
    "command.write_simulated_dataset = broken\n"
    "from ps_lab.cli import main\n"
    "sys.argv[0] = 'ps-lab'\n"
    "main()\n"
)


@pytest.mark.parametrize("verbose", [[], ["-vv"]], ids=["quiet", "vv"])
def test_a_bug_is_one_line_naming_the_log(verbose, workspace) -> None:
    """An exception that is not a PsLabError: one line saying it is a bug and where the log is."""
    out = workspace.root / "new"
    result = subprocess.run(
        [sys.executable, "-c", BUG, *verbose, "simulate", str(out), "--size", "16"],
        cwd=workspace.root,
        capture_output=True,
        text=True,
        env=environment(workspace.home),
        timeout=120,
    )
    assert result.returncode == 2, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    line = lines[-1]
    assert line.startswith("error: internal error (a bug in ps-lab"), result.stderr
    assert "ZeroDivisionError: injected bug" in line
    log_file = Path(line.split("traceback in ", 1)[1].split(";", 1)[0])
    assert log_file.is_file() and "Traceback" in log_file.read_text()
    assert log_file.is_relative_to(workspace.home)
    if verbose:
        assert "Traceback" in result.stderr
    else:
        assert len(lines) == 1 and "Traceback" not in result.stderr
    assert not out.exists()
