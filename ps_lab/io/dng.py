"""Write real DNG files (Bayer CFA, uncompressed) with tifffile.

The simulated camera writes its frames with :func:`write_dng`, and tests write DNGs whose mosaic
they control, so the RAW loader can be checked against exact values. The files follow the
DNG 1.4 specification closely enough for LibRaw (and so rawpy) to read them:

* IFD0 holds the raw image itself (``NewSubfileType`` 0, uncompressed, one strip,
  ``PhotometricInterpretation`` 32803 = CFA, 16 bits per sample);
* ``CFARepeatPatternDim`` (33421) = 2, 2 and ``CFAPattern`` (33422) with 0 = red, 1 = green,
  2 = blue, row by row (RGGB = 0 1 1 2);
* ``DNGVersion`` (50706) 1.4.0.0, ``DNGBackwardVersion`` (50707) 1.1.0.0,
  ``UniqueCameraModel`` (50708), ``Make`` (271), ``Model`` (272);
* ``BlackLevelRepeatDim`` (50713) = 2, 2 with four ``BlackLevel`` (50714) values, one per CFA
  position (all equal unless a per-position list is given), ``WhiteLevel`` (50717);
* ``ColorMatrix1`` (50721, identity by default), ``CalibrationIlluminant1`` (50778, D65) and
  ``AsShotNeutral`` (50728, 1 1 1): colour is irrelevant to photometric stereo, but LibRaw
  wants a colour description;
* ``ExposureTime`` (33434) as a RATIONAL in IFD0 (TIFF/EP allows it there; LibRaw reads it
  into ``rawpy.RawPy.other.shutter_speed`` and :func:`ps_lab.io.raw.load_raw` reads the
  exact rational back with tifffile).

LibRaw refuses images narrower or lower than 22 pixels, so :func:`write_dng` does too.
"""

from __future__ import annotations

from collections.abc import Sequence
from fractions import Fraction
from os import PathLike
from pathlib import Path

import numpy as np
import tifffile

__all__ = ["CFA_PATTERNS", "MIN_DNG_SIZE", "write_dng"]

#: CFA layouts of a 2x2 Bayer tile, row by row; 0 = red, 1 = green, 2 = blue (TIFF/EP codes).
CFA_PATTERNS: dict[str, tuple[int, int, int, int]] = {
    "RGGB": (0, 1, 1, 2),
    "BGGR": (2, 1, 1, 0),
    "GRBG": (1, 0, 2, 1),
    "GBRG": (1, 2, 0, 1),
}

#: LibRaw treats smaller images as "not a RAW file".
MIN_DNG_SIZE = 22

_PHOTOMETRIC_CFA = 32803
_RATIONAL_DENOMINATOR_LIMIT = 2**31 - 1


