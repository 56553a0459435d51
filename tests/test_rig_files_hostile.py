"""Hostile LED-model files, board heights and result folders (issue 43), run as a user runs them.

A small near-light rig is calibrated once with ``--flat-field`` (``light_positions.txt``,
``light_anisotropy.txt``, ``light_axes.txt``, ``flat_field.npz``, ...); each case damages one
array of one file and runs ``ps-lab reconstruct`` (or ``calibrate --board``). The promise
(README, "Failure behaviour"): exit 2, one ``error:`` line naming the file and the array (or the
option), no traceback or numpy warning, nothing created or changed.
"""

from __future__ import annotations

import io
import shutil
import zipfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from helpers.bad_input import CaseTable
from helpers.hostile import (
    Result,
    assert_one_error_line,
    assert_quiet,
    refused,
    run,
    snapshot,
    temporary_leftovers,
)

from ps_lab.render.table_rig import (
    TableRig,
    write_board_frames,
    write_table_rig,
)

# A quarter of the table rig (120x90): calibration and a failing run take about a second each.
RIG = replace(
    TableRig(shape=(90, 120), origin_px=(59.0, 46.0), dome_radius=165.0,
             spheres=((15.0, 74.0, 10.0), (105.0, 15.5, 10.0)), object_center=(61.0, 44.0),
             object_radius=28.0, object_top=7.0, led_radius=3.0),
    beam_mu=2.0, beam_tilt_deg=8.0, output_spread=0.1,
)
SPHERES = [a for c in RIG.spheres for a in ("--sphere", f"{c[0]:g},{c[1]:g},{c[2]:g}")]
N = 24


@pytest.fixture(scope="session")
def near(tmp_path_factory) -> dict[str, Path]:
    """The calibrated rig (``near``) and its board frames (``board``)."""
    root = tmp_path_factory.mktemp("rig-files")
    write_table_rig(root / "near", RIG)
    write_board_frames(root / "board", RIG)
    result = run(["calibrate", str(root / "near"), *SPHERES, "--object", "table",
                  "--flat-field", str(root / "board")], root, root / "home")
    assert result.code == 0, result.stderr
    assert_quiet(result)
    for name in ("flat_field.npz", "light_axes.txt", "light_anisotropy.txt"):
        assert (root / "near" / name).is_file()
    return {"near": root / "near", "board": root / "board"}


# --- damage ------------------------------------------------------------------------------------


def _flat(**arrays) -> Callable[[Path], None]:
    """Rewrite flat_field.npz with ``arrays`` replaced (a callable: of the old array; None:
    dropped)."""

    def damage(ds: Path) -> None:
        with np.load(ds / "flat_field.npz") as data:
            current = {k: data[k] for k in data.files}
        for key, value in arrays.items():
            if value is None:
                current.pop(key)
            else:
                current[key] = value(current[key]) if callable(value) else value
        with open(ds / "flat_field.npz", "wb") as handle:
            np.savez(handle, **current)

    return damage


