"""The hostile sweeps' runner: ``ps-lab`` as a user runs it, and the README's failure promise.

Every case runs a real subprocess of the ``ps-lab`` entry point next to the running interpreter
(or ``$PS_LAB_EXE``) with ``TMPDIR`` and the cache inside the case's home, so that a temporary
file left behind is seen (:func:`temporary_leftovers`). The promise (README, "Failure
behaviour"): exit code 2, exactly one line on stderr, starting with ``error:``, naming the
user's file or option, no traceback and no numpy warning (:func:`assert_one_error_line`),
nothing created or changed in the case's folder (:func:`snapshot`).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

PS_LAB = os.environ.get("PS_LAB_EXE") or str(Path(sys.executable).with_name("ps-lab"))
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
#: What must never reach a user's terminal, on success or failure.
NOISE = ("Traceback", "RuntimeWarning", "DeprecationWarning", "UserWarning", "internal error")


@dataclass
class Result:
    code: int
    stdout: str
    stderr: str
    max_rss: int  # bytes

    @property
    def lines(self) -> list[str]:
        return [line for line in ANSI.sub("", self.stderr).splitlines() if line.strip()]


def environment(home: Path) -> dict[str, str]:
    """The caller's environment with colour off, 100 columns, cache and ``TMPDIR`` in ``home``."""
    env = {k: v for k, v in os.environ.items() if k not in ("FORCE_COLOR", "PY_COLORS")}
    (home / "tmp").mkdir(parents=True, exist_ok=True)
    env.update(
        XDG_CACHE_HOME=str(home / "cache"), COLUMNS="100", NO_COLOR="1", TMPDIR=str(home / "tmp")
    )
    return env


def start(args: list[str], cwd: Path, home: Path, prefix: tuple[str, ...] = ()):
    """Start ``ps-lab args`` with stdout/stderr to files (so that wait4 gives its rusage).

    ``home`` (made if missing) holds those files, the cache and ``TMPDIR``.
    """
    home.mkdir(parents=True, exist_ok=True)
    out, err = home / "stdout.txt", home / "stderr.txt"
    with out.open("wb") as o, err.open("wb") as e:
        proc = subprocess.Popen(
            [*prefix, PS_LAB, *args], cwd=cwd, stdout=o, stderr=e, stdin=subprocess.DEVNULL,
            env=environment(home),
        )  # fmt: skip
    return proc, out, err


def finish(proc: subprocess.Popen, out: Path, err: Path, timeout: float = 120) -> Result:
    deadline = time.monotonic() + timeout
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            break
        if time.monotonic() > deadline:
            proc.kill()
            pid, status, usage = os.wait4(proc.pid, 0)
            break
        time.sleep(0.02)
    code = os.waitstatus_to_exitcode(status)
    proc.returncode = code
    return Result(
        code, out.read_text(errors="replace"), err.read_text(errors="replace"),
        usage.ru_maxrss * 1024,
    )  # fmt: skip


def run(
    args: list[str], cwd: Path, home: Path, timeout: float = 120, prefix: tuple[str, ...] = ()
) -> Result:
    proc, out, err = start(args, cwd, home, prefix)
    return finish(proc, out, err, timeout)


def temporary_leftovers(home: Path) -> list[str]:
    return sorted(p.name for p in (home / "tmp").iterdir()) if (home / "tmp").is_dir() else []


def snapshot(folder: Path) -> dict[str, tuple]:
    """Names, kinds, sizes and mtimes of everything under ``folder`` (links not followed)."""
    entries: dict[str, tuple] = {}
    for dirpath, dirnames, filenames in os.walk(folder, followlinks=False):
        for name in dirnames + filenames:
            path = Path(dirpath, name)
            st = path.lstat()
            kind = "d" if path.is_dir() and not path.is_symlink() else "f"
            entries[str(path.relative_to(folder))] = (
                (kind,) if kind == "d" else (kind, st.st_size, st.st_mtime_ns)
            )
    return entries


def assert_quiet(result: Result) -> None:
    """No traceback, internal error or Python warning on stderr, whatever the exit code."""
    text = ANSI.sub("", result.stderr)
    for word in NOISE:
        assert word not in text, f"{word!r} reached the terminal:\n{text}"