def _rational(value: float) -> tuple[int, int]:
    """Return ``(numerator, denominator)`` of the closest uint32 fraction to a positive value."""
    frac = Fraction(value).limit_denominator(_RATIONAL_DENOMINATOR_LIMIT)
    while frac.numerator > 2**32 - 1:
        frac = Fraction(value).limit_denominator(max(1, frac.denominator // 2))
    return frac.numerator, frac.denominator


def _srational_flat(values: Sequence[float], denominator: int = 10000) -> tuple[int, ...]:
    return tuple(x for v in values for x in (int(round(v * denominator)), denominator))


def write_dng(
    path: str | PathLike[str],
    mosaic: np.ndarray,
    *,
    black_level: int | Sequence[int],
    white_level: int,
    cfa: str = "RGGB",
    exposure_s: float | None = None,
    make: str = "ps-lab",
    model: str = "simulated camera",
    unique_camera_model: str | None = None,
    color_matrix: Sequence[float] | None = None,
    as_shot_neutral: Sequence[float] = (1.0, 1.0, 1.0),
) -> None:
    """Write a Bayer mosaic as an uncompressed DNG file.

    Parameters
    ----------
    path : path-like
        Target file (written in place; callers that need atomicity write a temporary name
        and rename it).
    mosaic : ndarray of shape (H, W), uint16
        Raw sensor values including the black level; H and W even and at least
        :data:`MIN_DNG_SIZE`.
    black_level : int or sequence of 4 ints
        Black level, for all CFA positions or one per position of the 2x2 tile, row by row.
    white_level : int
        Saturation value (e.g. 16383 for a 14-bit sensor); must exceed every black level and
        fit in uint16.
    cfa : {"RGGB", "BGGR", "GRBG", "GBRG"}
        Colour of the 2x2 tile's pixels, row by row.
    exposure_s : float, optional
        Exposure time in seconds, stored as the ExposureTime rational.
    make, model, unique_camera_model : str
        Identification tags (``unique_camera_model`` defaults to ``"<make> <model>"``).
    color_matrix : sequence of 9 floats, optional
        ColorMatrix1 (XYZ to camera), identity by default.
    as_shot_neutral : sequence of 3 floats
        AsShotNeutral (camera white balance), 1 1 1 by default.

    Raises
    ------
    ValueError
        On a mosaic of the wrong dtype or shape, an unknown CFA, or inconsistent levels.

    """
    mosaic = np.asarray(mosaic)
    if mosaic.dtype != np.uint16:
        raise ValueError(f"mosaic must be uint16, got {mosaic.dtype}")
    if mosaic.ndim != 2:
        raise ValueError(f"mosaic must be 2-D (H, W), got shape {mosaic.shape}")
    height, width = mosaic.shape
    if height % 2 or width % 2:
        raise ValueError(f"mosaic height and width must be even, got {mosaic.shape}")
    if height < MIN_DNG_SIZE or width < MIN_DNG_SIZE:
        raise ValueError(
            f"mosaic must be at least {MIN_DNG_SIZE}x{MIN_DNG_SIZE} (LibRaw's minimum), "
            f"got {mosaic.shape}"
        )
    cfa = cfa.upper()
    if cfa not in CFA_PATTERNS:
        raise ValueError(f"unknown CFA {cfa!r}; expected one of {sorted(CFA_PATTERNS)}")
    blacks = (
        [int(black_level)] * 4 if np.ndim(black_level) == 0 else [int(b) for b in black_level]  # type: ignore[union-attr]
    )
    if len(blacks) != 4:
        raise ValueError(f"black_level must be one value or four, got {len(blacks)}")
    white_level = int(white_level)
    if not 0 < white_level <= 65535:
        raise ValueError(f"white_level must be in 1..65535, got {white_level}")
    if min(blacks) < 0 or max(blacks) >= white_level:
        raise ValueError(f"black levels {blacks} must be in 0..white_level-1 ({white_level - 1})")
    if color_matrix is None:
        color_matrix = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    if len(color_matrix) != 9:
        raise ValueError("color_matrix must have 9 entries")
    if len(as_shot_neutral) != 3 or min(as_shot_neutral) <= 0:
        raise ValueError("as_shot_neutral must be 3 positive values")
    if unique_camera_model is None:
        unique_camera_model = f"{make} {model}"

    # (code, dtype, count, value, writeonce); tifffile writes tags sorted by code.
    tags: list[tuple[int, str, int, object, bool]] = [
        (271, "s", 0, make, True),
        (272, "s", 0, model, True),
        (33421, "H", 2, (2, 2), True),
        (33422, "B", 4, CFA_PATTERNS[cfa], True),
        (50706, "B", 4, (1, 4, 0, 0), True),
        (50707, "B", 4, (1, 1, 0, 0), True),
        (50708, "s", 0, unique_camera_model, True),
        (50713, "H", 2, (2, 2), True),
        (50714, "I", 4, tuple(blacks), True),
        (50717, "I", 1, (white_level,), True),
        (50721, "2i", 9, _srational_flat(color_matrix), True),
        (50728, "2I", 3, tuple(x for v in as_shot_neutral for x in _rational(v)), True),
        (50778, "H", 1, (21,), True),
    ]
    if exposure_s is not None:
        if not np.isfinite(exposure_s) or exposure_s <= 0:
            raise ValueError(f"exposure_s must be positive, got {exposure_s}")
        tags.append((33434, "2I", 1, _rational(float(exposure_s)), True))

    tifffile.imwrite(
        Path(path),
        mosaic,
        photometric=_PHOTOMETRIC_CFA,
        compression=None,
        rowsperstrip=height,
        subfiletype=0,
        metadata=None,
        software=False,
        extratags=tags,
    )
