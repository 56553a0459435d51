"""Image readers for photometric-stereo datasets: one linear float32 image per file.

Every reader returns an :class:`Image`: linear values as float32 ``(H, W, C)`` with ``C`` = 1 or 3
(colour in RGB order), and a per-pixel saturation mask. Scaling:

- 8/16-bit PNG and TIFF (and integer ``.npy``): value / type maximum, so 65535 → 1.0; a pixel is
  saturated where any channel equals the type maximum.
- 32-bit float TIFF, PFM and float ``.npy``: values as stored; never saturated. Non-finite values
  are set to 0 and marked saturated, so the solvers drop them.
- OpenEXR (``.exr``, half or float channels): values as stored (:func:`read_exr`).
- camera RAW (``.dng .cr2 .cr3 .nef .arw``): :func:`ps_lab.io.raw.load_raw` — linear,
  (raw − black) / (white − black), 2×2 binned; saturated where the raw value reached the white
  level.
- JPEG: saturated where any channel is within :data:`JPEG_CLIP_LEVELS` (4) of 255, since the
  codec smears a clipped highlight's edge below 255.
- non-linear files (JPEG; 8-bit PNG and TIFF that say so): decoded to linear by
  :func:`decode_nonlinear` with the transfer curve :func:`image_encoding` finds (``encoding``:
  ``"auto"`` from the file's ICC profile, EXIF colour space or PNG ``sRGB``/``gAMA`` chunk;
  ``"srgb"``; ``"linear"``). A JPEG without metadata is sRGB (the JPEG/JFIF default); an 8-bit
  PNG or TIFF without metadata, and every 16-bit file, stay linear (DiLiGenT's and RAW's data).

Every failure raises :class:`~ps_lab.errors.DatasetError` with one line that names the file. Readers
work on one file at a time so that callers can stream large captures.
"""

from __future__ import annotations

import os
import re
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import OpenEXR
import tifffile

from ps_lab.errors import DatasetError, PsLabError
from ps_lab.io.coding import Coded, Coding, code_table
from ps_lab.io.codecs import decode_image, decoder_said, imread, native_stderr_captured
from ps_lab.io.encoding import ENCODINGS, JPEG_SUFFIXES, image_encoding
from ps_lab.io.exr import exr_layout
from ps_lab.io.raw import load_raw

__all__ = [
    "ENCODINGS", "JPEG_SUFFIXES", "Coded", "Image", "linear_image", "read_frame", "read_image",
    "read_image_size",
]

# OpenCV logs decoder failures on stderr; we report them ourselves as one DatasetError line.
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)

RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".nef", ".arw")
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".pfm", ".npy", ".exr", *JPEG_SUFFIXES)
SUPPORTED_SUFFIXES = IMAGE_SUFFIXES + RAW_SUFFIXES

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
# Deflate (PNG) cannot compress better than 1032:1; a header claiming more pixels than its data can
# hold is forged or corrupt, and is refused before the decoder allocates what it claims.
MAX_COMPRESSION_RATIO = 1100
#: A JPEG's clipped highlights decode up to this many levels below 255 (its 8 x 8 blocks smear the
#: clipped edge; measured up to 4 at quality 95-100): such pixels are saturated too.
JPEG_CLIP_LEVELS = 4


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
    bit_depth: int | None = None  # bits per sample of an integer file (8, 16), else None
    encoding: str = "linear"  # the transfer curve decoded (``image_encoding``'s answer)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the image."""
        return self.data.shape[:2]


def is_supported(path: Path) -> bool:
    """Tell whether ``path`` has a suffix one of the readers handles (case-insensitive)."""
    return Path(path).suffix.lower() in SUPPORTED_SUFFIXES


def read_image(path: Path, encoding: str = "auto") -> Image:
    """Read any supported image file as linear float32.

    Parameters
    ----------
    path : Path
        A PNG, TIFF, JPEG, PFM, ``.npy``, OpenEXR or camera RAW file.
    encoding : {"auto", "linear", "srgb"}
        How integer pixel values map to light (:func:`image_encoding`); float and RAW files
        are always linear.

    Returns
    -------
    Image
        ``data`` of shape (H, W, C) float32, ``saturated`` of shape (H, W).

    Raises
    ------
    DatasetError
        The file is missing, of an unsupported type, unreadable or corrupt (message names the file).

    """
    frame = read_frame(path, encoding)
    return linear_image(frame) if isinstance(frame, Coded) else frame


