"""A full disk (a 256 KiB tmpfs in a private mount namespace): one line, nothing left behind.

``reconstruct``, ``calibrate`` and ``integrate`` writing onto a disk with 8 KiB free: exit 2, one
``error:`` line naming the folder and the space, the earlier result unchanged and no staging or
temporary file left. Skips where ``unshare -rm`` is not allowed.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.bad_input import Workspace, run
from helpers.hostile import (
    PS_LAB,
    Result,
    assert_one_error_line,
    environment,
    temporary_leftovers,
    tmpfs_prefix,
)


# --- a full disk: a 256 KiB tmpfs in a private mount namespace -----------------------------------


DISK_FILLERS = {
    # A 128 x 128 result (normals.npy alone is 192 KiB) after a 16 x 16 one that fits.
    "reconstruct": lambda w, full: ["reconstruct", str(w.root / "big"), "--out", str(full / "r")],
    "calibrate": lambda w, full: ["calibrate", str(w.root / "run"), "--out", str(full / "cal")],
    "integrate": lambda w, full: ["integrate", str(w.root / "bigresult"), "--out",
                                  str(full / "depth")],
}


@pytest.fixture(scope="session")
def big(templates, tmp_path_factory) -> dict[str, Path]:
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
def test_full_disk_is_one_line_and_leaves_nothing(command, templates, big, tmp_path) -> None:
    w = Workspace(tmp_path / "case", tmp_path / "home", {**templates, **big})
    w.root.mkdir()
    w.home.mkdir()
    full = w.root / "full"
    prefix = tmpfs_prefix(full)
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
