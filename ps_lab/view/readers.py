"""The result folder's files read without trusting them: each is checked before it is decoded.

A result folder given to ``ps-lab view`` may be damaged or hostile: a FIFO or a device where a
file should be (opening it would wait for ever), a ``.npy`` header that claims more than the file
holds or an array of strings, a truncated PNG (libpng prints its own line on stderr), a
``metrics.json`` with ``NaN`` (not JSON to a browser). The readers here refuse each with a
:class:`DatasetError` that names the file:

- :func:`present`: whether an optional file exists; a folder, a FIFO, a device, a socket or a
  broken link in its place is refused, never opened.
- :func:`read_bytes`: opens with ``O_NONBLOCK`` (a FIFO swapped in after the check cannot block)
  and checks the open descriptor again (``fstat``: a regular file, under a size limit).
- :func:`read_array`: a ``.npy`` file whose header is checked (real numbers, the dimensions
  asked for, a size the file holds) before its data is read.
- :func:`read_grey_png`: a PNG whose chunk layout is checked before libpng runs, decoded with
  the decoder's own stderr lines captured.
- :func:`read_json`: a JSON object; ``NaN``, ``Infinity`` and numbers beyond float range read as
  None, so what the viewer passes on is always valid JSON.
"""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

from ps_lab.errors import DatasetError
from ps_lab.io.codecs import decode_image, decoder_said
from ps_lab.io.images import available_memory, png_layout_problem, read_npy_header

__all__ = ["open_regular", "present", "read_array", "read_bytes", "read_grey_png", "read_json"]

#: Largest ``metrics.json`` read (a ps-lab one is a few kB).
MAX_JSON_BYTES = 16 << 20

#: The dtype kinds a numeric layer may hold: bool, signed and unsigned integers, floats.
NUMERIC_KINDS = "biuf"