def linear_image(coded: Coded) -> Image:
    """The linear :class:`Image` of a file's codes (table lookup; saturated at the clip level)."""
    codes, table = coded.codes, coded.coding.table
    assert table is not None
    data = np.empty(codes.shape, np.float32)
    saturated = np.zeros(codes.shape[:2], bool)
    for c in range(codes.shape[2]):
        np.take(table[:, c], codes[:, :, c], out=data[:, :, c])
        saturated |= codes[:, :, c] >= coded.coding.clip
    return Image(data, saturated, None, coded.bit_depth, coded.encoding)


def read_frame(path: Path, encoding: str = "auto") -> Image | Coded:
    """Read an image file: an 8/16-bit file as its :class:`Coded` codes, any other as an Image.

    Parameters and errors as :func:`read_image` (which is ``read_frame(...)`` made linear).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    check_is_file(path, "image file")
    if suffix in RAW_SUFFIXES:
        return _read_raw(path)
    if suffix in JPEG_SUFFIXES:
        array = _read_jpeg(path)
    elif suffix == ".png":
        array = _read_png(path)
    elif suffix in (".tif", ".tiff"):
        array = _read_tiff(path)
    elif suffix == ".pfm":
        array = read_pfm(path)
    elif suffix == ".npy":
        array = _read_npy(path)
    elif suffix == ".exr":
        array = read_exr(path)
    else:
        raise DatasetError(
            f"{path}: unsupported image type {suffix!r} (supported: {' '.join(SUPPORTED_SUFFIXES)})"
        )
    array = _checked_layout(array, path)
    if array.dtype in (np.uint8, np.uint16):
        top = np.iinfo(array.dtype).max
        clip = top - JPEG_CLIP_LEVELS if suffix in JPEG_SUFFIXES and top == 255 else top
        curve = image_encoding(path, encoding)
        bits = array.dtype.itemsize * 8
        table = _code_table(bits, array.shape[2], curve)
        return Coded(array, Coding(array.dtype, array.shape[2], table, clip), bits, curve.name)
    image = _to_linear(array, path)
    if image.bit_depth is None:
        return image
    return decoded(image, image_encoding(path, encoding))


_TABLES: dict[tuple, np.ndarray] = {}


def _code_table(bits: int, channels: int, curve) -> np.ndarray:
    """:func:`ps_lab.io.coding.code_table` of ``curve``, kept for the next file of a capture."""
    table = None if curve.table is None else np.asarray(curve.table, np.float64)
    key = (bits, channels, curve.name, curve.gamma,
           None if table is None else (table.shape, table.tobytes()))
    found = _TABLES.get(key)
    if found is None:
        if curve.name == "linear":
            found = code_table(bits, channels, lambda v: v)
        else:
            found = code_table(bits, channels, curve.decode)
        if len(_TABLES) > 16:
            _TABLES.clear()
        _TABLES[key] = found
    return found


def decoded(image: Image, encoding) -> Image:
    """``image`` (values / type maximum) decoded to linear light with ``encoding``
    (:class:`ps_lab.io.encoding.Encoding`); the saturation mask is the file's."""
    if encoding.name == "linear":
        return Image(image.data, image.saturated, image.exposure_s, image.bit_depth, "linear")
    return Image(
        data=encoding.decode(image.data),
        saturated=image.saturated,
        exposure_s=image.exposure_s,
        bit_depth=image.bit_depth,
        encoding=encoding.name,
    )


def check_is_file(path: Path, what: str = "file") -> None:
    """Raise :class:`DatasetError` naming ``path`` unless it is a readable regular file.

    Tells the usual cases apart: missing, a folder, a link that leads nowhere or loops, or no
    permission to read.
    """
    path = Path(path)
    a_what = f"{'an' if what[:1] in 'aeiou' else 'a'} {what}"
    try:
        st = path.stat()
    except FileNotFoundError:
        kind = "a broken link" if path.is_symlink() else "not found"
        raise DatasetError(f"{path}: {what} {kind}") from None
    except OSError as exc:  # ELOOP, EACCES on a parent, ...
        raise DatasetError(f"{path}: cannot open {what} ({exc.strerror})") from None
    if os.path.isdir(path):
        raise DatasetError(f"{path}: is a folder, expected {a_what}")
    if not path.is_file():
        raise DatasetError(f"{path}: is not a regular file (expected {a_what})")
    if st.st_size == 0:
        raise DatasetError(f"{path}: {what} is empty (0 bytes)")
    if not os.access(path, os.R_OK):
        raise DatasetError(f"{path}: no permission to read the {what}")


