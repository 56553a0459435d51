"""The LEDs' beams and flat-field of a near-light calibration (``light_axes.txt``,
``flat_field.npz``).

Written by ``ps-lab calibrate --flat-field`` (:mod:`ps_lab.calibration._leds`), read by
``ps-lab reconstruct --led-model``. Scene frame of :mod:`ps_lab.geometry` (pixel units).
"""

from __future__ import annotations

import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from ps_lab.errors import DatasetError
from ps_lab.io.light_files import MAX_COORDINATE
from ps_lab.io.light_files import _read_table as read_table

__all__ = ["FlatField", "read_flat_field", "read_light_axes", "write_flat_field"]

LIGHT_AXES = "light_axes.txt"
FLAT_FIELD = "flat_field.npz"


@dataclass(frozen=True)
class FlatField:
    """Per-LED gains on a grid of the board's plane (:func:`fit_flat_field`).

    Attributes
    ----------
    gains : ndarray of shape (n, gh, gw)
        Measured over predicted irradiance on the board (the predicted one: the isotropic model
        times the light's intensity at the origin), one common scale.
    x : ndarray of shape (gw,)
        Scene x of the grid's columns (increasing).
    y : ndarray of shape (gh,)
        Scene y of the grid's rows (decreasing: image rows go down).
    height : float
        The board's height above the spheres' plane.
    positions : ndarray of shape (n, 3)
        The LED positions the gains were measured with.
    """

    gains: np.ndarray
    x: np.ndarray
    y: np.ndarray
    height: float
    positions: np.ndarray

    def at(self, points: np.ndarray) -> np.ndarray:
        """Gains (m, n) at surface points (m, 3).

        Each LED's gain is looked up where its ray through the point meets the board (bilinear
        between grid nodes, the edge value beyond them); a light without a position: below the
        point.
        """
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        pos = self.positions
        out = np.ones((len(pts), len(pos)))
        step_x = self.x[1] - self.x[0] if len(self.x) > 1 else 1.0
        step_y = self.y[1] - self.y[0] if len(self.y) > 1 else -1.0
        grids = _extended(np.asarray(self.gains, np.float64))
        for j, p in enumerate(pos):
            if not np.all(np.isfinite(p)):
                q = pts[:, :2]
            else:
                dz = pts[:, 2] - p[2]
                t = (self.height - p[2]) / np.where(np.abs(dz) > 1e-9, dz, 1e-9)
                q = p[None, :2] + t[:, None] * (pts[:, :2] - p[None, :2])
            col = (q[:, 0] - self.x[0]) / step_x + _MARGIN
            row = (q[:, 1] - self.y[0]) / step_y + _MARGIN
            out[:, j] = ndimage.map_coordinates(grids[j], [row, col], order=1, mode="nearest")
        return out


# Grid nodes added on every side, extrapolated linearly: a point above the board (an object on
# it) looks its low LEDs' gains up beyond the frame's edge.
_MARGIN = 8


def _extended(gains: np.ndarray) -> np.ndarray:
    """(n, gh + 2M, gw + 2M): the gains continued linearly past the grid's edges (floored)."""
    m = _MARGIN
    steps = np.arange(1, m + 1, dtype=np.float64)
    out = gains
    for axis in (1, 2):
        if out.shape[axis] < 2:
            out = np.concatenate([np.repeat(out, m, axis=axis), out,
                                  np.repeat(out, m, axis=axis)], axis=axis)
            continue
        first, second = np.take(out, [0], axis=axis), np.take(out, [1], axis=axis)
        last, before = np.take(out, [-1], axis=axis), np.take(out, [-2], axis=axis)
        shape = [1, 1, 1]
        shape[axis] = m
        k = steps.reshape(shape)
        low = first + (first - second) * np.flip(k, axis=axis)
        high = last + (last - before) * k
        out = np.concatenate([low, out, high], axis=axis)
    return np.maximum(out, 0.05 * float(np.median(gains)))


def write_flat_field(path: Path, flat: FlatField) -> None:
    """Write ``flat_field.npz`` (gains, grid axes, board height, LED positions)."""
    with open(path, "wb") as handle:
        np.savez_compressed(handle, gains=flat.gains, x=flat.x, y=flat.y,
                            height=np.array(flat.height), positions=flat.positions)


#: Gains outside this range are not a board's measurement (the writer scales their median to 1).
GAIN_RANGE = (1e-6, 1e6)


#: The most values one array of the file may hold (a forged header is refused before reading).
MAX_VALUES = 1 << 27


def _header(data: np.lib.npyio.NpzFile, name: str) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of the archive's array ``name``, from its header alone."""
    with data.zip.open(f"{name}.npy") as member:
        version = np.lib.format.read_magic(member)
        read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                else np.lib.format.read_array_header_2_0)
        shape, _, dtype = read(member)
    return shape, dtype


def _real_array(path: Path, data, name: str, ndim: int) -> np.ndarray:
    """``data[name]`` as float64 with ``ndim`` dimensions, else a DatasetError naming both.

    Type, shape and size are checked on the array's header before its values are read.
    """
    if name not in data.files:
        raise DatasetError(f"{path}: not a flat-field file (no array '{name}')")
    try:
        shape, dtype = _header(data, name)
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as exc:
        raise DatasetError(f"{path}: array '{name}' cannot be read ({exc})") from None
    if dtype.kind not in "fiu":
        raise DatasetError(f"{path}: array '{name}' holds {dtype} values, not real numbers")
    if len(shape) != ndim:
        want = {0: "one number", 1: "a 1-D axis", 2: "a 2-D table", 3: "a 3-D stack"}[ndim]
        raise DatasetError(f"{path}: array '{name}' has shape {shape}, expected {want}")
    if int(np.prod(shape, dtype=np.float64)) > MAX_VALUES:
        raise DatasetError(f"{path}: array '{name}' claims shape {shape}, more values than a "
                           f"flat-field holds (at most {MAX_VALUES})")
    try:
        raw = data[name]
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise DatasetError(f"{path}: array '{name}' cannot be read ({exc})") from None
    return np.asarray(raw, np.float64)


