"""Linear camera-RAW loading: black level out, white level to 1, Bayer mosaic reduced linearly.

Photometric stereo needs values proportional to scene radiance. LibRaw's usual output path
(``postprocess``) applies a gamma curve, auto-brightness and white balance, any of which breaks
the model, so :func:`load_raw` takes the *visible raw data* from rawpy and does only linear
arithmetic on it:

``value = (raw - black[c]) / (white - black[c])``

where ``c`` is the CFA colour of the pixel (LibRaw's ``raw_colors_visible`` maps pixels to
``black_level_per_channel``) and ``white`` is LibRaw's white level. Values below the black
level stay negative, so averages over dark pixels stay unbiased (a dark frame subtracted later
cancels the offset instead of leaving a clipped bias).

The mosaic then becomes an RGB image without any non-linear step:

* ``demosaic="half"`` (default): each 2x2 Bayer block becomes one pixel with R, the mean of
  the two G and B of that block. Exact (no interpolation), fast, half the resolution.
* ``demosaic="linear"``: full-resolution bilinear demosaic: every channel is the weighted
  mean of the samples of that colour in the 3x3 neighbourhood (normalised convolution with
  weights 4 at the centre, 2 at the edge neighbours, 1 at the corners); measured samples are
  kept unchanged.

``saturated`` marks output pixels computed from any raw value ``>= white``: the 2x2 block for
``"half"``; for ``"linear"``, the 3x3 neighbourhood that the interpolation reads.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import cv2
import numpy as np
import rawpy
import tifffile

from ps_lab.errors import DatasetError
from ps_lab.io.files import utf8_path

__all__ = ["DEMOSAIC_MODES", "RAW_SUFFIXES", "RawImage", "is_raw_file", "load_raw", "read_exposure"]

RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".nef", ".arw")
DEMOSAIC_MODES = ("half", "linear")

# LibRaw colour indices in raw_colors: 0 = R, 1 = G, 2 = B, 3 = second G.
_RED, _GREEN, _BLUE, _GREEN2 = 0, 1, 2, 3


@dataclass(frozen=True)
class RawImage:
    """A RAW frame in linear, normalised units.

    Attributes
    ----------
    image : ndarray of shape (H, W, 3), float32
        ``(raw - black) / (white - black)`` per channel: 1.0 is the white level.
    saturated : ndarray of shape (H, W), bool
        True where any raw value that went into the pixel reached the white level.
    black_level : ndarray of shape (3,), float64
        Black level of the R, G, B channels (G: mean of the two greens).
    white_level : float
        White (saturation) level in raw units.
    exposure_s : float or None
        Exposure time stored in the file, if any.

    """

    image: np.ndarray
    saturated: np.ndarray
    black_level: np.ndarray
    white_level: float
    exposure_s: float | None


def is_raw_file(path: str | PathLike[str]) -> bool:
    """Return True when the file name has one of :data:`RAW_SUFFIXES` (any case)."""
    return Path(path).suffix.lower() in RAW_SUFFIXES


def load_raw(path: str | PathLike[str], *, demosaic: str = "half") -> RawImage:
    """Load a camera RAW file as a linear, normalised RGB image.

    Parameters
    ----------
    path : path-like
        A RAW file (DNG, CR2, CR3, NEF, ARW, or anything else LibRaw reads) with a 2x2 Bayer CFA.
    demosaic : {"half", "linear"}
        ``"half"``: 2x2 binning to an (H/2, W/2, 3) image; ``"linear"``: bilinear demosaic to
        (H, W, 3). H, W are the visible raw size (an odd row or column is dropped for ``"half"``).

    Returns
    -------
    RawImage

    Raises
    ------
    DatasetError
        Naming the file, when it is missing, truncated, not a RAW file, or not a Bayer sensor.
    ValueError
        On an unknown ``demosaic`` mode.

    """
    if demosaic not in DEMOSAIC_MODES:
        raise ValueError(f"demosaic must be one of {DEMOSAIC_MODES}, got {demosaic!r}")
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: no such RAW file")
    if path.stat().st_size == 0:
        raise DatasetError(f"{path}: empty file, not a RAW image")
    if path.suffix.lower() == ".dng":
        _check_tiff_not_truncated(path)

    raw, colors, blacks, white, shutter = _read_with_rawpy(path)
    if raw.ndim != 2 or raw.shape[0] < 2 or raw.shape[1] < 2:
        raise DatasetError(f"{path}: no Bayer raw data (shape {raw.shape})")
    exposure_s = _exposure_from_tiff(path) if path.suffix.lower() == ".dng" else None
    if exposure_s is None and shutter is not None and shutter > 0:
        # rawpy reports a float32; 7 significant digits recover the decimal value written.
        exposure_s = float(f"{shutter:.7g}")

    white_f = float(white)
    if not np.all(white_f > blacks):
        raise DatasetError(f"{path}: white level {white_f} not above black levels {blacks}")
    tile = _bayer_tile(colors, path)
    if demosaic == "half":
        image, saturated = _bin_half(raw, tile, blacks, white)
    else:
        image, saturated = _demosaic_linear(raw, tile, blacks, white)
    black_rgb = np.array(
        [blacks[_RED], 0.5 * (blacks[_GREEN] + blacks[_GREEN2]), blacks[_BLUE]], dtype=np.float64
    )
    return RawImage(
        image=image,
        saturated=saturated,
        black_level=black_rgb,
        white_level=white_f,
        exposure_s=exposure_s,
    )


def read_exposure(path: str | PathLike[str]) -> float | None:
    """Return the exposure time (s) stored in a RAW file, or None when absent or unreadable.

    Reads metadata only (the ExposureTime rational of a DNG/TIFF, else LibRaw's shutter value);
    never raises for a bad file.
    """
    path = Path(path)
    if not path.is_file():
        return None
    exposure = _exposure_from_tiff(path)
    if exposure is not None:
        return exposure
    try:
        with _open_raw(path) as handle:
            shutter = float(handle.other.shutter_speed)
    except (rawpy.LibRawError, AttributeError, OSError):
        return None
    return float(f"{shutter:.7g}") if math.isfinite(shutter) and shutter > 0 else None


def _open_raw(path: Path):
    """``rawpy.imread`` for any path (LibRaw takes names as UTF-8 text only; else a stream)."""
    if utf8_path(path):
        return rawpy.imread(str(path))
    with open(path, "rb") as stream:
        return rawpy.imread(stream)


def _read_with_rawpy(
    path: Path,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, float | None]:
    try:
        with _open_raw(path) as handle:
            raw = np.array(handle.raw_image_visible, copy=True)
            colors = np.array(handle.raw_colors_visible, copy=True)
            blacks = np.asarray(handle.black_level_per_channel, dtype=np.float64)
            white = int(handle.white_level)
            num_colors = int(handle.num_colors)
            try:
                shutter: float | None = float(handle.other.shutter_speed)
            except (AttributeError, rawpy.LibRawError):  # older rawpy has no ``other``
                shutter = None
    except rawpy.LibRawFileUnsupportedError:
        raise DatasetError(f"{path}: not a RAW file LibRaw can read") from None
    except rawpy.LibRawIOError:
        raise DatasetError(f"{path}: truncated or unreadable RAW file") from None
    except rawpy.LibRawError as exc:
        raise DatasetError(f"{path}: corrupt RAW file ({_libraw_message(exc)})") from None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except (RuntimeError, ValueError) as exc:  # e.g. "RAW image is not flat" (LinearRaw DNG)
        raise DatasetError(
            f"{path}: unsupported RAW layout ({exc}); need a Bayer CFA mosaic"
        ) from None
    if num_colors != 3 or blacks.shape != (4,):
        raise DatasetError(f"{path}: unsupported sensor ({num_colors} colours); need a Bayer CFA")
    return raw, colors, blacks, white, shutter


def _libraw_message(exc: Exception) -> str:
    text = exc.args[0] if exc.args else exc
    return text.decode(errors="replace") if isinstance(text, bytes) else str(text)


@contextmanager
def _quiet_tifffile() -> Iterator[None]:
    """Silence tifffile's log while probing a file that may be broken or not TIFF at all.

    The probe's verdict is reported as one clear error (or ignored); tifffile's own warnings
    would add stray lines to the CLI's one-line error.
    """
    logger = logging.getLogger("tifffile")
    previous = logger.level
    logger.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        logger.setLevel(previous)


def _check_tiff_not_truncated(path: Path) -> None:
    """Fail early (and quietly: LibRaw prints to stderr) when image data runs past the file end."""
    size = path.stat().st_size
    try:
        with _quiet_tifffile(), tifffile.TiffFile(path) as tif:
            for page in tif.pages:
                offsets = getattr(page, "dataoffsets", ()) or ()
                counts = getattr(page, "databytecounts", ()) or ()
                for offset, count in zip(offsets, counts, strict=False):
                    if offset + count > size:
                        raise DatasetError(
                            f"{path}: truncated RAW file ({size} bytes, image data needs "
                            f"{offset + count})"
                        )
    except DatasetError:
        raise
    except Exception:  # noqa: BLE001 - not parseable as TIFF: let LibRaw give the verdict
        return


def _exposure_from_tiff(path: Path) -> float | None:
    """Read ExposureTime (33434) from IFD0 or the EXIF IFD as an exact rational."""
    try:
        with _quiet_tifffile(), tifffile.TiffFile(path) as tif:
            page = tif.pages.first
            tag = page.tags.get(33434)
            value = tag.value if tag is not None else None
            if value is None:
                exif = page.tags.get(34665)
                if exif is not None and isinstance(exif.value, dict):
                    value = exif.value.get("ExposureTime")
    except Exception:  # noqa: BLE001 - metadata is optional; rawpy's value is the fallback
        return None
    if isinstance(value, tuple) and len(value) == 2 and value[1]:
        value = value[0] / value[1]
    try:
        result = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return result if math.isfinite(result) and result > 0 else None


def _bayer_tile(colors: np.ndarray, path: Path) -> np.ndarray:
    """Return the 2x2 tile of LibRaw colour indices (second green as 3); reject non-Bayer CFAs."""
    height, width = colors.shape
    tile = np.array(colors[:2, :2], dtype=np.intp)
    for r in range(2):
        for c in range(2):
            if not np.all(colors[r::2, c::2] == tile[r, c]):
                raise DatasetError(f"{path}: CFA is not a 2x2 Bayer pattern")
    found = sorted(tile.ravel().tolist())
    if found not in ([_RED, _GREEN, _GREEN, _BLUE], [_RED, _GREEN, _BLUE, _GREEN2]):
        raise DatasetError(f"{path}: CFA is not an RGB Bayer pattern (tile {tile.tolist()})")
    return tile


def _normalised_plane(
    raw: np.ndarray, r: int, c: int, black: float, white: int, height: int, width: int
) -> tuple[np.ndarray, np.ndarray]:
    """One CFA position's samples as (raw - black) / (white - black) in float32, and clipping."""
    samples = raw[r:height:2, c:width:2]
    values = (samples.astype(np.float32) - np.float32(black)) / np.float32(white - black)
    return values, samples >= white


def _positions(tile: np.ndarray) -> dict[str, list[tuple[int, int]]]:
    positions: dict[str, list[tuple[int, int]]] = {"r": [], "g": [], "b": []}
    for r in range(2):
        for c in range(2):
            key = {_RED: "r", _BLUE: "b"}.get(int(tile[r, c]), "g")
            positions[key].append((r, c))
    return positions


def _bin_half(
    raw: np.ndarray, tile: np.ndarray, blacks: np.ndarray, white: int
) -> tuple[np.ndarray, np.ndarray]:
    height, width = raw.shape[0] // 2 * 2, raw.shape[1] // 2 * 2
    image = np.empty((height // 2, width // 2, 3), dtype=np.float32)
    saturated = np.zeros((height // 2, width // 2), dtype=bool)
    for channel, key in enumerate("rgb"):
        total = None
        members = _positions(tile)[key]
        for r, c in members:
            values, clipped = _normalised_plane(raw, r, c, blacks[tile[r, c]], white, height, width)
            total = values if total is None else total + values
            saturated |= clipped
        assert total is not None
        image[..., channel] = total if len(members) == 1 else total * np.float32(0.5)
    return image, saturated


def _demosaic_linear(
    raw: np.ndarray, tile: np.ndarray, blacks: np.ndarray, white: int
) -> tuple[np.ndarray, np.ndarray]:
    height, width = raw.shape
    kernel = np.array([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]], dtype=np.float32)
    image = np.empty((height, width, 3), dtype=np.float32)
    clipped = np.zeros((height, width), dtype=np.uint8)
    for channel, key in enumerate("rgb"):
        values = np.zeros((height, width), dtype=np.float32)
        sampled = np.zeros((height, width), dtype=np.float32)
        for r, c in _positions(tile)[key]:
            plane, plane_clipped = _normalised_plane(
                raw, r, c, blacks[tile[r, c]], white, height, width
            )
            values[r::2, c::2] = plane
            sampled[r::2, c::2] = 1.0
            clipped[r::2, c::2] |= plane_clipped
        # Normalised convolution with zero padding: the weighted mean of the available samples.
        sums = cv2.filter2D(values, -1, kernel, borderType=cv2.BORDER_CONSTANT)
        weights = cv2.filter2D(sampled, -1, kernel, borderType=cv2.BORDER_CONSTANT)
        image[..., channel] = np.where(sampled > 0, values, sums / np.maximum(weights, 1e-12))
    saturated = cv2.dilate(
        clipped, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0
    )
    return image, saturated.astype(bool)