def png_layout_problem(raw: bytes) -> str | None:
    """Check a PNG's chunks (lengths, CRCs, IHDR, IDAT, IEND) without decoding any pixel.

    Returns
    -------
    str or None
        Why the file cannot be a valid PNG (``"truncated ..."``, a forged size), else None.
        Catching these before libpng runs keeps libpng's own messages off stderr and stops a
        forged header from making the decoder allocate the size it claims.

    """
    if not raw.startswith(_PNG_SIGNATURE):
        return "not a PNG file"
    pos, idat, header = 8, 0, None
    while True:
        if pos + 8 > len(raw):
            return "corrupt or truncated PNG file (no IEND chunk)"
        length, kind = struct.unpack(">I4s", raw[pos : pos + 8])
        end = pos + 12 + length
        name = kind.decode("latin-1")
        if end > len(raw):
            return f"corrupt or truncated PNG file ({name!r} chunk cut short)"
        data = raw[pos + 8 : pos + 8 + length]
        if zlib.crc32(kind + data) != struct.unpack(">I", raw[end - 4 : end])[0]:
            return f"corrupt PNG file ({name!r} chunk fails its CRC)"
        if kind == b"IHDR" and length == 13:
            header = struct.unpack(">IIBBBBB", data)
        elif kind == b"IDAT":
            idat += length
        elif kind == b"IEND":
            break
        pos = end
    if header is None or idat == 0:
        return "corrupt PNG file (no image header or no image data)"
    width, height, depth, colour = header[:4]
    channels = _PNG_CHANNELS.get(colour)
    if width == 0 or height == 0 or channels is None or depth not in (1, 2, 4, 8, 16):
        return f"corrupt PNG header ({width}x{height}, colour type {colour}, depth {depth})"
    raw_bytes = height * (1 + (width * channels * depth + 7) // 8)
    if raw_bytes > MAX_COMPRESSION_RATIO * idat:
        return (
            f"PNG header claims {width}x{height} pixels but the file holds only {idat} bytes of "
            "image data (forged or corrupt header)"
        )
    check_decode_memory(None, height, width, channels)
    return None


def available_memory() -> int:
    """Bytes of memory available now (``MemAvailable`` on Linux, else physical memory)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as stream:
            for line in stream:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 1 << 62


def check_decode_memory(path: Path | None, height: int, width: int, channels: int) -> None:
    """Refuse an image whose decoding would not fit in the memory available now.

    Decoding holds the file's array and its float32 copy (about 8 bytes per sample).
    """
    need = int(height) * int(width) * max(int(channels), 1) * 8
    have = available_memory()
    if need > have:
        where = f"{path}: " if path is not None else ""
        raise DatasetError(
            f"{where}image of {width}x{height} pixels would need {need / 2**30:.1f} GiB to decode, "
            f"{have / 2**30:.1f} GiB available (forged header, or too large for this machine)"
        )


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
    check_is_file(path, "image file")
    size: tuple[int, int] | None = None
    claimed = stored = 0
    try:
        if suffix == ".png":
            with path.open("rb") as stream:
                head = stream.read(26)
            if head.startswith(_PNG_SIGNATURE) and head[12:16] == b"IHDR":
                width, height = struct.unpack(">II", head[16:24])
                depth, colour = head[24], head[25]
                if width and height:
                    size = int(height), int(width)
                    claimed = height * width * depth * _PNG_CHANNELS.get(colour, 1) // 8
                    stored = MAX_COMPRESSION_RATIO * path.stat().st_size
        elif suffix == ".npy":
            with path.open("rb") as stream:
                shape, _, dtype, offset = read_npy_header(stream)
            if len(shape) in (2, 3):
                size = int(shape[0]), int(shape[1])
                claimed = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
                stored = path.stat().st_size - offset
        elif suffix in JPEG_SUFFIXES:
            size = _jpeg_size(path)
        elif suffix in (".tif", ".tiff"):
            with tifffile.TiffFile(path) as tiff:
                page = tiff.pages[0]
                if page.imagelength and page.imagewidth:
                    size = int(page.imagelength), int(page.imagewidth)
    except Exception:  # noqa: BLE001, S110 - any header problem: decode the file, which names it
        size = None
    if size is not None:
        if claimed > stored:
            raise DatasetError(
                f"{path}: header claims {size[1]}x{size[0]} pixels, more than the file's "
                f"{path.stat().st_size} bytes can hold (forged or truncated)"
            )
        if suffix in (".tif", ".tiff"):
            _check_tiff_layout(path)
        return size
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
    if len(raw) - match.end() < width * height * channels * 4:
        raise DatasetError(
            f"{path}: PFM header claims {width}x{height} pixels but the file is shorter "
            "(truncated or forged)"
        )
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


def read_png_bytes(path: Path) -> bytes:
    """The bytes of a PNG file whose structure is sound (see :func:`png_layout_problem`)."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read file ({exc.strerror})") from None
    problem = png_layout_problem(raw)
    if problem is not None:
        raise DatasetError(f"{path}: {problem}")
    return raw