def _check_axis(path: Path, name: str, axis: np.ndarray, length: int, sign: float) -> None:
    """A grid axis: ``length`` finite nodes, strictly increasing (``sign`` +1) or decreasing."""
    if len(axis) != length:
        raise DatasetError(f"{path}: array '{name}' has {len(axis)} nodes, the gains' grid "
                           f"{length}")
    if not np.all(np.isfinite(axis)) or np.any(np.abs(axis) > MAX_COORDINATE):
        raise DatasetError(f"{path}: array '{name}' must be finite pixel coordinates "
                           f"(|value| <= {MAX_COORDINATE:g})")
    if length > 1 and not np.all(np.diff(axis) * sign > 0):
        way = "increasing" if sign > 0 else "decreasing"
        raise DatasetError(f"{path}: array '{name}' must be strictly {way}")


def read_flat_field(path: Path, count: int | None = None) -> FlatField:
    """Read ``flat_field.npz``; a DatasetError naming the file and the array at fault.

    Every array is checked by shape, type and value before use: ``gains`` (n, gh, gw) finite
    in :data:`GAIN_RANGE`, ``x`` (gw,) increasing and ``y`` (gh,) decreasing,
    ``height`` one finite number below every placed LED, ``positions`` (n, 3) finite rows or
    all-NaN rows (a light too far to place).
    """
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise DatasetError(f"{path}: not a flat-field file ({exc})") from None
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise DatasetError(f"{path}: not a flat-field file (one array, not an .npz archive)")
    with data:
        gains = _real_array(path, data, "gains", 3)
        x, y = _real_array(path, data, "x", 1), _real_array(path, data, "y", 1)
        height_array = _real_array(path, data, "height", 0)
        positions = _real_array(path, data, "positions", 2)
    n, gh, gw = gains.shape
    if n == 0 or gh == 0 or gw == 0:
        raise DatasetError(f"{path}: array 'gains' is empty (shape {gains.shape})")
    if count is not None and n != count:
        raise DatasetError(f"{path}: array 'gains' holds {n} lights, the dataset has {count}")
    low, high = GAIN_RANGE
    if not np.all(np.isfinite(gains)):
        raise DatasetError(f"{path}: array 'gains' contains NaN or infinite values")
    if np.any(gains < low) or np.any(gains > high):
        raise DatasetError(f"{path}: array 'gains' must lie in [{low:g}, {high:g}] "
                           f"(found {gains.min():.3g} .. {gains.max():.3g})")
    _check_axis(path, "x", x, gw, 1.0)
    _check_axis(path, "y", y, gh, -1.0)
    if positions.shape != (n, 3):
        raise DatasetError(f"{path}: array 'positions' has shape {positions.shape}, expected "
                           f"({n}, 3)")
    finite = np.isfinite(positions)
    placed = finite.all(axis=1)
    unplaced = np.isnan(positions).all(axis=1)
    if not np.all(placed | unplaced) or np.any(np.abs(positions[placed]) > MAX_COORDINATE):
        row = int(np.flatnonzero(~(placed | unplaced)
                                 | np.any(np.abs(np.where(finite, positions, 0.0))
                                          > MAX_COORDINATE, axis=1))[0])
        raise DatasetError(f"{path}: array 'positions' row {row + 1} must be three finite "
                           f"coordinates (|value| <= {MAX_COORDINATE:g}) or all NaN")
    height = float(height_array)
    if not np.isfinite(height) or abs(height) > MAX_COORDINATE:
        raise DatasetError(f"{path}: array 'height' must be one finite number of pixels")
    if placed.any() and height >= positions[placed, 2].min():
        j = int(np.flatnonzero(placed)[np.argmin(positions[placed, 2])])
        raise DatasetError(f"{path}: array 'height': the board plane at z={height:g} px is not "
                           f"below LED {j + 1} (z={positions[j, 2]:g} px)")
    return FlatField(gains.astype(np.float32), x, y, height, positions)


def read_light_axes(path: Path, count: int | None = None,
                    positions: np.ndarray | None = None) -> np.ndarray:
    """Read ``light_axes.txt``: each LED's unit optical axis ``ax ay az`` per row.

    With ``positions`` (n, 3) (NaN rows: lights not placed), each placed LED's axis must point
    into the lower half-space of its LED (toward the scene below it): an axis pointing up or
    sideways gives a beam that never reaches the object.
    """
    axes = read_table(path, (3,))
    if count is not None and len(axes) != count:
        raise DatasetError(f"{path}: {len(axes)} rows of 'ax ay az', the dataset has {count} "
                           "lights")
    scale = np.max(np.abs(axes), axis=1, keepdims=True)
    if np.any(scale[:, 0] <= 0):
        row = int(np.flatnonzero(scale[:, 0] <= 0)[0])
        raise DatasetError(f"{path}: row {row + 1}: the axis is the zero vector")
    unit = axes / scale  # scaled first: no overflow in the norm of huge rows
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    if positions is not None:
        placed = np.isfinite(positions).all(axis=1)
        up = placed & (unit[:, 2] >= 0.0)
        if up.any():
            row = int(np.flatnonzero(up)[0])
            raise DatasetError(f"{path}: row {row + 1}: the axis points up or sideways "
                               f"(z={unit[row, 2]:.3g}), away from the scene below the LED")
    return unit
