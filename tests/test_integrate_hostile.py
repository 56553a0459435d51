"""``ps-lab integrate`` into folders that are not its own, and on normals it cannot use.

It writes only into its own folders (a user's folder, a file, another result's metrics are
refused), refuses complex, NaN, back-facing or too sparse normals and a pickled albedo in one
line naming the file, and Ctrl-C leaves no new folder.
"""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from helpers.bad_input import (
    NOT_UTF8,
    CaseTable,
    Workspace,
    finish,
    lacks,
    succeeded,
)
from helpers.hostile import assert_one_error_line, snapshot, start, wait_until


CASES = CaseTable()
case = CASES.case


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


@case("s3-integrate-out-not-utf8", (), code=0, check=succeeded)
def _(w):
    return ["integrate", str(w.copy("result")), "--out", str(w.root / NOT_UTF8)]


# s5: what integrate cannot use, in one line naming it -------------------------------------------


def _result_with(w: Workspace, normals=None, albedo=None) -> Path:
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
      check=lambda w, r, line: lacks(r.lines[0], "normals.npy"))
def _(w):
    return ["integrate", str(_result_with(w, albedo=lambda a: np.array([{"a": 1}] * 4)))]


for _option, _value in (
    ("--focal-length", "1e300"),
    ("--focal-length", "1e-6"),
    ("--pixel-size", "1e300"),
):

    @case(f"s5-integrate{_option}-{_value}", (_option,))
    def _(w, option=_option, value=_value):
        return ["integrate", str(w.copy("result")), option, value, "--out", str(w.root / "new")]


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


#: The cases CI runs; ``pytest -m slow`` runs every case of the table.
CI_CASES = {
    "s1-integrate-into-a-user-folder",
    "s1-integrate-metrics-not-json",
    "s5-albedo-pickled",
    "s5-integrate--focal-length-1e300",
    "s5-integrate--pixel-size-1e300",
    "s5-mask-checkerboard",
    "s5-normals-back-facing",
    "s5-normals-complex",
}
test_bad_input = CASES.test(CI_CASES)