def _kind_of(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def present(path: Path, what: str) -> bool:
    """Whether the optional file ``path`` exists as a regular file (False when absent).

    Raises
    ------
    DatasetError
        Something other than a regular file is in its place (a folder, FIFO, device, socket),
        a link leads nowhere or loops, or a parent cannot be searched.
    """
    path = Path(path)
    try:
        mode = path.lstat().st_mode
    except FileNotFoundError:
        return False
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: cannot open {what} ({_reason(exc)})") from None
    if stat.S_ISLNK(mode):
        try:
            mode = path.stat().st_mode
        except FileNotFoundError:
            raise DatasetError(f"{path}: {what} is a broken link") from None
        except OSError as exc:
            raise DatasetError(f"{path}: cannot open {what} ({_reason(exc)})") from None
    if not stat.S_ISREG(mode):
        raise DatasetError(f"{path}: {what} is {_kind_of(mode)}, not a regular file")
    return True


def _reason(exc: BaseException) -> str:
    return getattr(exc, "strerror", None) or str(exc)


def _open_regular(path: Path, what: str, limit: int | None = None) -> tuple[int, int]:
    """Open ``path`` for reading without blocking; ``(fd, size)`` of a regular file."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    flags |= getattr(os, "O_NOCTTY", 0)
    try:
        fd = os.open(path, flags)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: cannot open {what} ({_reason(exc)})") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise DatasetError(f"{path}: {what} is {_kind_of(info.st_mode)}, not a regular file")
        if limit is not None and info.st_size > limit:
            raise DatasetError(
                f"{path}: {what} of {info.st_size} bytes is too large (at most {limit})"
            )
        if info.st_size == 0:
            raise DatasetError(f"{path}: {what} is empty (0 bytes)")
    except BaseException:
        os.close(fd)
        raise
    return fd, info.st_size


def open_regular(path: Path, what: str) -> BinaryIO:
    """``path`` open for binary reading, refused unless a regular file that is not empty."""
    fd, _ = _open_regular(path, what)
    try:
        os.set_blocking(fd, True)
    except OSError:
        pass
    return os.fdopen(fd, "rb", closefd=True)


def read_bytes(path: Path, what: str, limit: int | None = None) -> bytes:
    """The bytes of the regular file ``path`` (refused: not regular, empty, over ``limit``)."""
    fd, size = _open_regular(path, what, limit)
    try:
        with os.fdopen(fd, "rb", closefd=True) as stream:
            data = stream.read(size + 1 if limit is None else min(size, limit) + 1)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read {what} ({_reason(exc)})") from None
    if limit is not None and len(data) > limit:
        raise DatasetError(f"{path}: {what} is too large (at most {limit} bytes)")
    return data


def read_array(path: Path, what: str, ndims: tuple[int, ...]) -> np.ndarray:
    """A numeric ``.npy`` array with one of the dimension counts ``ndims``, checked first.

    The header must describe real numbers (bool, integer or float; no strings, records,
    complex or objects), ``len(shape)`` in ``ndims``, no zero-length axis, and a data size the
    file holds; only then is the data read (so a forged header costs no memory).

    Returns
    -------
    ndarray
        As stored (its own dtype).
    """
    fd, size = _open_regular(path, what)
    try:
        with os.fdopen(fd, "rb", closefd=True) as stream:
            try:
                shape, fortran, dtype, offset = read_npy_header(stream)
            except (ValueError, EOFError, TypeError, SyntaxError, OverflowError) as exc:
                raise DatasetError(f"{path}: corrupt or unreadable .npy file ({exc})") from None
            _check_array_header(path, what, shape, dtype, ndims)
            claimed = math.prod(shape) * dtype.itemsize
            if offset + claimed > size:
                raise DatasetError(
                    f"{path}: .npy header claims shape {shape} ({claimed} bytes) but the file "
                    f"holds {size - offset} bytes (truncated or forged)"
                )
            _check_memory(path, what, shape, claimed)
            data = stream.read(claimed)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read {what} ({_reason(exc)})") from None
    if len(data) != claimed:
        raise DatasetError(f"{path}: .npy file is truncated")
    return np.frombuffer(data, dtype).reshape(shape, order="F" if fortran else "C")


#: Bytes the viewer holds per pixel of a layer file: its float32 layers (8 channels), their
#: half-float pyramid and the float64 work copies of one layer while it is read.
BYTES_PER_PIXEL = 8 * 4 + 8 * 2 * 4 // 3 + 3 * 8


def _check_memory(path: Path, what: str, shape: tuple[int, ...], claimed: int) -> None:
    """Refuse an array whose reading and layers would not fit in the memory available now."""
    need = claimed + shape[0] * (shape[1] if len(shape) > 1 else 1) * BYTES_PER_PIXEL
    have = available_memory()
    if need > have:
        raise DatasetError(
            f"{path}: {what} of shape {shape} would need {need / 2**30:.1f} GiB to show, "
            f"{have / 2**30:.1f} GiB available (too large for this machine)"
        )


def _check_array_header(
    path: Path, what: str, shape: tuple[int, ...], dtype: np.dtype, ndims: tuple[int, ...]
) -> None:
    if dtype.kind not in NUMERIC_KINDS or dtype.fields is not None or dtype.subdtype is not None:
        raise DatasetError(f"{path}: {what} must hold real numbers, not {dtype.str!r} values")
    if len(shape) not in ndims:
        wanted = " or ".join(f"{n}-D" for n in ndims)
        raise DatasetError(f"{path}: {what} must be a {wanted} array, got shape {shape}")
    if 0 in shape:
        raise DatasetError(f"{path}: {what} is empty (shape {shape})")


def read_grey_png(path: Path, what: str) -> np.ndarray:
    """A PNG as 8-bit grey (H, W): its chunks checked first, libpng's stderr lines captured."""
    raw = read_bytes(path, what)
    problem = png_layout_problem(raw)
    if problem is not None:
        raise DatasetError(f"{path}: {problem}")
    picture, messages = decode_image(raw, cv2.IMREAD_GRAYSCALE)
    if picture is None:
        raise DatasetError(f"{path}: corrupt or truncated PNG file{decoder_said(messages)}")
    return picture


#: Integers of more digits than this read as None (beyond a float's range, like ``1e400``).
MAX_INT_DIGITS = 308


def _finite_or_none(text: str) -> float | None:
    value = float(text)
    return value if math.isfinite(value) else None


def _int_or_none(text: str) -> int | None:
    return int(text) if len(text.lstrip("-")) <= MAX_INT_DIGITS else None


def read_json(path: Path, what: str) -> dict:
    """A JSON object, with ``NaN``/``Infinity`` and out-of-range numbers read as None.

    Integers of more than :data:`MAX_INT_DIGITS` digits read as None too. A document that is not
    JSON, not UTF-8 or nested too deep is refused; one that is JSON but not an object reads as
    ``{}``.
    """
    raw = read_bytes(path, what, MAX_JSON_BYTES)
    try:
        value = json.loads(
            raw.decode("utf-8-sig"),
            parse_constant=lambda _name: None,
            parse_float=_finite_or_none,
            parse_int=_int_or_none,
        )
    except (ValueError, RecursionError) as exc:
        reason = "nested too deep" if isinstance(exc, RecursionError) else str(exc)
        raise DatasetError(f"{path}: {what} is not valid JSON ({reason})") from None
    return value if isinstance(value, dict) else {}
