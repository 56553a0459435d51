"""The one place that writes files safely: atomic files, staged folders, sha256, JSON-safe values.

- :func:`write_bytes_atomic` / :func:`write_json_atomic`: a file holds either its old or its new
  content, never a part (temporary sibling, fsync, rename, fsync of the folder);
  :func:`publish_file` does the last steps for a file a device wrote under a temporary name;
- :func:`staged_folder`: a whole output folder built in a hidden sibling and renamed into place
  only when complete (``ps-lab reconstruct``, ``ps-lab simulate``);
- :func:`staged_files`: files built in a hidden sub-folder, then each renamed into an existing
  folder (``ps-lab calibrate`` writes into a capture run); :func:`staging_folder` is that
  sub-folder alone, for writers that move their files themselves (``ps-lab relight``);
- :func:`sha256` of a file, and :func:`json_safe` values for ``json.dumps``.

Staging folders carry the writer's process id (``.OUT.partial-PID``); a run killed by SIGKILL
leaves one behind, and the next run writing to the same place removes those whose process is gone
(:func:`remove_stale_staging`).

A full disk is an error, never a crash: :func:`preallocate` reserves a file's bytes before it is
written (a memory-mapped page of a sparse file on a full filesystem kills the process with
SIGBUS), and both staging helpers turn "no space left" into one :class:`PsLabError` naming the
output, after removing what they staged. ``--out`` given as a link to a folder writes into the
folder it points to; a read-only earlier result is refused before any work.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import re
import shutil
import stat
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
            remove_tree(entry)
            log.info("removed %s, left by process %s (killed or crashed)", entry, match.group(1))
            removed.append(entry)
    return removed


def utf8_path(path: Path) -> bool:
    """Whether ``path``'s bytes are UTF-8 (what C++ libraries taking a name as text need)."""
    try:
        os.fsencode(path).decode("utf-8")
    except (UnicodeError, ValueError):
        return False
    return True


def remove_tree(path: Path) -> None:
    """Remove ``path`` (a folder, a file or a link, never what a link points to), best effort.

    Folders of ours made read-only (an earlier result the user locked, then replaced) are made
    writable first, so that nothing hidden stays behind.
    """
    path = Path(path)
    if path.is_symlink() or not path.is_dir():
        try:
            path.unlink()
        except OSError:
            pass
        return

    def unlock(function, name, excinfo) -> None:
        parent = os.path.dirname(name)
        try:
            os.chmod(parent, os.stat(parent).st_mode | stat.S_IWUSR | stat.S_IXUSR)
            if function is os.rmdir or function is os.unlink:
                function(name)
            elif os.path.isdir(name) and not os.path.islink(name):
                os.chmod(name, os.stat(name).st_mode | stat.S_IRWXU)
                shutil.rmtree(name, ignore_errors=True)
        except OSError:
            pass

    shutil.rmtree(path, onerror=unlock)
    if path.exists():
        shutil.rmtree(path, ignore_errors=True)


#: numpy's ``tofile`` (used by tifffile) reports a full disk as a short write, without errno.
_SHORT_WRITE = re.compile(r"\d+ requested and \d+ written")
#: ``errno`` values of a full disk or an exhausted quota.
NO_SPACE = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})


def no_space_error(exc: BaseException | None) -> OSError | None:
    """The "disk full" ``OSError`` behind ``exc`` (itself, or what it was raised from), or None.

    Writers re-raise an ``OSError`` as their own error naming the file; the original stays as
    the exception's context, which is looked at here.
    """
    seen = 0
    while exc is not None and seen < 8:
        if isinstance(exc, OSError) and (
            exc.errno in NO_SPACE or (exc.errno is None and _SHORT_WRITE.search(str(exc)))
        ):
            return exc
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return None


def is_no_space(exc: BaseException) -> bool:
    """Whether ``exc`` says the disk (or the user's quota, or the file size limit) is full."""
    return no_space_error(exc) is not None


def preallocate(handle: Any, offset: int, length: int) -> None:
    """Reserve ``length`` bytes of an open file from ``offset`` (``posix_fallocate``).

    A full disk raises ``OSError(ENOSPC)`` here, where it can be reported, instead of SIGBUS at
    the first write through a memory map. Where the call is missing or the filesystem does not
    support it, the file is extended to its size as before.
    """
    fd = handle if isinstance(handle, int) else handle.fileno()
    if length <= 0:
        return
    try:
        os.posix_fallocate(fd, offset, length)
    except AttributeError:  # pragma: no cover - not on this platform
        os.ftruncate(fd, max(os.fstat(fd).st_size, offset + length))
    except OSError as exc:
        if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
            raise
        os.ftruncate(fd, max(os.fstat(fd).st_size, offset + length))


def fsync_path(path: Path) -> None:
    """fsync the file or folder ``path`` (a folder: the names in it)."""
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
    fsync_path(path.parent)


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
    fsync_path(Path(final).parent)


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


def output_target(out: Path, error: type[PsLabError] = PsLabError) -> Path:
    """The folder an output ``out`` names: itself, or where a link to a folder points.

    Raises ``error`` for a link that points nowhere or not to a folder.
    """
    out = Path(out)
    if not out.is_symlink():
        return out
    target = Path(os.path.realpath(out))
    if not target.is_dir():
        raise error(
            f"{out}: is a link to {target}, which is not a folder: remove the link or choose "
            "another output folder"
        )
    return target


def check_writable_folder(out: Path, error: type[PsLabError] = PsLabError) -> None:
    """Refuse an existing folder ``out`` whose entries cannot be removed (read-only).

    Replacing a read-only earlier result would leave it behind, hidden; it is refused instead.
    """
    out = Path(out)
    if out.is_dir() and not os.access(out, os.W_OK | os.X_OK):
        raise error(
            f"{out}: the folder is read-only, so the earlier result there cannot be replaced "
            "(make it writable, or choose another output folder)"
        )


