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

A statement that cannot be used (a damaged EXIF or ICC block, a tone curve that is flat,
decreasing or not finite) never changes the decoding silently: the rules go on as if it were
absent, and one warning names the file and the problem.
"""

from __future__ import annotations

import logging
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ps_lab.errors import DatasetError

log = logging.getLogger("ps_lab.io.encoding")

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
        With ``"auto"``, damaged or unusable metadata (a truncated EXIF IFD or ICC tag table,
        offsets outside the block, a tone curve that is flat, decreasing or not finite) gives
        the format's documented default (JPEG: sRGB; PNG and TIFF: linear, or what their other
        chunks state) and logs one warning naming the file (once per file and problem).

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
    problems: list[str] = []
    found = None
    try:
        if suffix in JPEG_SUFFIXES:
            found = _jpeg_encoding(path.read_bytes(), problems)
        elif suffix == ".png":
            found = _png_encoding(path.read_bytes(), problems)
        elif suffix in (".tif", ".tiff"):
            found = _tiff_encoding(path, problems)
    except OSError:
        pass  # unreadable: the decoder names the file
    found = found or Encoding("linear", "no metadata")
    if problems:
        _warn_once(path, f"{'; '.join(problems)}: decoded as {found.name} ({found.source})")
    return found


class MetadataDamaged(ValueError):
    """A file's colour metadata cannot be used (why: the message)."""


# What reading a damaged block raises besides MetadataDamaged: short slices, bad zlib streams.
_DAMAGE = (ValueError, struct.error, IndexError, zlib.error, OverflowError)
_WARNED: set[tuple[str, str]] = set()


def _warn_once(path: Path, message: str) -> None:
    """Log ``path: message`` once per process (a frame is read again by every pass)."""
    key = (str(path), message)
    if key not in _WARNED:
        _WARNED.add(key)
        log.warning("%s: %s", path, message)


def _why(exc: Exception, block: str) -> str:
    if isinstance(exc, MetadataDamaged):
        return str(exc)
    return f"damaged {block} (truncated or malformed)"


def _jpeg_encoding(raw: bytes, problems: list[str]) -> Encoding:
    """ICC tone curves, else EXIF ColorSpace 1, else the JPEG default (sRGB)."""
    default = Encoding("srgb", "JPEG default")
    try:
        icc, exif = _jpeg_metadata(raw)
    except _DAMAGE as exc:
        problems.append(_why(exc, "JPEG metadata segments"))
        return default
    if icc is not None:
        try:
            return _icc_encoding(icc)
        except _DAMAGE as exc:
            problems.append(_why(exc, "ICC profile"))
    if exif is not None:
        try:
            if _exif_colour_space(exif) == 1:
                return Encoding("srgb", "EXIF")
        except _DAMAGE as exc:
            problems.append(_why(exc, "EXIF block"))
    return default


