"""The LEDs' beams and flat-field of a near-light calibration (``light_axes.txt``,
``flat_field.npz``).

Written by ``ps-lab calibrate --flat-field`` (:mod:`ps_lab.calibration._leds`), read by
``ps-lab reconstruct --led-model``. Scene frame of :mod:`ps_lab.geometry` (pixel units).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from ps_lab.errors import DatasetError

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


def read_flat_field(path: Path, count: int | None = None) -> FlatField:
    """Read ``flat_field.npz``; a DatasetError naming the file when it is not one."""
    try:
        with np.load(path) as data:
            flat = FlatField(np.asarray(data["gains"], np.float32), np.asarray(data["x"], float),
                             np.asarray(data["y"], float), float(data["height"]),
                             np.asarray(data["positions"], float))
    except (OSError, ValueError, KeyError) as exc:
        raise DatasetError(f"{path}: not a flat-field file ({exc})") from None
    n = flat.gains.shape[0]
    if flat.gains.ndim != 3 or flat.positions.shape != (n, 3) or (count is not None
                                                                   and n != count):
        raise DatasetError(f"{path}: gains for {n} lights, expected {count}")
    if not np.all(np.isfinite(flat.gains)) or np.any(flat.gains <= 0):
        raise DatasetError(f"{path}: gains must be finite and positive")
    return flat


def read_light_axes(path: Path, count: int | None = None) -> np.ndarray:
    """Read ``light_axes.txt``: each LED's unit optical axis ``ax ay az`` per row."""
    try:
        axes = np.loadtxt(path, ndmin=2, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: cannot read LED axes ({exc})") from None
    if axes.shape[1] != 3 or (count is not None and len(axes) != count):
        raise DatasetError(f"{path}: expected {count} rows of 'ax ay az', got {axes.shape}")
    norm = np.linalg.norm(axes, axis=1)
    if not np.all(np.isfinite(norm)) or np.any(norm < 1e-6):
        raise DatasetError(f"{path}: every axis must be a finite non-zero vector")
    return axes / norm[:, None]
