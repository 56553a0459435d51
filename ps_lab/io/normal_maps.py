"""Normal maps other tools read: 16-bit PNG and float32 OpenEXR.

Both hold the normals in the camera frame x right, y up, z toward the camera (the convention of
OpenGL normal maps; ``convention="directx"`` stores y down instead, as DirectX, Unreal and 3ds Max
expect): ``normal16.png`` as RGB = (n + 1) / 2 scaled to 0..65535 (the same mapping as
the 8-bit ``normal.png``), ``normals.exr`` as float32 channels R, G, B = x, y, z (zeros where there
is no normal).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import OpenEXR

from ps_lab.errors import OutputError
from ps_lab.io.codecs import imwrite
from ps_lab.io.files import utf8_path

__all__ = [
    "CONVENTIONS",
    "normal16_picture",
    "read_normals_exr",
    "to_convention",
    "write_normal16",
    "write_normals_exr",
]

#: Normal-map conventions: the axis of green (y) points up (OpenGL) or down (DirectX).
CONVENTIONS = ("opengl", "directx")
#: The result files' OpenEXR compression (see :func:`write_rgb_exr`).
EXR_COMPRESSION = OpenEXR.RLE_COMPRESSION
#: Image rows per band of :func:`normal16_picture`'s work arrays.
PICTURE_ROWS = 64


def to_convention(normals: np.ndarray, convention: str = "opengl") -> np.ndarray:
    """Camera-frame normals (y up) in a normal-map convention: ``directx`` negates y."""
    if convention not in CONVENTIONS:
        raise ValueError(f"normal-map convention must be one of {CONVENTIONS}, got {convention!r}")
    if convention == "opengl":
        return np.asarray(normals)
    return np.asarray(normals) * np.array([1.0, -1.0, 1.0], dtype=np.asarray(normals).dtype)


def normal16_picture(
    normals: np.ndarray, mask: np.ndarray, convention: str = "opengl"
) -> np.ndarray:
    """Colour-code normals as 16-bit RGB = (n + 1) / 2 · 65535, black outside the mask.

    Parameters
    ----------
    normals : ndarray of shape (H, W, 3)
        Camera frame (y up).
    mask : ndarray of shape (H, W), bool
    convention : {"opengl", "directx"}
        See :func:`to_convention`.

    Returns
    -------
    ndarray of shape (H, W, 3), uint16, RGB
    """
    return _normal16(normals, mask, convention, bgr=False)


def _normal16(normals: np.ndarray, mask: np.ndarray, convention: str, *, bgr: bool) -> np.ndarray:
    """:func:`normal16_picture` in RGB or (``bgr``, OpenCV's order) BGR channel order.

    Computed by bands of :data:`PICTURE_ROWS` rows with the whole-image expression's operations
    and types (float32 normals stay float32), so the temporaries stay in the cache and the BGR
    picture needs no reordered copy; the pixels are those of the whole-image expression.
    """
    normals = np.asarray(normals)
    outside = ~np.asarray(mask, bool)
    picture = np.empty(normals.shape, np.uint16)
    for start in range(0, normals.shape[0], PICTURE_ROWS):
        rows = slice(start, start + PICTURE_ROWS)
        band = to_convention(normals[rows], convention)
        band = np.clip(np.rint((band + 1.0) * 0.5 * 65535.0), 0, 65535).astype(np.uint16)
        band[outside[rows]] = 0
        picture[rows] = band[..., ::-1] if bgr else band
    return picture


def write_normal16(
    path: Path, normals: np.ndarray, mask: np.ndarray, convention: str = "opengl"
) -> None:
    """Write ``normal16.png`` (see :func:`normal16_picture`).

    OpenCV's PNG encoder with its default settings: in OpenCV 5 they are its fastest (explicit
    zlib levels 1-3 were 2-4x slower on a 4 MP normal map, level 0 no faster and 40 % larger).
    """
    if not imwrite(path, _normal16(normals, mask, convention, bgr=True)):
        raise OutputError(f"{path}: OpenCV could not write the PNG")


def write_normals_exr(path: Path, normals: np.ndarray, convention: str = "opengl") -> None:
    """Write float32 normals (H, W, 3) as an OpenEXR file with channels R, G, B = x, y, z.

    With ``convention="directx"`` G holds -y (see :func:`to_convention`).
    """
    write_rgb_exr(path, to_convention(np.asarray(normals, np.float32), convention))


def write_rgb_exr(path: Path, rgb: np.ndarray) -> None:
    """Write a float image (H, W, 3) as OpenEXR float channels R, G, B (RLE, scanlines).

    The one OpenEXR writer of the result files (normals, colour albedo, relit pictures); NaN
    is written as 0 (and +-inf as the largest float32, :func:`numpy.nan_to_num`), copying the
    image only when it holds such a value. A name that is not UTF-8 is encoded in memory and
    written from Python.

    RLE is lossless and read by every OpenEXR reader (it is in the format since 1.0): on a 4 MP
    normal map it wrote in a quarter of ZIP's time and its files were 5 % larger (float
    normals' low mantissa bits do not compress; both pack the zeros outside the object).
    """
    pixels = np.asarray(rgb, np.float32)
    if not np.isfinite(pixels).all():
        pixels = np.nan_to_num(pixels)
    pixels = np.ascontiguousarray(pixels)
    header = {"type": OpenEXR.scanlineimage, "compression": EXR_COMPRESSION}
    try:
        with OpenEXR.File(header, {"RGB": pixels}) as exr:
            if utf8_path(path):
                exr.write(str(path))
            else:  # the library takes UTF-8 names only: encode in memory, write from Python
                buffer = io.BytesIO()
                exr.write(buffer)
                Path(path).write_bytes(buffer.getvalue())
    except (OSError, RuntimeError) as exc:
        raise OutputError(f"{path}: cannot write the OpenEXR file ({exc})") from None


def read_normals_exr(path: Path) -> np.ndarray:
    """Read an OpenEXR normal map written by :func:`write_normals_exr`: (H, W, 3) float32."""
    with OpenEXR.File(str(path)) as exr:
        channels = exr.channels()
        if "RGB" in channels:
            return np.asarray(channels["RGB"].pixels, np.float32)
        return np.stack([channels[c].pixels for c in "RGB"], axis=-1).astype(np.float32)
