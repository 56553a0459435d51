"""`ps-lab` in a new shell after `make demo`: the ~/.local/bin launcher (tools/launcher.sh)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tools" / "launcher.sh"
SYSTEM_PATH = "/usr/bin:/bin"


@pytest.fixture
def clone(tmp_path):
    """A home folder and a clone whose .venv/bin/ps-lab prints a marker."""
    home = tmp_path / "home"
    home.mkdir()
    target = tmp_path / "clone" / ".venv" / "bin" / "ps-lab"
    target.parent.mkdir(parents=True)
    target.write_text("#!/bin/sh\necho this-clone\n")
    target.chmod(0o755)
    return home, target


def launcher(action, home, target, path=SYSTEM_PATH):
    done = subprocess.run(
        ["sh", str(SCRIPT), action, str(target)],
        env={"HOME": str(home), "PATH": path},
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_link_makes_ps_lab_a_command_and_says_how_to_reach_it(clone):
    home, target = clone
    link = home / ".local" / "bin" / "ps-lab"
    out = launcher("link", home, target)
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert out.splitlines()[0] == f"linked {link} -> {target}"
    # Not on PATH yet (a shell started before the folder existed): the one line to type.
    assert 'export PATH="$HOME/.local/bin:$PATH"' in out.splitlines()[1]
    assert f"source {target.parent}/activate" in out.splitlines()[1]
    # In a shell that has it on PATH (a new login shell on Debian/Ubuntu), ps-lab is this clone's.
    path = f"{link.parent}:{SYSTEM_PATH}"
    assert launcher("check", home, target, path) == f"ps-lab: {link} -> {target}\n"
    ran = subprocess.run(["ps-lab"], env={"PATH": path}, capture_output=True, text=True)
    assert ran.stdout == "this-clone\n"
    # Again: nothing changes, one line.
    assert launcher("link", home, target, path) == f"ps-lab: {link} -> {target}\n"


@pytest.mark.parametrize("kind", ["file", "link to another clone"])
def test_another_ps_lab_is_left_alone(clone, tmp_path, kind):
    home, target = clone
    link = home / ".local" / "bin" / "ps-lab"
    link.parent.mkdir(parents=True)
    other = tmp_path / "other" / ".venv" / "bin" / "ps-lab"
    if kind == "file":
        link.write_text("#!/bin/sh\necho pip-user\n")
    else:
        link.symlink_to(other)
    before = link.read_text() if kind == "file" else os.readlink(link)
    out = launcher("link", home, target)
    assert (link.read_text() if kind == "file" else os.readlink(link)) == before
    assert f"{link} is another ps-lab" in out and "left as it is" in out
    assert f"source {target.parent}/activate" in out
    assert launcher("unlink", home, target) == ""  # `make clean` keeps it too
    assert link.exists() or link.is_symlink()


def test_unlink_removes_only_a_link_into_this_venv(clone):
    home, target = clone
    link = home / ".local" / "bin" / "ps-lab"
    launcher("link", home, target)
    out = launcher("unlink", home, target)
    assert not link.exists() and not link.is_symlink()
    assert out == f"removed {link} (it pointed into {target.parent.parent})\n"
    assert launcher("unlink", home, target) == ""


def test_the_makefile_links_on_install_checks_after_the_demo_and_unlinks_on_clean():
    rules = {}
    current = None
    for line in (ROOT / "Makefile").read_text().splitlines():
        if line and not line.startswith(("\t", "#", " ")) and ":" in line and "=" not in line:
            current = line.split(":")[0]
            rules[current] = []
        elif line.startswith("\t") and current:
            rules[current].append(line.strip())
    assert "@sh tools/launcher.sh link $(LAUNCHER)" in rules["$(STAMP)"]
    assert rules["demo"][-1] == "@sh tools/launcher.sh check $(LAUNCHER)"
    assert rules["clean"][0] == "@sh tools/launcher.sh unlink $(LAUNCHER)"