def _jpeg_metadata(raw: bytes) -> tuple[bytes | None, bytes | None]:
    """The ICC profile (its chunks joined in order) and the EXIF block of a JPEG, or None."""
    chunks: dict[int, bytes] = {}
    totals: set[int] = set()
    exif = None
    pos = 2
    while pos + 2 <= len(raw):
        if raw[pos] != 0xFF:
            raise MetadataDamaged(f"JPEG segment structure broken at byte {pos}")
        marker = raw[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no metadata after this
            break
        if 0xD0 <= marker <= 0xD7 or marker == 0x01:  # no length field
            pos += 2
            continue
        length = struct.unpack(">H", raw[pos + 2 : pos + 4])[0]
        if length < 2 or pos + 2 + length > len(raw):
            raise MetadataDamaged(f"JPEG segment 0xFF{marker:02X} at byte {pos} cut short")
        body = raw[pos + 4 : pos + 2 + length]
        if marker == 0xE2 and body.startswith(b"ICC_PROFILE\0"):
            if len(body) < 14:
                raise MetadataDamaged("empty ICC profile chunk")
            chunks[body[12]] = body[14:]  # 12-byte name, chunk number, chunk count
            totals.add(body[13])
        elif marker == 0xE1 and body.startswith(b"Exif\0\0") and exif is None:
            exif = body[6:]
        pos += 2 + length
    if not chunks:
        return None, exif
    if len(totals) != 1 or sorted(chunks) != list(range(1, max(totals) + 1)):
        raise MetadataDamaged(
            f"ICC profile chunks {sorted(chunks)} of {sorted(totals)}: missing or out of order"
        )
    return b"".join(chunks[k] for k in sorted(chunks)), exif


def _exif_colour_space(tiff: bytes) -> int | None:
    """EXIF ``ColorSpace`` (tag 0xA001 in the Exif IFD): 1 = sRGB, 0xFFFF = uncalibrated.

    MetadataDamaged for a block that is empty, not TIFF-structured, has an IFD that is cut short
    or outside the block, loops back, or holds a ColorSpace that is not a defined value.
    """
    if len(tiff) < 8:
        raise MetadataDamaged(f"EXIF block of {len(tiff)} bytes (empty or truncated)")
    if tiff[:2] not in (b"II", b"MM"):
        raise MetadataDamaged("EXIF block without a TIFF byte-order mark")
    order = "<" if tiff[:2] == b"II" else ">"
    if struct.unpack(order + "H", tiff[2:4])[0] != 42:
        raise MetadataDamaged("EXIF block without the TIFF magic number 42")
    first = struct.unpack(order + "I", tiff[4:8])[0]

    def entries(offset: int):
        if offset < 8 or offset + 2 > len(tiff):
            raise MetadataDamaged(f"EXIF IFD at offset {offset}, outside the {len(tiff)}-byte block")
        count = struct.unpack(order + "H", tiff[offset : offset + 2])[0]
        if offset + 2 + 12 * count > len(tiff):
            raise MetadataDamaged(
                f"EXIF IFD at offset {offset} truncated ({count} entr{'y' if count == 1 else 'ies'})"
            )
        for k in range(count):
            e = offset + 2 + 12 * k
            tag, kind, _ = struct.unpack(order + "HHI", tiff[e : e + 8])
            yield tag, kind, tiff[e + 8 : e + 12]

    for tag, _, value in entries(first):
        if tag == 0x8769:  # Exif IFD pointer
            sub_ifd = struct.unpack(order + "I", value)[0]
            if sub_ifd == first:
                raise MetadataDamaged("EXIF IFD pointer loops back to IFD0")
            for sub, kind, v in entries(sub_ifd):
                if sub == 0xA001:
                    if kind not in (3, 4):
                        raise MetadataDamaged(f"EXIF ColorSpace of TIFF type {kind}")
                    short = kind == 3
                    space = struct.unpack(order + ("H" if short else "I"), v[: 2 if short else 4])
                    if space[0] not in (1, 2, 0xFFFF):  # 2: Adobe RGB in DCF's usage
                        raise MetadataDamaged(f"EXIF ColorSpace {space[0]} is not a defined value")
                    return space[0]
    return None


def _png_encoding(raw: bytes, problems: list[str]) -> Encoding:
    if not raw.startswith(b"\x89PNG\r\n\x1a\n"):
        return Encoding("linear", "no metadata")
    pos, depth, gamma, srgb, icc = 8, 8, None, False, None
    while pos + 8 <= len(raw):
        length, kind = struct.unpack(">I4s", raw[pos : pos + 8])
        data = raw[pos + 8 : pos + 8 + length]
        if kind == b"IHDR" and len(data) >= 9:
            depth = data[8]
        elif kind == b"sRGB":
            srgb = True
        elif kind == b"gAMA":
            gamma = struct.unpack(">I", data)[0] / 100000.0 if length == 4 else 0.0
        elif kind == b"iCCP":
            icc = data
        elif kind in (b"IDAT", b"IEND"):
            break
        pos += 12 + length
    if depth > 8:
        return Encoding("linear", "16-bit")
    if icc is not None:
        try:
            return _icc_encoding(_inflate(icc[icc.index(b"\0") + 2 :]))
        except _DAMAGE as exc:
            problems.append(_why(exc, "PNG iCCP chunk"))
    if srgb:
        return Encoding("srgb", "PNG sRGB chunk")
    if gamma is not None:
        # gAMA stores the encoding exponent (V = L^g, 1/2.2 -> 0.45455): decode with 1/g.
        if not 0.1 <= gamma <= 10.0:
            problems.append(f"PNG gAMA chunk of {gamma:g} (not a usable exponent)")
        else:
            return Encoding(f"gamma {1.0 / gamma:.3g}", "PNG gAMA chunk", gamma=1.0 / gamma)
    return Encoding("linear", "no metadata")


def _inflate(data: bytes, limit: int = 16 << 20) -> bytes:
    """A zlib stream inflated to at most ``limit`` bytes (an ICC profile is far smaller)."""
    inflater = zlib.decompressobj()
    out = inflater.decompress(data, limit)
    if inflater.unconsumed_tail:
        raise MetadataDamaged(f"ICC profile over {limit >> 20} MiB when inflated")
    return out


def _tiff_encoding(path: Path, problems: list[str]) -> Encoding:
    import tifffile  # noqa: PLC0415 - only here (already a dependency of ps_lab.io.images)

    try:
        with tifffile.TiffFile(path) as tiff:
            page = tiff.pages.first
            depth = int(page.bitspersample)
            tag = page.tags.get(34675)  # InterColorProfile
            profile = bytes(tag.value) if tag is not None else None
    except Exception:  # noqa: BLE001 - tifffile raises many types; the decoder names the file
        return Encoding("linear", "no metadata")
    if depth > 8:
        return Encoding("linear", "16-bit")
    if profile is not None:
        try:
            return _icc_encoding(profile)
        except _DAMAGE as exc:
            problems.append(_why(exc, "TIFF ICC profile"))
    return Encoding("linear", "no metadata")


def _icc_encoding(profile: bytes) -> Encoding:
    """The tone curves of an ICC profile; MetadataDamaged when it has none that can be used."""
    if len(profile) < 132:
        raise MetadataDamaged(f"ICC profile of {len(profile)} bytes (truncated)")
    declared, count = struct.unpack(">I", profile[:4])[0], struct.unpack(">I", profile[128:132])[0]
    if declared > len(profile):
        raise MetadataDamaged(f"ICC profile truncated ({len(profile)} of {declared} bytes)")
    if 132 + 12 * count > len(profile):
        raise MetadataDamaged(f"ICC tag table truncated ({count} tags in {len(profile)} bytes)")
    tags = {}
    for k in range(count):
        sig, offset, size = struct.unpack(">4sII", profile[132 + 12 * k : 144 + 12 * k])
        if offset + size > len(profile):
            raise MetadataDamaged(f"ICC tag {sig!r} points outside the profile")
        tags[sig] = profile[offset : offset + size]
    names = [b"rTRC", b"gTRC", b"bTRC"] if b"rTRC" in tags else [b"kTRC"]
    if not all(n in tags for n in names):
        raise MetadataDamaged("ICC profile without tone curves (rTRC, gTRC, bTRC or kTRC)")
    table = np.array([_trc_table(tags[n], n.decode()) for n in names])
    grid = np.linspace(0.0, 1.0, table.shape[1])
    if np.allclose(table, grid[None, :], atol=1e-4):
        return Encoding("linear", "ICC profile")
    if np.allclose(table, srgb_to_linear(grid)[None, :], atol=2e-3):
        return Encoding("srgb", "ICC profile")
    return Encoding("icc", "ICC profile", table=table)


def _trc_table(tag: bytes, name: str, k: int = 1024) -> np.ndarray:
    """A ``curv`` or ``para`` tone curve sampled at ``k`` points of [0, 1], checked.

    A curve must be finite, rise from dark to bright (by at least half the range) and never
    fall by more than 1e-3 (table quantisation); its values are clipped to [0, 1] (ICC.1).
    """
    x = np.linspace(0.0, 1.0, k)
    kind = tag[:4]
    if kind == b"curv":
        n = struct.unpack(">I", tag[8:12])[0]
        if len(tag) < 12 + 2 * max(n, 1) and n != 0:
            raise MetadataDamaged(f"ICC {name} curve truncated ({n} entries)")
        if n == 0:
            return x
        if n == 1:
            table = x ** (struct.unpack(">H", tag[12:14])[0] / 256.0)
        else:
            values = np.frombuffer(tag[12 : 12 + 2 * n], dtype=">u2") / 65535.0
            table = np.interp(x, np.linspace(0.0, 1.0, n), values)
    elif kind == b"para":
        function = struct.unpack(">H", tag[8:10])[0]
        count = {0: 1, 1: 3, 2: 4, 3: 5, 4: 7}.get(function)
        if count is None:
            raise MetadataDamaged(f"ICC {name} parametric curve of unknown type {function}")
        if len(tag) < 12 + 4 * count:
            raise MetadataDamaged(f"ICC {name} parametric curve truncated")
        p = [v / 65536.0 for v in struct.unpack(f">{count}i", tag[12 : 12 + 4 * count])]
        g = p[0]
        if g <= 0:
            raise MetadataDamaged(f"ICC {name} curve with gamma {g:g} (must be > 0)")
        if function and p[1] <= 0:
            raise MetadataDamaged(f"ICC {name} curve with slope a = {p[1]:g} (must be > 0)")
        with np.errstate(all="ignore"):
            table = _para(function, x, p)
    else:
        raise MetadataDamaged(f"ICC {name} tag of unknown type {kind!r}")
    if not np.all(np.isfinite(table)):
        raise MetadataDamaged(f"ICC {name} curve is not finite")
    if np.any(np.diff(table) < -1e-3) or table[-1] - table[0] < 0.5:
        raise MetadataDamaged(f"ICC {name} curve is not increasing from dark to bright")
    return np.clip(table, 0.0, 1.0)


def _para(function: int, x: np.ndarray, p: list[float]) -> np.ndarray:
    """ICC ``para`` functions 0-4 (ICC.1:2010 table 65), with a > 0 and g > 0."""
    g = p[0]
    if function == 0:
        return x**g
    a, b = p[1], p[2]
    if function == 1:
        return np.where(x >= -b / a, np.clip(a * x + b, 0, None) ** g, 0.0)
    c = p[3]
    if function == 2:
        return np.where(x >= -b / a, np.clip(a * x + b, 0, None) ** g + c, c)
    d = p[4]
    e, f = (p[5], p[6]) if function == 4 else (0.0, 0.0)
    return np.where(x >= d, np.clip(a * x + b, 0, None) ** g + e, c * x + f)


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