def _read_png(path: Path) -> np.ndarray:
    try:
        raw = read_png_bytes(path)
    except DatasetError as exc:
        if str(path) in str(exc):
            raise
        raise DatasetError(f"{path}: {exc}") from None
    array, messages = decode_image(raw)
    if array is None:
        raise DatasetError(f"{path}: corrupt or truncated PNG file{decoder_said(messages)}")
    return _bgr_to_rgb(array)


def _read_jpeg(path: Path) -> np.ndarray:
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read file ({exc.strerror})") from None
    size = _jpeg_size_of(raw)
    if size is None:
        raise DatasetError(f"{path}: corrupt or truncated JPEG file (no frame header)")
    check_decode_memory(path, size[0], size[1], 3)
    array = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED)
    if array is None:
        raise DatasetError(f"{path}: corrupt or truncated JPEG file")
    return _bgr_to_rgb(array)


def _jpeg_size_of(raw: bytes) -> tuple[int, int] | None:
    """``(H, W)`` from a JPEG's frame header (SOF0-SOF15 but DHT, JPG, DAC), else None."""
    if not raw.startswith(b"\xff\xd8"):
        return None
    pos = 2
    while pos + 4 <= len(raw):
        if raw[pos] != 0xFF:
            return None
        marker = raw[pos + 1]
        if marker == 0xFF:
            pos += 1
            continue
        length = struct.unpack(">H", raw[pos + 2 : pos + 4])[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if pos + 9 > len(raw):
                return None
            height, width = struct.unpack(">HH", raw[pos + 5 : pos + 9])
            return (int(height), int(width)) if height and width else None
        if marker in (0xD9, 0xDA):
            return None
        pos += 2 + length
    return None


def _jpeg_size(path: Path) -> tuple[int, int] | None:
    with path.open("rb") as stream:
        head = stream.read(1 << 18)  # metadata (EXIF thumbnails, ICC) precedes the frame header
    return _jpeg_size_of(head)


def _read_tiff(path: Path) -> np.ndarray:
    # tifffile keeps every sample type exactly; OpenCV covers compressions tifffile cannot decode
    # without the optional imagecodecs package (LZW, JPEG).
    _check_tiff_layout(path)
    try:
        array = tifffile.imread(path)
    except Exception as tiff_exc:  # noqa: BLE001 - any decoder failure → try the second decoder
        try:
            array = imread(path)
        except OSError:
            array = None
        if array is None:
            raise DatasetError(f"{path}: corrupt or unreadable TIFF file ({tiff_exc})") from None
        return _bgr_to_rgb(array)
    array = np.asarray(array)
    # Planar (samples-first) colour TIFFs come back as (C, H, W).
    if array.ndim == 3 and array.shape[0] in (3, 4) and array.shape[2] not in (3, 4):
        array = np.moveaxis(array, 0, -1)
    return array


def _check_tiff_layout(path: Path) -> None:
    """Refuse a TIFF whose first page claims more pixels than its strips or tiles hold."""
    try:
        with tifffile.TiffFile(path) as tiff:
            page = tiff.pages.first
            height, width = int(page.imagelength), int(page.imagewidth)
            samples = int(page.samplesperpixel)
            stored = int(sum(page.databytecounts or ()))
            claimed = height * width * samples * max(int(page.bitspersample), 1) // 8
            compressed = int(page.compression) != 1
    except Exception:  # noqa: BLE001, S110 - the decoder below names the problem
        return
    limit = stored * (MAX_COMPRESSION_RATIO if compressed else 1)
    if claimed > limit or stored > path.stat().st_size:
        raise DatasetError(
            f"{path}: TIFF header claims {width}x{height}x{samples} samples but the file holds "
            f"only {stored} bytes of image data (forged or corrupt header)"
        )
    check_decode_memory(path, height, width, samples)


def _read_npy(path: Path) -> np.ndarray:
    try:
        with path.open("rb") as stream:
            shape, _, dtype, offset = read_npy_header(stream)
        claimed = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
    except (OSError, ValueError, EOFError, TypeError) as exc:
        raise DatasetError(f"{path}: corrupt or unreadable .npy file ({exc})") from None
    if offset + claimed > path.stat().st_size:
        raise DatasetError(
            f"{path}: .npy header claims shape {tuple(shape)} ({claimed} bytes) but the file "
            f"holds {path.stat().st_size - offset} bytes (truncated or forged)"
        )
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise DatasetError(f"{path}: corrupt or unreadable .npy file ({exc})") from None


def read_exr(path: Path) -> np.ndarray:
    """Read an OpenEXR image (its first part) as float32 (H, W) or (H, W, 3).

    Channels: ``R G B`` (an ``A`` dropped), else ``Y`` (luminance), else a single channel of any
    name; half and float samples are returned as float32, linear as stored.

    Raises
    ------
    DatasetError
        Not an OpenEXR file, or no channel layout above (the message names the file).
    """
    layout = exr_layout(path)  # the header checked against the file before OpenEXR allocates
    # Every part's samples as stored, and the first part's float32 copy: in units of 8 bytes.
    pixels = layout.height * layout.width
    check_decode_memory(path, layout.height, layout.width,
                        -(-(layout.pixel_bytes + 4 * pixels * layout.channels) // (8 * pixels)))
    try:
        with native_stderr_captured((1, 2)) as said, OpenEXR.File(str(path)) as exr:
            channels = {name: np.asarray(c.pixels) for name, c in exr.channels().items()}
    except Exception as exc:  # noqa: BLE001 - the OpenEXR bindings raise several types
        reason = str(exc).splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
        raise DatasetError(f"{path}: corrupt or unreadable OpenEXR file ({reason})") from None
    if said:
        raise DatasetError(f"{path}: corrupt OpenEXR file (OpenEXR: {said[0][:200]})")
    for name in ("RGB", "RGBA"):
        if name in channels:
            return channels[name][..., :3].astype(np.float32)
    if all(c in channels for c in "RGB"):
        return np.stack([channels[c] for c in "RGB"], axis=-1).astype(np.float32)
    if "Y" in channels or len(channels) == 1:
        return np.asarray(channels.get("Y", next(iter(channels.values()))), np.float32)
    raise DatasetError(
        f"{path}: OpenEXR channels {', '.join(sorted(channels))}: expected R, G, B or Y"
    )


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
    """OpenCV's BGR(A) as RGB: a contiguous copy (the stores copy it without strides)."""
    if array.ndim == 3 and array.shape[2] == 3:
        if array.dtype in (np.uint8, np.uint16, np.float32) and array.flags.c_contiguous:
            return cv2.cvtColor(array, cv2.COLOR_BGR2RGB)
        return np.ascontiguousarray(array[:, :, ::-1])
    if array.ndim == 3 and array.shape[2] == 4:
        return array[:, :, [2, 1, 0, 3]]
    return array


#: A JPEG's clipped highlights decode up to this many levels below 255 (its 8 x 8 blocks smear the
#: clipped edge; measured up to 4 at quality 95-100): such pixels are saturated too.
JPEG_CLIP_LEVELS = 4


def _checked_layout(array: np.ndarray, path: Path) -> np.ndarray:
    """``array`` as (H, W, C) with C = 1 or 3 (alpha dropped), or a DatasetError naming ``path``."""
    if array.ndim == 3 and array.shape[2] in (2, 4):
        array = array[:, :, : array.shape[2] - 1]  # drop alpha
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3 or array.shape[2] not in (1, 3) or 0 in array.shape:
        raise DatasetError(
            f"{path}: expected a grey or RGB image, got an array of shape {array.shape}"
        )
    return array


def _to_linear(array: np.ndarray, path: Path) -> Image:
    """Scale an integer or float array of shape (H, W[, C]) to an :class:`Image`."""
    array = _checked_layout(array, path)
    if array.dtype == np.bool_:
        array = array.astype(np.uint8)
    bit_depth = None
    if np.issubdtype(array.dtype, np.integer):
        top = np.iinfo(array.dtype).max
        bit_depth = array.dtype.itemsize * 8
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
    return Image(data=np.ascontiguousarray(data), saturated=saturated, bit_depth=bit_depth)
