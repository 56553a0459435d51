"""Image readers for photometric-stereo datasets: one linear float32 image per file.

Every reader returns an :class:`Image`: linear values as float32 ``(H, W, C)`` with ``C`` = 1 or 3
(colour in RGB order), and a per-pixel saturation mask. Scaling:

- 8/16-bit PNG and TIFF (and integer ``.npy``): value / type maximum, so 65535 → 1.0; a pixel is
  saturated where any channel equals the type maximum.
- 32-bit float TIFF, PFM and float ``.npy``: values as stored; never saturated. Non-finite values
  are set to 0 and marked saturated, so the solvers drop them.
- camera RAW (``.dng .cr2 .cr3 .nef .arw``): :func:`ps_lab.io.raw.load_raw` — linear,
  (raw − black) / (white − black), 2×2 binned; saturated where the raw value reached the white
  level.

Every failure raises :class:`~ps_lab.errors.DatasetError` with one line that names the file. Readers
work on one file at a time so that callers can stream large captures.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import tifffile

from ps_lab.errors import DatasetError, PsLabError
from ps_lab.io.raw import load_raw

# OpenCV logs decoder failures on stderr; we report them ourselves as one DatasetError line.
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)

RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".nef", ".arw")
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".pfm", ".npy")
SUPPORTED_SUFFIXES = IMAGE_SUFFIXES + RAW_SUFFIXES

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@dataclass(frozen=True)
class Image:
    """One linear image.

    Attributes
    ----------
    data : ndarray of shape (H, W, C), float32
        Linear values, C = 1 (grey) or 3 (RGB).
    saturated : ndarray of shape (H, W), bool
        True where the sensor clipped (any channel) or the value is not finite.
    exposure_s : float or None
        Exposure time stored in the file (RAW only), else None.

    """

    data: np.ndarray
    saturated: np.ndarray
    exposure_s: float | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the image."""
        return self.data.shape[:2]


def is_supported(path: Path) -> bool:
    """Tell whether ``path`` has a suffix one of the readers handles (case-insensitive)."""
    return Path(path).suffix.lower() in SUPPORTED_SUFFIXES


def read_image(path: Path) -> Image:
    """Read any supported image file as linear float32.

    Parameters
    ----------
    path : Path
        A PNG, TIFF, PFM, ``.npy`` or camera RAW file.

    Returns
    -------
    Image
        ``data`` of shape (H, W, C) float32, ``saturated`` of shape (H, W).

    Raises
    ------
    DatasetError
        The file is missing, of an unsupported type, unreadable or corrupt (message names the file).

    """
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise DatasetError(f"{path}: image file not found")
    if suffix in RAW_SUFFIXES:
        return _read_raw(path)
    if suffix == ".png":
        array = _read_png(path)
    elif suffix in (".tif", ".tiff"):
        array = _read_tiff(path)
    elif suffix == ".pfm":
        array = read_pfm(path)
    elif suffix == ".npy":
        array = _read_npy(path)
    else:
        raise DatasetError(
            f"{path}: unsupported image type {suffix!r} (supported: {' '.join(SUPPORTED_SUFFIXES)})"
        )
    return _to_linear(array, path)


def read_image_size(path: Path) -> tuple[int, int]:
    """Size ``(H, W)`` of an image file, from its header when the format allows.

    PNG (IHDR chunk), ``.npy`` (array header) and TIFF (first page) are read without decoding
    the pixels; other formats (PFM, camera RAW) are decoded once.

    Raises
    ------
    DatasetError
        The file is missing or unreadable (message names the file).

    """
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".png":
            with path.open("rb") as stream:
                head = stream.read(24)
            if head.startswith(_PNG_SIGNATURE) and head[12:16] == b"IHDR":
                width, height = struct.unpack(">II", head[16:24])
                if width and height:
                    return int(height), int(width)
        elif suffix == ".npy":
            with path.open("rb") as stream:
                shape, _, _, _ = read_npy_header(stream)
            if len(shape) in (2, 3):
                return int(shape[0]), int(shape[1])
        elif suffix in (".tif", ".tiff"):
            with tifffile.TiffFile(path) as tiff:
                page = tiff.pages[0]
                if page.imagelength and page.imagewidth:
                    return int(page.imagelength), int(page.imagewidth)
    except Exception:  # noqa: BLE001, S110 - any header problem: decode the file, which names it
        pass
    return read_image(path).shape


