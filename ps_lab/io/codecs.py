"""OpenCV's image codecs for any path, without its C libraries' own stderr lines.

OpenCV's file functions take a path as UTF-8 text (a name with a byte that is not UTF-8 crashes
them) and libpng prints ``libpng error: ...`` on a damaged stream before OpenCV returns None:
:func:`imread` and :func:`imwrite` do the file I/O in Python and the coding in memory, and
:func:`decode_image` captures the decoder's lines for the caller's one error line.
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

__all__ = ["decode_image", "decoder_said", "imread", "imwrite", "native_stderr_captured"]

_NATIVE_STDERR = threading.Lock()


@contextmanager
def native_stderr_captured(fds: tuple[int, ...] = (2,)) -> Iterator[list[str]]:
    """Capture what C libraries print on the process's stderr (fd 2) in the block.

    libpng prints its own ``libpng error: ...`` line on a damaged stream before OpenCV returns
    None; the lines are yielded (filled in at the end of the block) for the caller's one error
    line instead. ``fds=(1, 2)`` also captures stdout (OpenEXR's binding prints warnings there).
    One block at a time per process (a lock).
    """
    lines: list[str] = []
    with _NATIVE_STDERR:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError, AttributeError):
                pass
        saved: dict[int, int] = {}
        try:
            for fd in fds:
                saved[fd] = os.dup(fd)
        except OSError:  # no such descriptor: capture what can be
            pass
        with tempfile.TemporaryFile() as sink:
            for fd in saved:
                os.dup2(sink.fileno(), fd)
            try:
                yield lines
            finally:
                for stream in (sys.stdout, sys.stderr):  # what Python code printed meanwhile
                    try:
                        stream.flush()
                    except (OSError, ValueError, AttributeError):
                        pass
                for fd, copy in saved.items():
                    os.dup2(copy, fd)
                    os.close(copy)
                sink.seek(0)
                text = sink.read(4096).decode("utf-8", "replace")
                lines.extend(line.strip() for line in text.splitlines() if line.strip())


def decoder_said(messages: list[str]) -> str:
    """The decoder's captured lines as a tail for an error line (``" (libpng: ...)"``), or ''."""
    said = [re.sub(r"^lib(\w+) error: ", r"lib\1: ", m) for m in messages]
    return f" ({'; '.join(said)})" if said else ""


def decode_image(
    raw: bytes | np.ndarray, flags: int = cv2.IMREAD_UNCHANGED
) -> tuple[np.ndarray | None, list[str]]:
    """``cv2.imdecode`` with the decoder's own stderr lines captured: ``(array or None, lines)``."""
    with native_stderr_captured() as messages:
        array = cv2.imdecode(np.frombuffer(raw, np.uint8), flags)
    return array, messages


def imread(path: Path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray | None:
    """``cv2.imread`` for any path: read by Python, decoded from memory (None when not an image).

    OpenCV's own file functions take the path as UTF-8 text; a name with a byte that is not
    UTF-8 crashes them (SIGSEGV). Raises ``OSError`` when the file cannot be read.
    """
    return decode_image(Path(path).read_bytes(), flags)[0]


def imwrite(path: Path, picture: np.ndarray) -> bool:
    """``cv2.imwrite`` for any path: encoded in memory (format from the suffix), written by Python.

    Returns False when OpenCV cannot encode ``picture`` in that format; raises ``OSError`` when
    the file cannot be written (a full disk among them).
    """
    path = Path(path)
    ok, encoded = cv2.imencode(path.suffix or ".png", np.asarray(picture))
    if not ok:
        return False
    with open(path, "wb") as handle:
        handle.write(encoded.tobytes())
    return True