def _truncate(ds: Path) -> None:
    data = (ds / "flat_field.npz").read_bytes()
    (ds / "flat_field.npz").write_bytes(data[: len(data) // 2])


def _npy_instead(ds: Path) -> None:
    with open(ds / FLAT, "wb") as handle:
        np.save(handle, np.ones((24, 3, 3)))


def _forged_gains(ds: Path) -> None:
    """gains.npy whose header claims 24 x 90000 x 90000 values (1.5 TB) over the real bytes."""
    with np.load(ds / FLAT) as data:
        arrays = {k: data[k] for k in data.files}
    members = {}
    for key, value in arrays.items():
        buffer = io.BytesIO()
        np.save(buffer, value)
        members[key] = buffer.getvalue()
    raw = members["gains"]
    end = raw.index(b"\n") + 1
    shape = str(arrays["gains"].shape).encode()
    header = raw[:end].replace(shape, b"(24, 90000, 90000)")
    header = header[:-1].rstrip(b" ").ljust(end - 1) + b"\n"  # the same length
    members["gains"] = header + raw[end:]
    with zipfile.ZipFile(ds / FLAT, "w") as archive:
        for key, value in members.items():
            archive.writestr(f"{key}.npy", value)


def _text(name: str, rows: str) -> Callable[[Path], None]:
    def damage(ds: Path) -> None:
        (ds / name).write_text(rows)

    return damage


def _nan_row(a: np.ndarray) -> np.ndarray:
    a = a.astype(np.float64)
    a[0] = np.nan
    return a


def _partly_nan(a: np.ndarray) -> np.ndarray:
    a = a.copy()
    a[2, 0] = np.nan
    return a


@dataclass(frozen=True)
class Case:
    id: str
    damage: Callable[[Path], None]
    names: tuple[str, ...]  # the error line names one of these and every one of ``also``
    model: str = "flat-field"
    also: tuple[str, ...] = ()


FLAT, AXES, MU = "flat_field.npz", "light_axes.txt", "light_anisotropy.txt"
CASES = [
    Case("truncated npz", _truncate, (FLAT,)),
    Case("not an archive", lambda ds: (ds / FLAT).write_bytes(np.ones(3).tobytes()), (FLAT,)),
    Case("one array, not an archive", _npy_instead, (FLAT,)),
    Case("forged gains header", _forged_gains, (FLAT,), also=("gains",)),
    Case("scalar gains", _flat(gains=np.array(1.0)), (FLAT,), also=("gains",)),
    Case("2-D gains", _flat(gains=lambda g: g[0]), (FLAT,), also=("gains",)),
    Case("empty gains axis", _flat(gains=lambda g: g[:, :0]), (FLAT,), also=("gains",)),
    Case("NaN gains", _flat(gains=_nan_row), (FLAT,), also=("gains",)),
    Case("zero gains", _flat(gains=lambda g: g * 0), (FLAT,), also=("gains",)),
    Case("huge gains", _flat(gains=lambda g: g * np.float32(1e30)), (FLAT,), also=("gains",)),
    Case("text gains", _flat(gains=lambda g: g.astype(str)), (FLAT,), also=("gains",)),
    Case("boolean gains", _flat(gains=lambda g: g > 0), (FLAT,), also=("gains",)),
    Case("gains for other lights", _flat(gains=lambda g: g[:5]), (FLAT,), also=("gains",)),
    Case("two-value height", _flat(height=np.array([1.0, 2.0])), (FLAT,), also=("height",)),
    Case("NaN height", _flat(height=np.array(np.nan)), (FLAT,), also=("height",)),
    Case("height above the LEDs", _flat(height=np.array(5000.0)), (FLAT,), also=("height",)),
    Case("empty x axis", _flat(x=np.zeros(0)), (FLAT,), also=("'x'",)),
    Case("NaN x axis", _flat(x=_nan_row), (FLAT,), also=("'x'",)),
    Case("x axis reversed", _flat(x=lambda x: x[::-1].copy()), (FLAT,), also=("'x'",)),
    Case("short y axis", _flat(y=lambda y: y[:2]), (FLAT,), also=("'y'",)),
    Case("complex y axis", _flat(y=lambda y: y + 1j), (FLAT,), also=("'y'",)),
    Case("no positions", _flat(positions=None), (FLAT,), also=("positions",)),
    Case("infinite position", _flat(positions=lambda p: p * np.inf), (FLAT,),
         also=("positions",)),
    Case("position partly NaN", _flat(positions=_partly_nan), (FLAT,), also=("positions",)),
    Case("NaN axis", _text(AXES, "nan nan nan\n" * N), (AXES,), "beam"),
    Case("empty axes", _text(AXES, ""), (AXES,), "beam"),
    Case("axes pointing up", _text(AXES, "0 0 1\n" * N), (AXES,), "beam"),
    Case("zero axis", _text(AXES, "0 0 0\n" * N), (AXES,), "beam"),
    Case("NaN exponent", _text(MU, "nan\n" * N), (MU,), "beam"),
    Case("empty exponents", _text(MU, "# none\n"), (MU,), "beam"),
    Case("huge exponent", _text(MU, "1e308\n" * N), (MU,), "beam"),
    Case("huge LED position", _text("light_positions.txt", "1e308 1e308 1e308\n" * N),
         ("light_positions.txt",), "isotropic"),
    Case("LEDs under the outline", _text("object_outline.txt", "5000\n"),
         ("light_positions.txt",), "isotropic", also=("object_outline.txt",)),
    Case("huge intensity", _text("light_intensities.txt", "1e308\n" * N),
         ("light_intensities.txt",), "isotropic"),
]


# Run by `make test` (one or two per file and array: the cases first); the rest with
# `-m slow` (`make test-slow`), as in the sweeps.
CI_CASES = {
    "truncated npz", "forged gains header", "scalar gains", "empty gains axis", "NaN gains",
    "two-value height", "height above the LEDs", "empty x axis", "complex y axis",
    "infinite position", "NaN axis", "axes pointing up", "huge exponent", "huge LED position",
    "LEDs under the outline", "huge intensity",
}


def _params() -> list:
    assert CI_CASES <= {c.id for c in CASES}
    return [pytest.param(c, id=c.id, marks=() if c.id in CI_CASES else pytest.mark.slow)
            for c in CASES]


@dataclass
class Outcome:
    result: Result
    before: dict
    after: dict
    leftovers: list[str]


def _run_case(case: Case, folder: Path, near: Path) -> Outcome:
    ds = folder / "ds"
    shutil.copytree(near, ds)
    case.damage(ds)
    before = snapshot(folder)
    result = run(["reconstruct", str(ds), "--led-model", case.model, "--out", str(folder / "r")],
                 folder, folder.parent / "home")
    return Outcome(result, before, snapshot(folder), temporary_leftovers(folder.parent / "home"))


@pytest.fixture(scope="session")
def outcomes(request, near, tmp_path_factory) -> dict[str, Outcome]:
    """Every selected case at once, a few processes side by side (they mostly import)."""
    chosen = [
        item.callspec.params["case"]
        for item in request.session.items
        if getattr(item, "originalname", "") == "test_damaged_led_model_file_is_one_line_naming_it"
        and not item.get_closest_marker("skip")
    ]
    folders = []
    for case in chosen:
        root = tmp_path_factory.mktemp("led-case")
        (root / "case").mkdir()
        folders.append(root / "case")
    with ThreadPoolExecutor(max_workers=4) as pool:
        done = list(pool.map(_run_case, chosen, folders, [near["near"]] * len(chosen)))
    return {c.id: o for c, o in zip(chosen, done, strict=True)}


@pytest.mark.parametrize("case", _params())
def test_damaged_led_model_file_is_one_line_naming_it(case: Case, outcomes) -> None:
    outcome = outcomes[case.id]
    line = assert_one_error_line(outcome.result, case.names)
    for word in case.also:
        assert word in line, line
    assert "light_vectors" not in line and "no pixel" not in line, line
    assert_quiet(outcome.result)
    assert outcome.after == outcome.before, "files created or changed"
    assert outcome.leftovers == []


def test_sound_led_model_files_reconstruct(near, tmp_path) -> None:
    """The undamaged files pass every check (the reference for the table above)."""
    result = run(["reconstruct", str(near["near"]), "--led-model", "flat-field", "--out",
                  str(tmp_path / "r")], tmp_path, tmp_path / "home")
    assert result.code == 0, result.stderr
    assert_quiet(result)


# --- the board of calibrate --flat-field -----------------------------------------------------


@pytest.mark.parametrize(
    "board", ["5000", "80", pytest.param("1e308", marks=pytest.mark.slow),
              pytest.param("-1e6", marks=pytest.mark.slow)],
)
def test_board_not_below_every_led_names_the_option(board, near, tmp_path) -> None:
    """A board above some LED (the LEDs sit 65-145 px up) or absurdly far below them."""
    ds = tmp_path / "case" / "ds"
    shutil.copytree(near["near"], ds)
    line = refused(["calibrate", str(ds), *SPHERES, "--object", "table", "--flat-field",
                    str(near["board"]), f"--board={board}"], ds.parent, tmp_path / "home",
                   ("--board",))
    assert "no lit pixels" not in line and "board plane" in line, line


# --- an earlier result holding the user's files ------------------------------------------------


@pytest.fixture(scope="session")
def earlier(tmp_path_factory) -> dict[str, Path]:
    """A 16x16 dataset and its result, made once."""
    root = tmp_path_factory.mktemp("earlier")
    for args in (["simulate", str(root / "ds"), "--size", "16", "--lights", "8"],
                 ["reconstruct", str(root / "ds"), "--out", str(root / "result")]):
        result = run(args, root, root / "home")
        assert result.code == 0, result.stderr
    return {"ds": root / "ds", "result": root / "result"}


def _notes(result: Path) -> str:
    (result / "notes.txt").write_text("what I did to the object\n")
    return "notes.txt"


def _folder(result: Path) -> str:
    (result / "extra").mkdir()
    (result / "extra" / "photo.jpg").write_bytes(b"\xff\xd8")
    return "extra"


def _hidden(result: Path) -> str:
    (result / ".my-notes").write_text("x")
    return ".my-notes"


@pytest.mark.parametrize("add", [_notes, _folder, _hidden], ids=["notes", "folder", "hidden"])
def test_earlier_result_with_user_files_is_refused_naming_them(add, earlier, tmp_path) -> None:
    out = tmp_path / "case" / "result"
    shutil.copytree(earlier["result"], out)
    name = add(out)
    refused(["reconstruct", str(earlier["ds"]), "--out", str(out)], out.parent, tmp_path / "home",
            (str(out / name),))


def test_earlier_result_with_its_depth_files_is_replaced(earlier, tmp_path) -> None:
    """What ps-lab wrote there (the result, then integrate's depth files) may be replaced."""
    out = tmp_path / "result"
    shutil.copytree(earlier["result"], out)
    for args in (["integrate", str(out)], ["reconstruct", str(earlier["ds"]), "--out", str(out)]):
        result = run(args, tmp_path, tmp_path / "home")
        assert result.code == 0, result.stderr
        assert_quiet(result)
    assert not (out / "mesh.ply").exists() and (out / "normals.npy").is_file()


def test_frames_that_are_not_a_board_are_refused(near, tmp_path) -> None:
    """Seeded noise in place of the board frames: the beam model cannot fit them."""
    board = tmp_path / "noise"
    board.mkdir()
    rng = np.random.default_rng(5)
    for frame in sorted(near["board"].glob("*.png")):
        shape = cv2.imread(str(frame), cv2.IMREAD_UNCHANGED).shape
        cv2.imwrite(str(board / frame.name), rng.integers(0, 65535, shape).astype(np.uint16))
    ds = tmp_path / "case" / "ds"
    shutil.copytree(near["near"], ds)
    line = refused(["calibrate", str(ds), *SPHERES, "--object", "table", "--flat-field",
                    str(board)], ds.parent, tmp_path / "home", (str(board),))
    assert "--flat-field" in line and "not a flat board" in line, line


# --- bad input: rig files ``capture`` cannot use (the table's engine: tests/helpers/bad_input.py)


BAD_INPUT = CaseTable()
case = BAD_INPUT.case


@case("x-rig-not-utf8", ("small.toml",))
def _(w):
    rig = w.copy("rig") / "small.toml"
    rig.write_bytes(rig.read_bytes() + b"\n# caf\xe9\n")
    return ["capture", "--rig", str(rig), "--out", str(w.root / "out"), "-q"]


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


#: The cases CI runs; ``pytest -m slow`` runs every case of the table.
BAD_INPUT_CI = {
    "x-rig-exposure-nan",
    "x-rig-unknown-key",
}
test_bad_input = BAD_INPUT.test(BAD_INPUT_CI)
