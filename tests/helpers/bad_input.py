"""The bad-input tables: malformed inputs run through ``ps-lab`` as a user runs it, and checked.

Each command's test file holds a :class:`CaseTable` of :class:`Case` (one malformed input: how to
build it in a fresh :class:`Workspace`, and what the one error line must name) and one test
parametrised over it. The conftest's session fixture ``bad_input_outcomes`` runs every selected
case of every table at once, a few commands in parallel (each is a separate process that mostly
imports and reads); each case's test then checks the README's promise (:func:`check_outcome`):
exit code 2, exactly one line on stderr, starting with ``error:``, that names the offending file
or option, no traceback, and no file created or changed in the case's folder. The inputs are
copies of small templates (:class:`Templates`: 16x16 datasets with 8 lights, a 6-light capture
run, a result) made once per session, each when a case first asks for it.
"""

from __future__ import annotations

import os
import shutil
import struct
import threading
import time
import zlib
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from helpers.hostile import (
    IS_ROOT,
    Result,
    assert_one_error_line,
    assert_quiet,
    finish as _finish,
    run as _run,
    snapshot,
    temporary_leftovers,
)
from helpers.rigs import NEAR_RIG_ONE_SPHERE_MISSING, SMALL_RIG


def run(args: list[str], cwd: Path, home: Path, timeout: float = 120) -> Result:
    """Every CLI run of the tables: no numpy warning or traceback, whatever the exit code."""
    result = _run(args, cwd, home, timeout)
    assert_quiet(result)
    return result


def finish(proc, out: Path, err: Path, timeout: float = 120) -> Result:
    """:func:`helpers.hostile.finish`, and nothing noisy on the terminal (as :func:`run`)."""
    result = _finish(proc, out, err, timeout)
    assert_quiet(result)
    return result


MiB = 1 << 20
NOT_UTF8 = os.fsdecode(b"caf\xe9")  # Latin-1 "café": not UTF-8


# --- making and damaging datasets -------------------------------------------------------------


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


def fill_images(ds: Path, value_of: Callable[[np.ndarray], np.ndarray]) -> None:
    for file in image_files(ds):
        if file.suffix == ".png":
            image = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
            write_png16(file, value_of(image))
        elif file.suffix == ".npy":
            np.save(file, value_of(np.load(file)))
        else:
            tifffile.imwrite(file, value_of(tifffile.imread(file)))


def staging_folders(folder: Path) -> list[Path]:
    return [
        p for p in folder.rglob(".*") if ".partial-" in p.name or p.name.startswith(".calibrate-")
    ]


# --- checks a case adds (``check=lambda w, r, line: ...``) ----------------------------------------


def has(line: str, *words: str) -> None:
    for word in words:
        assert word in line, line


def lacks(text: str, word: str) -> None:
    assert word not in text, text


def equals(line: str, expected: str) -> None:
    assert line == expected, line


def succeeded(w: Workspace, result: Result, line: str | None) -> None:
    """A case that must work (``code=0``): exit 0, no traceback, no staging folder left."""
    assert result.code == 0, result.stderr
    assert "Traceback" not in result.stderr
    assert not [p for p in w.root.rglob(".*") if ".partial-" in p.name], "staging left behind"


# --- the templates (one session, each made when first asked for) --------------------------------


def _simulated(root: Path, home: Path, name: str, fmt: str) -> Path:
    args = ["simulate", str(root / name), "--size", "16", "--lights", "8"]
    result = run([*args, "--format", fmt] if fmt else args, root, home)
    assert result.code == 0, result.stderr
    return root / name


def _rig(root: Path, home: Path, t: Templates) -> Path:
    rig = root / "rig" / "small.toml"
    rig.parent.mkdir()
    rig.write_text(SMALL_RIG)
    return rig.parent


def _captured(root: Path, home: Path, name: str, rig: Path) -> Path:
    result = run(["capture", "--rig", str(rig), "--out", str(root / name), "-q"], root, home)
    assert result.code == 0, result.stderr
    return root / name


def _near(root: Path, home: Path, t: Templates) -> Path:
    rig = root / "near.toml"
    rig.write_text(NEAR_RIG_ONE_SPHERE_MISSING)
    return _captured(root, home, "near", rig)


def _result(root: Path, home: Path, t: Templates) -> Path:
    result = root / "result"
    done = run(["reconstruct", str(t["png"]), "--method", "ls", "--out", str(result)], root, home)
    assert done.code == 0, done.stderr
    return result


