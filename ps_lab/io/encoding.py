"""Non-linear image encodings: which transfer curve a file's pixel values carry, and its inverse.

Photometric stereo needs values proportional to light. Camera JPEGs (and 8-bit PNG or TIFF
saved by most software) store ``V = f(L)`` with a transfer curve ``f``: the sRGB curve unless the
file states another (an ICC profile's tone curves, EXIF ``ColorSpace``, PNG ``sRGB``/``gAMA``).
:func:`image_encoding` reads that statement from the file's metadata without decoding pixels;
:meth:`Encoding.decode` maps values in [0, 1] back to linear light.

Rules for ``"auto"``:

- an ICC profile with tone curves (``rTRC``/``gTRC``/``bTRC`` or ``kTRC``: ``curv`` gamma or
  table, ``para`` functions 0-4; ICC.1:2010 section 10.6 and 10.18) is used as stated;
- else a JPEG is sRGB (EXIF ``ColorSpace`` 1, or no statement at all: the JFIF/Exif default);
  a PNG with an ``sRGB`` chunk is sRGB, one with only ``gAMA`` (g) decodes as ``V^(1/g)``;
- an 8-bit PNG or TIFF with no statement, and every 16-bit file, are linear (the field's
  linear data: DiLiGenT's PNGs, RAW conversions, ``ps-lab simulate``).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ps_lab.errors import DatasetError

JPEG_SUFFIXES = (".jpg", ".jpeg")
ENCODINGS = ("auto", "linear", "srgb")


@dataclass(frozen=True)
class Encoding:
    """A transfer curve and where it was learnt.

    Attributes
    ----------
    name : str
        ``"linear"``, ``"srgb"``, ``"gamma G"`` or ``"icc"``.
    source : str
        Why: ``"given"``, ``"ICC profile"``, ``"EXIF"``, ``"JPEG default"``, ``"PNG sRGB chunk"``,
        ``"PNG gAMA chunk"``, ``"no metadata"``, ``"16-bit"``.
    table : ndarray of shape (k,) or None
        The ICC tone curve sampled on ``linspace(0, 1, k)`` (encoded -> linear), per channel
        ``(c, k)`` for RGB profiles.
    gamma : float
        Exponent of a plain gamma curve (``name == "gamma G"``).

    """

    name: str
    source: str
    table: np.ndarray | None = None
    gamma: float = 1.0

    @property
    def label(self) -> str:
        """``"srgb (EXIF)"``: what calibration.json and metrics.json record."""
        return f"{self.name} ({self.source})"

    def decode(self, values: np.ndarray) -> np.ndarray:
        """Linear light from encoded values in [0, 1], shape (H, W, C) float32."""
        return decode_nonlinear(values, self)


LINEAR = Encoding("linear", "given")


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """The inverse sRGB transfer curve (IEC 61966-2-1): V/12.92 below 0.04045, else
    ((V + 0.055)/1.055)^2.4."""
    v = np.asarray(values, dtype=np.float32)
    return np.where(
        v <= np.float32(0.04045), v / np.float32(12.92), ((v + 0.055) / 1.055) ** 2.4
    ).astype(np.float32)


def linear_to_srgb(values: np.ndarray) -> np.ndarray:
    """The sRGB transfer curve (for tests and renders saved as camera JPEGs would be)."""
    v = np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)


def decode_nonlinear(values: np.ndarray, encoding: Encoding) -> np.ndarray:
    """Map encoded values in [0, 1] of shape (H, W, C) to linear light (float32).

    Parameters
    ----------
    values : ndarray of shape (H, W, C)
        Integer pixel values divided by the type maximum.
    encoding : Encoding
        From :func:`image_encoding`.

    Returns
    -------
    ndarray of shape (H, W, C), float32

    """
    v = np.asarray(values, dtype=np.float32)
    if encoding.name == "linear":
        return v
    if encoding.name == "srgb":
        return srgb_to_linear(v)
    if encoding.name.startswith("gamma"):
        return np.power(np.clip(v, 0, 1), np.float32(encoding.gamma)).astype(np.float32)
    table = np.atleast_2d(encoding.table)
    grid = np.linspace(0.0, 1.0, table.shape[1])
    out = np.empty_like(v)
    for c in range(v.shape[2]):
        out[..., c] = np.interp(v[..., c], grid, table[min(c, len(table) - 1)])
    return out


def image_encoding(path: Path, requested: str = "auto") -> Encoding:
    """The transfer curve of an integer image file (JPEG, PNG, TIFF).

    Parameters
    ----------
    path : Path
        The image file (only its metadata is read).
    requested : {"auto", "linear", "srgb"}
        ``"auto"`` reads the file's statement (module docstring); the others are used as given.

    Returns
    -------
    Encoding

    Raises
    ------
    DatasetError
        An unknown ``requested`` value.

    """
    if requested not in ENCODINGS:
        raise DatasetError(
            f"unknown encoding {requested!r} (choose one of {', '.join(ENCODINGS)})"
        )
    if requested == "linear":
        return LINEAR
    if requested == "srgb":
        return Encoding("srgb", "given")
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix in JPEG_SUFFIXES:
            return _jpeg_encoding(path.read_bytes())
        if suffix == ".png":
            return _png_encoding(path.read_bytes())
        if suffix in (".tif", ".tiff"):
            return _tiff_encoding(path)
    except (OSError, ValueError, struct.error, zlib.error, IndexError):
        # Unreadable metadata: the decoder names a broken file; the pixels stay as stored.
        pass
    return Encoding("linear", "no metadata")


def _jpeg_encoding(raw: bytes) -> Encoding:
    icc, exif = b"", None
    pos = 2
    while pos + 4 <= len(raw) and raw[pos] == 0xFF:
        marker = raw[pos + 1]
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no metadata after this
            break
        length = struct.unpack(">H", raw[pos + 2 : pos + 4])[0]
        body = raw[pos + 4 : pos + 2 + length]
        if marker == 0xE2 and body.startswith(b"ICC_PROFILE\0"):
            icc += body[14:]  # 12-byte name, chunk number, chunk count
        elif marker == 0xE1 and body.startswith(b"Exif\0\0"):
            exif = body[6:]
        pos += 2 + length
    if icc:
        found = _icc_encoding(icc)
        if found is not None:
            return found
    space = None if exif is None else _exif_colour_space(exif)
    if space == 1:
        return Encoding("srgb", "EXIF")
    return Encoding("srgb", "JPEG default")


def _exif_colour_space(tiff: bytes) -> int | None:
    """EXIF ``ColorSpace`` (tag 0xA001 in the Exif IFD): 1 = sRGB, 0xFFFF = uncalibrated."""
    order = "<" if tiff[:2] == b"II" else ">"
    ifd = struct.unpack(order + "I", tiff[4:8])[0]

    def entries(offset: int):
        count = struct.unpack(order + "H", tiff[offset : offset + 2])[0]
        for k in range(count):
            e = offset + 2 + 12 * k
            tag, kind, _ = struct.unpack(order + "HHI", tiff[e : e + 8])
            yield tag, kind, tiff[e + 8 : e + 12]

    for tag, _, value in entries(ifd):
        if tag == 0x8769:  # Exif IFD pointer
            for sub, kind, v in entries(struct.unpack(order + "I", value)[0]):
                if sub == 0xA001:
                    short = kind == 3
                    return struct.unpack(order + ("H" if short else "I"), v[: 2 if short else 4])[0]
    return None


def _png_encoding(raw: bytes) -> Encoding:
    if not raw.startswith(b"\x89PNG\r\n\x1a\n"):
        return Encoding("linear", "no metadata")
    pos, depth, gamma, srgb, icc = 8, 8, None, False, None
    while pos + 8 <= len(raw):
        length, kind = struct.unpack(">I4s", raw[pos : pos + 8])
        data = raw[pos + 8 : pos + 8 + length]
        if kind == b"IHDR":
            depth = data[8]
        elif kind == b"sRGB":
            srgb = True
        elif kind == b"gAMA" and length == 4:
            gamma = struct.unpack(">I", data)[0] / 100000.0
        elif kind == b"iCCP":
            name_end = data.index(b"\0")
            icc = zlib.decompress(data[name_end + 2 :])
        elif kind in (b"IDAT", b"IEND"):
            break
        pos += 12 + length
    if depth > 8:
        return Encoding("linear", "16-bit")
    if icc is not None:
        found = _icc_encoding(icc)
        if found is not None:
            return found
    if srgb:
        return Encoding("srgb", "PNG sRGB chunk")
    if gamma:
        # gAMA stores the encoding exponent (V = L^g, 1/2.2 -> 0.45455): decode with 1/g.
        return Encoding(f"gamma {1.0 / gamma:.3g}", "PNG gAMA chunk", gamma=1.0 / gamma)
    return Encoding("linear", "no metadata")


def _tiff_encoding(path: Path) -> Encoding:
    import tifffile  # noqa: PLC0415 - only here (already a dependency of ps_lab.io.images)

    with tifffile.TiffFile(path) as tiff:
        page = tiff.pages.first
        if int(page.bitspersample) > 8:
            return Encoding("linear", "16-bit")
        tag = page.tags.get(34675)  # InterColorProfile
        if tag is not None:
            found = _icc_encoding(bytes(tag.value))
            if found is not None:
                return found
    return Encoding("linear", "no metadata")


def _icc_encoding(profile: bytes) -> Encoding | None:
    """The tone curves of an ICC profile (None when it has none we can read)."""
    if len(profile) < 132:
        return None
    count = struct.unpack(">I", profile[128:132])[0]
    tags = {}
    for k in range(min(count, 256)):
        sig, offset, size = struct.unpack(">4sII", profile[132 + 12 * k : 144 + 12 * k])
        tags[sig] = profile[offset : offset + size]
    names = [b"rTRC", b"gTRC", b"bTRC"] if b"rTRC" in tags else [b"kTRC"]
    if not all(n in tags for n in names):
        return None
    tables = [_trc_table(tags[n]) for n in names]
    if any(t is None for t in tables):
        return None
    table = np.array(tables)
    grid = np.linspace(0.0, 1.0, table.shape[1])
    if np.allclose(table, grid[None, :], atol=1e-4):
        return Encoding("linear", "ICC profile")
    if np.allclose(table, srgb_to_linear(grid)[None, :], atol=2e-3):
        return Encoding("srgb", "ICC profile")
    return Encoding("icc", "ICC profile", table=table)


def _trc_table(tag: bytes, k: int = 1024) -> np.ndarray | None:
    """A ``curv`` or ``para`` tone curve sampled at ``k`` points of [0, 1]."""
    x = np.linspace(0.0, 1.0, k)
    kind = tag[:4]
    if kind == b"curv":
        n = struct.unpack(">I", tag[8:12])[0]
        if n == 0:
            return x
        if n == 1:
            return x ** (struct.unpack(">H", tag[12:14])[0] / 256.0)
        values = np.frombuffer(tag[12 : 12 + 2 * n], dtype=">u2") / 65535.0
        return np.interp(x, np.linspace(0.0, 1.0, n), values)
    if kind == b"para":
        function = struct.unpack(">H", tag[8:10])[0]
        sizes = {0: 1, 1: 3, 2: 4, 3: 5, 4: 7}
        if function not in sizes:
            return None
        count = sizes[function]
        p = [v / 65536.0 for v in struct.unpack(f">{count}i", tag[12 : 12 + 4 * count])]
        g = p[0]
        if function == 0:
            return x**g
        if function == 1:
            a, b = p[1], p[2]
            return np.where(x >= -b / a, np.clip(a * x + b, 0, None) ** g, 0.0)
        if function == 2:
            a, b, c = p[1], p[2], p[3]
            return np.where(x >= -b / a, np.clip(a * x + b, 0, None) ** g + c, c)
        a, b, c, d = p[1], p[2], p[3], p[4]
        e, f = (p[5], p[6]) if function == 4 else (0.0, 0.0)
        return np.where(x >= d, np.clip(a * x + b, 0, None) ** g + e, c * x + f)
    return None


_LINEAR_SUFFIXES = {".pfm": "float", ".npy": "array"}


def frames_encoding(path: Path, requested: str = "auto") -> str:
    """The label (``"srgb (EXIF)"``) of how a frame file is decoded, for the records.

    Float and RAW files are linear whatever is requested; ``.npy`` files are labelled by the
    request (integer arrays follow it).
    """
    suffix = Path(path).suffix.lower()
    if suffix in (".dng", ".cr2", ".cr3", ".nef", ".arw"):
        return "linear (RAW)"
    if suffix == ".pfm":
        return "linear (float)"
    return image_encoding(path, requested).label