def read_pfm(path: Path) -> np.ndarray:
    """Read a Portable Float Map.

    The header is ``PF`` (RGB) or ``Pf`` (grey), then width and height, then a scale whose sign
    gives the byte order (negative = little-endian); rows are stored bottom to top.

    Parameters
    ----------
    path : Path
        The ``.pfm`` file.

    Returns
    -------
    ndarray of shape (H, W, 3) or (H, W), float32
        Rows top to bottom, native byte order.

    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read file ({exc.strerror})") from None
    # Three whitespace-separated header tokens after the magic, then exactly one whitespace byte.
    match = re.match(rb"(P[Ff])\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)\s", raw)
    if match is None:
        raise DatasetError(f"{path}: not a PFM file (bad header)")
    channels = 3 if match.group(1) == b"PF" else 1
    width, height = int(match.group(2)), int(match.group(3))
    try:
        scale = float(match.group(4))
    except ValueError:
        raise DatasetError(f"{path}: not a PFM file (bad scale {match.group(4)!r})") from None
    if width == 0 or height == 0 or scale == 0.0:
        raise DatasetError(f"{path}: PFM header has zero size or zero scale")
    dtype = np.dtype("<f4") if scale < 0 else np.dtype(">f4")
    count = width * height * channels
    body = raw[match.end() :]
    if len(body) < count * 4:
        raise DatasetError(f"{path}: PFM file is truncated ({len(body)} of {count * 4} data bytes)")
    data = np.frombuffer(body, dtype=dtype, count=count).astype(np.float32)
    shape = (height, width, channels) if channels == 3 else (height, width)
    return np.ascontiguousarray(data.reshape(shape)[::-1])


def write_pfm(path: Path, image: np.ndarray) -> None:
    """Write a float image as PFM (little-endian, rows bottom to top).

    Parameters
    ----------
    path : Path
        Output file.
    image : ndarray of shape (H, W), (H, W, 1) or (H, W, 3)
        Values to store as float32.

    """
    array = np.asarray(image, dtype="<f4")
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[:, :, 0]
    if array.ndim == 2:
        magic = b"Pf"
    elif array.ndim == 3 and array.shape[2] == 3:
        magic = b"PF"
    else:
        raise ValueError(f"PFM holds (H, W) or (H, W, 3) images, got shape {array.shape}")
    height, width = array.shape[:2]
    header = magic + b"\n" + f"{width} {height}\n-1.0\n".encode("ascii")
    Path(path).write_bytes(header + np.ascontiguousarray(array[::-1]).tobytes())


def read_npy_header(stream) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    """Read the header of an open ``.npy`` file.

    Returns
    -------
    shape : tuple of int
    fortran_order : bool
    dtype : numpy dtype
    offset : int
        Byte offset of the array data.

    """
    version = np.lib.format.read_magic(stream)
    if version == (1, 0):
        shape, fortran_order, dtype = np.lib.format.read_array_header_1_0(stream)
    else:
        shape, fortran_order, dtype = np.lib.format.read_array_header_2_0(stream)
    return tuple(shape), bool(fortran_order), np.dtype(dtype), stream.tell()


def _read_png(path: Path) -> np.ndarray:
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read file ({exc.strerror})") from None
    if not raw.startswith(_PNG_SIGNATURE):
        raise DatasetError(f"{path}: not a PNG file")
    array = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED)
    if array is None:
        raise DatasetError(f"{path}: corrupt or truncated PNG file")
    return _bgr_to_rgb(array)


def _read_tiff(path: Path) -> np.ndarray:
    # tifffile keeps every sample type exactly; OpenCV covers compressions tifffile cannot decode
    # without the optional imagecodecs package (LZW, JPEG).
    try:
        array = tifffile.imread(path)
    except Exception as tiff_exc:  # noqa: BLE001 - any decoder failure → try the second decoder
        array = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if array is None:
            raise DatasetError(f"{path}: corrupt or unreadable TIFF file ({tiff_exc})") from None
        return _bgr_to_rgb(array)
    array = np.asarray(array)
    # Planar (samples-first) colour TIFFs come back as (C, H, W).
    if array.ndim == 3 and array.shape[0] in (3, 4) and array.shape[2] not in (3, 4):
        array = np.moveaxis(array, 0, -1)
    return array


def _read_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise DatasetError(f"{path}: corrupt or unreadable .npy file ({exc})") from None


def _read_raw(path: Path) -> Image:
    try:
        raw = load_raw(path)
    except PsLabError as exc:
        message = str(exc)
        if str(path) not in message and path.name not in message:
            message = f"{path}: {message}"
        raise DatasetError(message) from None
    except Exception as exc:  # noqa: BLE001 - LibRaw raises many types for a broken file
        raise DatasetError(f"{path}: corrupt or unreadable RAW file ({exc})") from None
    data = np.asarray(raw.image, dtype=np.float32)
    if data.ndim == 2:
        data = data[:, :, None]
    return Image(
        data=data, saturated=np.asarray(raw.saturated, dtype=bool), exposure_s=raw.exposure_s
    )


def _bgr_to_rgb(array: np.ndarray) -> np.ndarray:
    if array.ndim == 3 and array.shape[2] == 3:
        return array[:, :, ::-1]
    if array.ndim == 3 and array.shape[2] == 4:
        return array[:, :, [2, 1, 0, 3]]
    return array


def _to_linear(array: np.ndarray, path: Path) -> Image:
    """Scale an integer or float array of shape (H, W[, C]) to an :class:`Image`."""
    if array.ndim == 3 and array.shape[2] in (2, 4):
        array = array[:, :, : array.shape[2] - 1]  # drop alpha
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3 or array.shape[2] not in (1, 3) or 0 in array.shape:
        raise DatasetError(
            f"{path}: expected a grey or RGB image, got an array of shape {array.shape}"
        )
    if array.dtype == np.bool_:
        array = array.astype(np.uint8)
    if np.issubdtype(array.dtype, np.integer):
        top = np.iinfo(array.dtype).max
        saturated = array[:, :, 0] >= top
        for k in range(1, array.shape[2]):
            saturated |= array[:, :, k] >= top
        data = np.multiply(array, np.float32(1.0 / top), dtype=np.float32)
    elif np.issubdtype(array.dtype, np.floating):
        data = array.astype(np.float32)
        bad = ~np.isfinite(data)
        saturated = np.any(bad, axis=2)
        if saturated.any():
            data[bad] = 0.0
    else:
        raise DatasetError(f"{path}: unsupported pixel type {array.dtype}")
    return Image(data=np.ascontiguousarray(data), saturated=saturated)
