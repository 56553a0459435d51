"""``ps-lab reconstruct``'s options and output folder, wrong, and its signals.

Options that reach the maths unchecked (``--shadow-threshold nan``, ``--memory-budget 0``) or that
typer refuses, ``--out`` onto a file, the dataset or a read-only folder, names that are not UTF-8
and links; SIGTERM/SIGHUP/SIGINT and SIGKILL in the middle of a solve. The promise (README,
"Failure behaviour"): exit 2 (130 for a signal), one ``error:`` line, nothing created or changed.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers.bad_input import (
    NOT_UTF8,
    CaseTable,
    Workspace,
    ds_name,
    equals,
    finish,
    run,
    staging_folders,
    succeeded,
)
from helpers.hostile import Result, assert_one_error_line, snapshot, start, wait_until

CASES = CaseTable()
case = CASES.case
option_case = CASES.option_case


@case("g1-shadow-threshold-nan", ("--shadow-threshold",))
def _(w):
    return ["reconstruct", str(w.png()), "--shadow-threshold", "nan"]


@case("g1-shadow-threshold-inf", ("--shadow-threshold",))
def _(w):
    return ["reconstruct", str(w.png()), "--shadow-threshold", "inf"]


@case("g1-shadow-threshold-above-every-value", lambda w: (str(w.ds), "--shadow-threshold"))
def _(w):
    return ["reconstruct", str(w.png()), "--shadow-threshold", "50"]


for _value, _label in (
    ("0", "zero"),
    ("-1GB", "negative"),
    ("nan", "nan"),
    ("inf", "inf"),
    ("lots", "word"),
    ("0.0000001", "rounds-to-zero"),
):


    option_case(f"g2-memory-budget-{_label}", ["reconstruct"], "--memory-budget", _value)


# Group 5: typer's own rejections as one line ---------------------------------------------------


@case(
    "g5-unknown-method",
    ("--method",),
    check=lambda w, r, line: equals(
        line, "error: --method: 'foo' is not one of auto, ls, l1, sbl, plls, plsbl, rpca"
    ),
)
def _(w):
    return ["reconstruct", str(w.png()), "--method", "foo"]


option_case("g5-unknown-channel", ["reconstruct"], "--channel", "x")
option_case("g5-threads-negative", ["reconstruct"], "--threads", "-1")
option_case("g5-threads-zero", ["reconstruct"], "--threads", "0")
option_case("g5-threads-word", ["reconstruct"], "--threads", "many")
option_case("g5-refine-lights-negative", ["reconstruct"], "--refine-lights", "-1")
option_case("g5-shadow-threshold-word", ["reconstruct"], "--shadow-threshold", "dark")


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


@case("x-run-not-calibrated", ("calibrate", "light_directions.txt"))
def _(w):
    return ["reconstruct", str(w.copy("run"))]


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


@case("s3-reconstruct-out-not-utf8", (), code=0, check=succeeded)
def _(w):
    return ["reconstruct", str(w.copy("png")), "--out", str(w.root / NOT_UTF8), "--depth",
            "poisson"]


# s4: links and read-only results ----------------------------------------------------------------


def _link_followed(w: Workspace, result: Result, line: str | None) -> None:
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


@case("s5-reconstruct-depth-two-diagonal-pixels", ("--depth",))
def _(w):
    ds = w.copy("png")
    mask = np.zeros((16, 16), np.uint8)
    mask[7, 7] = mask[8, 8] = 255
    cv2.imwrite(str(ds / "mask.png"), mask)
    return ["reconstruct", str(ds), "--method", "ls", "--depth", "poisson"]


#: The cases CI runs; ``pytest -m slow`` runs every case of the table.
CI_CASES = {
    "g1-shadow-threshold-above-every-value",
    "g1-shadow-threshold-nan",
    "g2-memory-budget-nan",
    "g2-memory-budget-word",
    "g5-refine-lights-negative",
    "g5-threads-negative",
    "g5-unknown-channel",
    "g5-unknown-method",
    "s3-reconstruct-out-not-utf8",
    "s4-earlier-result-read-only",
    "s4-out-is-a-link-to-an-earlier-result",
    "s5-reconstruct-depth-two-diagonal-pixels",
    "x-out-is-a-file",
    "x-out-is-the-dataset",
}
test_bad_input = CASES.test(CI_CASES)