def assert_one_error_line(result: Result, names: tuple[str, ...], code: int = 2) -> str:
    text = ANSI.sub("", result.stderr)
    assert "Traceback" not in text, text
    assert result.code == code, f"exit {result.code}, stderr:\n{text}"
    assert len(result.lines) == 1, f"expected one line on stderr, got:\n{text}"
    line = result.lines[0]
    assert line.startswith("error:"), line
    assert any(name in line for name in names), f"{line!r} names none of {names}"
    return line


def refused(
    args: list[str], cwd: Path, home: Path, names: tuple[str, ...], watch: Path | None = None,
    prefix: tuple[str, ...] = (),
) -> str:
    """Run ``ps-lab args`` (after ``prefix``, e.g. :func:`tmpfs_prefix`) and check the whole
    failure promise; return the ``error:`` line.

    Exit 2 with one ``error:`` line naming one of ``names`` (:func:`assert_one_error_line`),
    nothing noisy (:func:`assert_quiet`), nothing created or changed under ``watch`` (default
    ``cwd``) and no temporary file left in ``home``.
    """
    folder = cwd if watch is None else watch
    before = snapshot(folder)
    result = run(args, cwd, home, prefix=prefix)
    line = assert_one_error_line(result, names)
    assert_quiet(result)
    assert snapshot(folder) == before, "files created or changed"
    assert not temporary_leftovers(home), "temporary files left behind"
    return line


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def wait_until(predicate: Callable[[], bool], proc: subprocess.Popen, timeout: float = 90) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert _alive(proc.pid), "the command ended before the signal could be sent"
        assert time.monotonic() < deadline, "timed out waiting for the command to get going"
        time.sleep(0.005)


def tmpfs_prefix(mountpoint: Path, options: str = "rw") -> tuple[str, ...] | None:
    """``unshare`` arguments that run a command with a 256 KiB tmpfs on ``mountpoint`` mounted
    with ``options`` (``"ro"``: a read-only disk); None where ``unshare -rm`` is not allowed."""
    unshare = shutil.which("unshare")
    if unshare is None:
        return None
    mountpoint.mkdir(exist_ok=True)
    script = f'mount -t tmpfs -o size=256k,{options} tmpfs "$0" && exec "$@"'
    probe = subprocess.run(
        [unshare, "-rm", "sh", "-c", script, str(mountpoint), "true"], capture_output=True,
        check=False,
    )
    if probe.returncode != 0:
        return None
    return (unshare, "-rm", "sh", "-c", script, str(mountpoint))


def run_on_tmpfs(
    prefix: tuple[str, ...], mount: Path, args: list[str], home: Path, leave: int | None = None,
    timeout: float = 300,
) -> tuple[Result, list[str], list[str]]:
    """Run ``ps-lab args`` inside ``prefix`` (:func:`tmpfs_prefix` on ``mount``), first filling
    the tmpfs (a file ``filler``) to all but ``leave`` bytes unless ``leave`` is None.

    Returns the run's result (its stderr and exit code) and the paths under ``mount`` (the
    filler's included) before and after the run; a file in ``home`` carries them out.
    """
    listing = home / "tmpfs-listing.json"
    script = (
        "import json, os, subprocess\n"
        f"mount = {str(mount)!r}\n"
        f"if {leave is not None}:\n"
        "    space = os.statvfs(mount)\n"
        "    with open(os.path.join(mount, 'filler'), 'wb') as filler:\n"
        f"        filler.write(bytes(max(0, space.f_bavail * space.f_frsize - {leave or 0})))\n"
        "def tree():\n"
        "    return sorted(os.path.relpath(os.path.join(d, n), mount) for d, ds, fs in "
        "os.walk(mount) for n in ds + fs)\n"
        "before = tree()\n"
        f"done = subprocess.run([{PS_LAB!r}, *{args!r}], capture_output=True)\n"
        "json.dump({'before': before, 'after': tree(), 'code': done.returncode, "
        f"'stderr': done.stderr.decode('utf-8', 'replace')}}, open({str(listing)!r}, 'w'))\n"
    )
    finished = subprocess.run([*prefix, sys.executable, "-c", script], env=environment(home),
                              capture_output=True, timeout=timeout, check=False)
    assert finished.returncode == 0, finished.stderr.decode(errors="replace")
    record = json.loads(listing.read_text())
    return Result(record["code"], "", record["stderr"], 0), record["before"], record["after"]