def _jpeg_or_exr(root: Path, home: Path, t: Templates, suffix: str) -> Path:
    """The png template's frames as sRGB JPEGs (quality 100) or half-float RGB OpenEXR."""
    import OpenEXR

    from ps_lab.io.encoding import linear_to_srgb
    from ps_lab.io.images import read_image

    png = t["png"]
    names = (png / "filenames.txt").read_text().split()
    folder = root / suffix[1:]
    folder.mkdir()
    shutil.copy(png / "light_directions.txt", folder)
    shutil.copy(png / "mask.png", folder)
    (folder / "filenames.txt").write_text("".join(Path(n).stem + suffix + "\n" for n in names))
    for name in names:
        linear = read_image(png / name).data
        if suffix == ".jpg":
            encoded = np.round(linear_to_srgb(linear) * 255).astype(np.uint8)
            ok, data = cv2.imencode(".jpg", encoded, [cv2.IMWRITE_JPEG_QUALITY, 100])
            assert ok
            (folder / f"{Path(name).stem}.jpg").write_bytes(data.tobytes())
        else:
            rgb = np.repeat(linear, 3, axis=2) if linear.shape[2] == 1 else linear
            channels = {c: np.ascontiguousarray(rgb[..., k].astype(np.float16))
                        for k, c in enumerate("RGB")}  # fmt: skip
            with OpenEXR.File({"type": OpenEXR.scanlineimage}, channels) as file:
                file.write(str(folder / f"{Path(name).stem}.exr"))
    return folder


def _lp(root: Path, home: Path, t: Templates) -> Path:
    """The png template with a RelightLab ``dirs.lp`` instead of its two text files."""
    png = t["png"]
    names = (png / "filenames.txt").read_text().split()
    lp = root / "lp"
    shutil.copytree(png, lp)
    directions = np.loadtxt(png / "light_directions.txt")
    rows = [f"{n} {x:.6f} {y:.6f} {z:.6f}" for n, (x, y, z) in zip(names, directions, strict=True)]
    (lp / "light_directions.txt").unlink()
    (lp / "filenames.txt").unlink()
    (lp / "dirs.lp").write_text(f"{len(rows)}\n" + "\n".join(rows) + "\n")
    return lp


BUILDERS: dict[str, Callable[[Path, Path, Templates], Path]] = {
    "png": lambda root, home, t: _simulated(root, home, "png", "png16"),
    "npy": lambda root, home, t: _simulated(root, home, "npy", "npy"),
    "tiff": lambda root, home, t: _simulated(root, home, "tiff", "tiff32"),
    "rig": _rig,
    "run": lambda root, home, t: _captured(root, home, "run", t["rig"] / "small.toml"),
    "near": _near,
    "result": _result,
    "jpeg": lambda root, home, t: _jpeg_or_exr(root, home, t, ".jpg"),
    "exr": lambda root, home, t: _jpeg_or_exr(root, home, t, ".exr"),
    "lp": _lp,
}


class Templates(Mapping):
    """The read-only inputs the cases copy: ``png``, ``npy``, ``tiff`` (16x16 datasets, 8 lights),
    ``rig`` (a folder holding ``small.toml``), ``run`` (its capture), ``near`` (a near rig's
    capture whose second sphere is absent), ``result`` (``reconstruct --method ls`` of ``png``),
    ``jpeg``, ``exr`` and ``lp`` (``png`` as sRGB JPEGs, OpenEXR frames, a ``.lp`` file).

    Each is made on first use, once, under a lock (cases are built in parallel threads).
    """

    def __init__(self, root: Path, home: Path) -> None:
        self.root, self.home = root, home
        self._made: dict[str, Path] = {}
        self._locks = {name: threading.Lock() for name in BUILDERS}

    def __getitem__(self, name: str) -> Path:
        if name not in BUILDERS:
            raise KeyError(name)
        with self._locks[name]:
            if name not in self._made:
                self._made[name] = BUILDERS[name](self.root, self.home, self)
        return self._made[name]

    def __iter__(self):
        return iter(BUILDERS)

    def __len__(self) -> int:
        return len(BUILDERS)


@dataclass
class Workspace:
    """One case's folder (``root``, snapshotted) and home (cache, ``TMPDIR``)."""

    root: Path
    home: Path
    templates: Mapping[str, Path]
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


def ds_name(w: Workspace) -> tuple[str, ...]:
    return (str(w.ds),)


def named(*parts: str) -> Callable[[Workspace], tuple[str, ...]]:
    """A case's ``names``: the path ``parts`` under the case's folder."""
    return lambda w: (str(w.root.joinpath(*parts)),)


#: Ports that are no serial device (label, port; ``@file`` and ``@folder`` are made by
#: :func:`serial_port`).
SERIAL_PORTS = (
    ("dev-null", "/dev/null"),
    ("missing", "/nonexistent/ttyACM9"),
    ("regular-file", "@file"),
    ("folder", "@folder"),
)


def serial_port(w: Workspace, port: str) -> str:
    """``port`` itself, or a regular file (``@file``) or a folder (``@folder``) made for it."""
    if port == "@file":
        port = str(w.root / "port.txt")
        Path(port).write_text("not a tty\n")
    elif port == "@folder":
        port = str(w.root)
    w.notes["port"] = port
    return port


def named_port(w: Workspace) -> tuple[str, ...]:
    return ("--port", w.notes.get("port", ""))


# --- the tables ----------------------------------------------------------------------------------