def _no_space_line(out: Path, exc: OSError | None) -> str:
    reason = os.strerror(exc.errno) if exc is not None and exc.errno else "No space left on device"
    remedy = (
        "raise the file size limit (ulimit -f)"
        if exc is not None and exc.errno == errno.EFBIG
        else "free some space"
    )
    return (
        f"{out}: cannot write, {reason[:1].lower() + reason[1:]}; no output written (an earlier "
        f"result there is untouched): {remedy} and run again"
    )


def allocate_npy(path: Path, shape: tuple[int, ...], dtype: Any = np.float32) -> int:
    """Create the ``.npy`` file ``path`` of zeros, its bytes reserved on disk; return its offset.

    The array's rows are then written with :func:`write_npy_rows` (plain writes: a full disk is an
    ``OSError``, never SIGBUS as with a memory map of a sparse file).
    """
    dtype = np.dtype(dtype)
    header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False,
              "shape": tuple(int(n) for n in shape)}
    with open(path, "wb") as handle:
        np.lib.format.write_array_header_1_0(handle, header)
        offset = handle.tell()
        handle.flush()
        preallocate(handle, offset, int(np.prod(shape, dtype=np.int64)) * dtype.itemsize)
    return offset


def write_npy_rows(path: Path, offset: int, start: int, block: np.ndarray) -> None:
    """Write ``block`` (C order) as rows ``start, start + 1, ...`` of the array in ``path``."""
    data = np.ascontiguousarray(block)
    row_bytes = data[0].nbytes if len(data) else 0
    view = memoryview(data.reshape(-1).view(np.uint8))
    fd = os.open(path, os.O_WRONLY)
    try:
        position = offset + start * row_bytes
        while view:
            written = os.pwrite(fd, view, position)
            view, position = view[written:], position + written
    finally:
        os.close(fd)


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
    when the folder cannot be created, when ``out`` is a read-only folder, and for a full disk.
    ``out`` given as a link to a folder is that folder (the link stays, pointing at the new one).
    """
    out = output_target(out, error)
    if check is not None:
        check(out)
    check_writable_folder(out, error)
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
        remove_created(created)
        if is_no_space(exc):
            raise error(_no_space_line(out, no_space_error(exc))) from None
        raise error(f"{out}: cannot create the output folder ({exc.strerror})") from None
    try:
        yield stage
        if check is not None:
            check(out)  # nobody wrote there meanwhile
        retired = out.parent / f".{out.name}.old-{os.getpid()}"
        if out.exists() or out.is_symlink():
            out.rename(retired)
        try:
            stage.rename(out)
        except BaseException:
            if retired.exists() or retired.is_symlink():
                retired.rename(out)  # the earlier result back in place
            raise
        remove_tree(retired)
    except BaseException as exc:
        remove_tree(stage)
        remove_created(created)
        if is_no_space(exc):
            raise error(_no_space_line(out, no_space_error(exc))) from None
        raise


def missing_folders(folder: Path) -> list[Path]:
    """``folder`` and its parents that do not exist (no link either), innermost first: what
    creating ``folder`` creates, for :func:`remove_created` to remove again."""
    created: list[Path] = []
    while not folder.exists() and not folder.is_symlink():
        created.append(folder)
        folder = folder.parent
    return created


def remove_created(created: list[Path]) -> None:
    """Remove the (empty) parent folders a staging helper created (:func:`missing_folders`), innermost first."""
    for folder in created:
        try:
            folder.rmdir()
        except OSError:
            break


@contextmanager
def staged_files(
    out: Path,
    *,
    prefix: str = ".staged-",
    check: Callable[[Path], None] | None = None,
    error: type[PsLabError] | None = None,
) -> Iterator[Path]:
    """Yield a hidden sub-folder of ``out`` whose files move into ``out`` when the block succeeds.

    ``out`` is created if needed; every file is fsynced, then renamed into ``out``. The sub-folder
    (``PREFIX``, ``partial-`` and the process id) is removed in every case, so a failure leaves
    ``out`` as it was, and ``out`` itself (with any parent) is removed again when this created it;
    one left by a killed process is removed here. ``check(out)``, when given, runs before anything
    is created and again just before the files move (it raises when they may not). A full disk
    raises ``error`` when given, naming ``out``; other ``OSError`` come as they are.
    """
    out = Path(out)
    if check is not None:
        check(out)
    try:
        with staging_folder(out, f"{prefix}partial-") as staging:
            yield staging
            if check is not None:
                check(out)
            files = sorted(p for p in staging.iterdir() if p.is_file())
            for path in files:
                with open(path, "rb") as fh:
                    os.fsync(fh.fileno())
            for path in files:
                os.replace(path, out / path.name)
    except BaseException as exc:
        if error is not None and is_no_space(exc):
            raise error(_no_space_line(out, no_space_error(exc))) from None
        raise


@contextmanager
def staging_folder(parent: Path, stem: str) -> Iterator[Path]:
    """Yield a new empty hidden folder ``parent / (stem + process id)``, removed in every case.

    ``parent`` is created if needed, and removed again (with any parent this created) when the
    block fails; staging folders of ``stem`` left by processes that are gone are removed first.
    """
    created = missing_folders(parent)
    staging = parent / f"{stem}{os.getpid()}"
    try:
        parent.mkdir(parents=True, exist_ok=True)
        remove_stale_staging(parent, rf"{re.escape(stem)}(\d+)")
        if staging.exists():
            shutil.rmtree(staging)
        staging.mkdir()
        yield staging
    except BaseException:
        remove_tree(staging)
        remove_created(created)
        raise
    else:
        remove_tree(staging)
