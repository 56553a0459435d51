"""The one place that writes files safely: atomic files, staged folders, sha256, JSON-safe values.

- :func:`write_bytes_atomic` / :func:`write_json_atomic`: a file holds either its old or its new
  content, never a part (temporary sibling, fsync, rename, fsync of the folder);
  :func:`publish_file` does the last steps for a file a device wrote under a temporary name;
- :func:`staged_folder`: a whole output folder built in a hidden sibling and renamed into place
  only when complete (``ps-lab reconstruct``, ``ps-lab simulate``);
- :func:`staged_files`: files built in a hidden sub-folder, then each renamed into an existing
  folder (``ps-lab calibrate`` writes into a capture run);
- :func:`sha256` of a file, and :func:`json_safe` values for ``json.dumps``.

Staging folders carry the writer's process id (``.OUT.partial-PID``); a run killed by SIGKILL
leaves one behind, and the next run writing to the same place removes those whose process is gone
(:func:`remove_stale_staging`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from ps_lab.errors import PsLabError

#: Name prefix of a file being written by :func:`write_bytes_atomic`.
PARTIAL_PREFIX = ".partial-"

log = logging.getLogger(__name__)


def _process_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale_staging(folder: Path, pattern: str) -> list[Path]:
    r"""Remove the entries of ``folder`` named by ``pattern`` whose writing process is gone.

    Parameters
    ----------
    folder : Path
        Where the staging folders are.
    pattern : str
        Regular expression for a whole name, with one group capturing the process id, e.g.
        ``r"\.out\.(?:partial|old)-(\d+)"``.

    Returns
    -------
    list of Path
        What was removed. Entries of live processes (or of another user's) are left alone.

    """
    removed: list[Path] = []
    try:
        entries = list(Path(folder).iterdir())
    except OSError:
        return removed
    for entry in entries:
        match = re.fullmatch(pattern, entry.name)
        if match and not _process_alive(int(match.group(1))):
            shutil.rmtree(entry, ignore_errors=True)
            log.info("removed %s, left by process %s (killed or crashed)", entry, match.group(1))
            removed.append(entry)
    return removed


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_bytes_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that ``path`` holds either the old or the new content."""
    path = Path(path)
    tmp = path.with_name(PARTIAL_PREFIX + path.name)
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def publish_file(temp: Path, final: Path) -> None:
    """Give a complete file written under a temporary name its final name, durably.

    The file is fsynced, renamed over ``final`` and the folder fsynced: after a crash ``final``
    is either absent (or its old content) or complete.
    """
    fd = os.open(temp, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(temp, final)
    _fsync_dir(Path(final).parent)


def write_json_atomic(path: Path, obj: Any) -> None:
    """Write ``obj`` as JSON with :func:`write_bytes_atomic`."""
    write_bytes_atomic(path, (json.dumps(obj, indent=1) + "\n").encode("utf-8"))


def sha256(path: Path) -> str:
    """Hex SHA-256 of a file's content, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def json_safe(value: Any) -> Any:
    """Return ``value`` in a form ``json.dumps`` always accepts.

    Numpy scalars and arrays become Python values, non-finite floats None, paths strings and
    anything else unknown its ``repr``.
    """
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        return json_safe(value.item())
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    if isinstance(value, Path):
        return str(value)
    return repr(value)


@contextmanager
def staged_folder(
    out: Path,
    *,
    check: Callable[[Path], None] | None = None,
    error: type[PsLabError] = PsLabError,
) -> Iterator[Path]:
    """Yield an empty hidden folder that replaces ``out`` when the block succeeds.

    ``check(out)``, when given, runs first and again just before the rename (it raises when
    ``out`` may not be replaced). On any exception (Ctrl-C included) the hidden folder, and any
    parent folder created for it, are removed and ``out`` is left as it was. ``error`` is raised
    when the folder cannot be created.
    """
    out = Path(out)
    if check is not None:
        check(out)
    created: list[Path] = []
    parent = out.parent
    while not parent.exists():
        created.append(parent)
        parent = parent.parent
    remove_stale_staging(out.parent, rf"\.{re.escape(out.name)}\.(?:partial|old)-(\d+)")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        stage = out.parent / f".{out.name}.partial-{os.getpid()}"
        if stage.exists():
            shutil.rmtree(stage)
        stage.mkdir()
    except OSError as exc:
        raise error(f"{out}: cannot create the output folder ({exc.strerror})") from None
    try:
        yield stage
        if check is not None:
            check(out)  # nobody wrote there meanwhile
        retired = out.parent / f".{out.name}.old-{os.getpid()}"
        if out.exists():
            out.rename(retired)
        stage.rename(out)
        if retired.exists():
            shutil.rmtree(retired, ignore_errors=True)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        for folder in created:  # innermost first
            try:
                folder.rmdir()
            except OSError:
                break
        raise


@contextmanager
def staged_files(out: Path, *, prefix: str = ".staged-") -> Iterator[Path]:
    """Yield a hidden sub-folder of ``out`` whose files move into ``out`` when the block succeeds.

    ``out`` is created if needed; every file is fsynced, then renamed into ``out``. The sub-folder
    (``PREFIX``, ``partial-`` and the process id) is removed in every case, so a failure leaves
    ``out`` as it was; one left by a killed process is removed here. Raises ``OSError`` as it
    comes.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    remove_stale_staging(out, rf"{re.escape(prefix)}partial-(\d+)")
    staging = out / f"{prefix}partial-{os.getpid()}"
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir()
    try:
        yield staging
        files = sorted(p for p in staging.iterdir() if p.is_file())
        for path in files:
            with open(path, "rb") as fh:
                os.fsync(fh.fileno())
        for path in files:
            os.replace(path, out / path.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