@dataclass
class Case:
    """One malformed input: ``build(w)`` prepares ``w.root`` and returns the arguments.

    ``names(w)``: what the error line may name (one of them must appear); ``check(w, result,
    line)``: further checks (``line`` is None when ``code`` is 0: a case that must succeed, which
    ``check`` then judges alone). ``keeps_run``: a failed capture keeps its complete frames in
    ``--out`` for ``--resume``; ``leftovers`` (on unless turned off): no temporary file may be
    left in ``TMPDIR``; ``quiet_stdout``: nothing on stdout.
    """

    id: str
    build: Callable[[Workspace], list[str]]
    names: Callable[[Workspace], tuple[str, ...]]
    code: int = 2
    check: Callable[[Workspace, Result, str | None], None] | None = None
    root_ok: bool = True  # False: needs a non-root user (file permissions)
    timeout: float = 120
    keeps_run: bool = False
    leftovers: bool = True
    quiet_stdout: bool = False


class CaseTable:
    """A test file's cases; ``defaults`` apply to each (see :class:`Case`)."""

    def __init__(self, **defaults) -> None:
        self.cases: list[Case] = []
        self.defaults = defaults

    def case(self, id: str, names, **options):
        """Register the decorated ``build(w)`` as case ``id``."""

        def register(build):
            self.cases.append(
                Case(
                    id,
                    build,
                    names if callable(names) else (lambda w, n=names: tuple(n)),
                    **{**self.defaults, **options},
                )
            )
            return build

        return register

    def option_case(self, id: str, command: list[str], option: str, value: str, where="png"):
        """``command [copy of template where] option value``, refused naming the option."""

        @self.case(id, (option,))
        def _(w):
            target = [str(w.copy(where))] if where else []
            return [*command, *target, option, value]

    def test(self, ci: set[str]):
        """The table's test: each case checked by :func:`check_outcome` (``test_bad_input = ...``).

        The cases in ``ci`` run in CI, the rest with ``-m slow``.
        """

        @pytest.mark.parametrize("case", self.params(ci))
        def test_bad_input(case: Case, bad_input_outcomes: dict[str, Outcome]) -> None:
            check_outcome(case, bad_input_outcomes)

        return test_bad_input

    def params(self, ci: set[str]) -> list:
        """Every case as a pytest param: those in ``ci`` run in CI, the rest with ``-m slow``."""
        unknown = ci - {c.id for c in self.cases}
        assert not unknown, unknown
        return [
            pytest.param(c, id=c.id, marks=() if c.id in ci else pytest.mark.slow)
            for c in self.cases
        ]


@dataclass
class Outcome:
    workspace: Workspace
    result: Result | None = None
    before: dict | None = None
    error: BaseException | None = None


def _run_case(case: Case, workspace: Workspace) -> Outcome:
    outcome = Outcome(workspace)
    try:
        args = case.build(workspace)
        outcome.before = snapshot(workspace.root)
        started = time.monotonic()
        outcome.result = run(args, workspace.root, workspace.home, timeout=case.timeout)
        workspace.notes["seconds"] = time.monotonic() - started
    except Exception as exc:  # noqa: BLE001 - reported by the case's own test
        outcome.error = exc
    return outcome


def run_cases(cases: list[Case], templates: Mapping[str, Path], tmp_path_factory):
    """Run ``cases`` at once, a few commands in parallel; their outcomes by id."""
    ids = [c.id for c in cases]
    assert len(set(ids)) == len(ids), "two cases share an id"
    cases = [c for c in cases if c.root_ok or not IS_ROOT]
    workspaces = []
    for c in cases:
        folder = tmp_path_factory.mktemp(c.id)
        (folder / "home").mkdir()
        (folder / "case").mkdir()
        workspaces.append(Workspace(folder / "case", folder / "home", templates))
    with ThreadPoolExecutor(max_workers=max(2, os.cpu_count() or 2)) as pool:
        outcomes = list(pool.map(_run_case, cases, workspaces))
    return {c.id: o for c, o in zip(cases, outcomes, strict=True)}


def check_outcome(case: Case, outcomes: dict[str, Outcome]) -> None:
    """The README's promise for one case (or the case's own check, for one that must succeed)."""
    if IS_ROOT and not case.root_ok:
        pytest.skip("file permissions do not bind root")
    outcome = outcomes[case.id]
    if outcome.error is not None:
        raise outcome.error
    result, w = outcome.result, outcome.workspace
    assert result is not None and outcome.before is not None
    if case.code == 0:
        assert case.check is not None
        case.check(w, result, None)
        return
    line = assert_one_error_line(result, case.names(w), case.code)
    if case.quiet_stdout:
        assert result.stdout == "", result.stdout
    if case.check is not None:
        case.check(w, result, line)
    after = snapshot(w.root)
    if case.keeps_run:  # a failed capture keeps its complete frames for --resume
        after = {k: v for k, v in after.items() if k != "out" and not k.startswith("out/")}
    assert after == outcome.before, "files created or changed"
    if case.leftovers:
        assert not temporary_leftovers(w.home), "temporary files left behind"
