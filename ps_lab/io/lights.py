"""Light tables: directions, intensities and, for LEDs at a finite distance, positions.

``light_positions.txt`` (+ ``light_anisotropy.txt``) come from a two-sphere calibration.

``light_directions.txt`` has n rows ``x y z``, ``light_intensities.txt`` n rows of 3 (or 1): the
DiLiGenT text format read by every command and written by calibration and light refinement.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ps_lab.errors import DatasetError
from ps_lab.io.images import check_is_file

log = logging.getLogger("ps_lab.io.dataset")

_UNIT_TOLERANCE = 1e-3


def read_light_directions(path: Path, count: int | None = None) -> np.ndarray:
    """Read ``light_directions.txt``: one row ``x y z`` per light.

    Rows that are not unit length are normalised (with a logged warning).

    Parameters
    ----------
    path : Path
        The text file.
    count : int or None
        Expected number of rows (the number of images).

    Returns
    -------
    ndarray of shape (n, 3), float64, unit rows

    """
    rows = _read_table(path, (3,))
    if count is not None and len(rows) != count:
        raise DatasetError(
            f"{path}: {len(rows)} light directions but the dataset has {count} images"
        )
    norms = np.linalg.norm(rows, axis=1)
    for i, norm in enumerate(norms):
        if norm < 1e-12:
            raise DatasetError(f"{path}: light {i + 1} (row {i + 1}) has zero length")
    off = np.abs(norms - 1.0) > _UNIT_TOLERANCE
    if off.any():
        log.warning(
            "%s: %d light direction(s) not unit length (rows %s); normalised",
            path,
            int(off.sum()),
            ", ".join(str(i + 1) for i in np.flatnonzero(off)[:10]),
        )
    unit = rows / norms[:, None]
    problem = light_geometry_problem(unit)
    if problem is not None:
        raise DatasetError(f"{path}: {problem}")
    return unit


# Smallest singular value over the largest of the unit light directions below which the lights
# count as coplanar: about 0.06 degrees out of their plane.
_COPLANAR_TOLERANCE = 1e-3


def light_geometry_problem(directions: np.ndarray) -> str | None:
    """Say why ``directions`` cannot determine one normal per pixel, or return None.

    Parameters
    ----------
    directions : ndarray of shape (n_lights, 3)
        Unit light directions.

    Returns
    -------
    str or None
        Fewer than 3 lights, all along one line (identical or opposite), or all in one plane
        through the object (the 3x3 normal equations are then singular for every pixel).

    """
    d = np.asarray(directions, dtype=np.float64)
    n = d.shape[0]
    if n < 3:
        return f"{n} light{'' if n == 1 else 's'}: photometric stereo needs at least 3"
    s = np.linalg.svd(d, compute_uv=False)
    if s[1] <= _COPLANAR_TOLERANCE * s[0]:
        return f"all {n} lights point along one line: they must span 3 directions"
    if s[2] <= _COPLANAR_TOLERANCE * s[0]:
        return (
            f"all {n} lights lie in one plane through the object: they must span 3 directions "
            "(normals out of that plane cannot be recovered)"
        )
    return None


def read_light_intensities(path: Path, count: int | None = None) -> np.ndarray:
    """Read ``light_intensities.txt``: one row per light, ``r g b`` or a single value.

    Returns
    -------
    ndarray of shape (n, 3), float64, positive

    """
    check_is_file(path, "light intensities file")
    rows = _read_table(path, (1, 3))
    if count is not None and len(rows) != count:
        raise DatasetError(
            f"{path}: {len(rows)} light intensities but the dataset has {count} images"
        )
    bad = np.flatnonzero(np.any(rows <= 0, axis=1))
    if bad.size:
        raise DatasetError(f"{path}: row {bad[0] + 1}: intensities must be positive")
    return np.repeat(rows, 3, axis=1) if rows.shape[1] == 1 else rows


def read_light_positions(path: Path, count: int | None = None) -> np.ndarray:
    """Read ``light_positions.txt``: one row ``x y z`` per light, or ``nan nan nan``.

    Scene frame of :mod:`ps_lab.geometry` (pixel units: x right, y up, z toward the camera, origin
    at the image centre in the spheres' plane); a NaN row is a light too far to place
    (directional).

    Returns
    -------
    ndarray of shape (n, 3), float64
    """
    rows = _read_table(path, (3,), allow_nan=True)
    if count is not None and len(rows) != count:
        raise DatasetError(
            f"{path}: {len(rows)} light positions but the dataset has {count} images"
        )
    partial = np.isnan(rows).any(axis=1) & ~np.isnan(rows).all(axis=1)
    if partial.any():
        raise DatasetError(f"{path}: row {np.flatnonzero(partial)[0] + 1}: NaN in part of the row")
    return rows


def read_light_anisotropy(path: Path, count: int | None = None) -> np.ndarray:
    """Read ``light_anisotropy.txt``: each LED's ``cos^mu`` exponent, one value per row (>= 0)."""
    rows = _read_table(path, (1,))[:, 0]
    if count is not None and len(rows) != count:
        raise DatasetError(f"{path}: {len(rows)} values but the dataset has {count} images")
    if np.any(rows < 0):
        raise DatasetError(f"{path}: anisotropy exponents must be >= 0")
    return rows


def read_object_outline(path: Path) -> float:
    """Read ``object_outline.txt``: the height of the object's outline (pixels).

    One number: the outline's height above the spheres' plane (the scene frame of near lights;
    ``ps-lab calibrate --object``).
    """
    values = _read_table(path, (1,))
    if values.shape != (1, 1):
        raise DatasetError(f"{path}: expected one number (pixels), got {values.shape[0]} rows")
    return float(values[0, 0])


def read_camera(path: Path) -> tuple[float, float, float]:
    """Read ``camera.txt``: ``f cx cy`` (pixels), the perspective camera of a calibration.

    Focal length > 0 and principal point, of a near-light calibration through a lens.
    """
    values = _read_table(path, (3,))
    if values.shape != (1, 3) or not values[0, 0] > 0:
        raise DatasetError(f"{path}: expected one row 'f cx cy' (pixels) with f > 0")
    return float(values[0, 0]), float(values[0, 1]), float(values[0, 2])


def read_led_intensities(path: Path, count: int | None = None) -> np.ndarray:
    """Read a per-LED intensity file: each LED's relative radiant intensity.

    One row per light (one value, or r g b; W/sr in any unit); returned as (n, 3), all > 0.
    """
    table = _read_table(path, (1, 3))
    if table.shape[1] == 1:
        table = np.repeat(table, 3, axis=1)
    if count is not None and table.shape[0] != count:
        raise DatasetError(f"{path}: {table.shape[0]} rows for {count} lights")
    if np.any(table <= 0):
        raise DatasetError(f"{path}: LED intensities must be > 0")
    return table


def write_light_table(path: Path, rows: np.ndarray) -> None:
    """Write a light table (directions or intensities) in the DiLiGenT text format."""
    rows = np.atleast_2d(np.asarray(rows, dtype=np.float64))
    np.savetxt(path, rows, fmt="%.9f")


def _read_table(path: Path, widths: tuple[int, ...], *, allow_nan: bool = False) -> np.ndarray:
    """Parse a whitespace (or comma) separated numeric table; ``#`` starts a comment."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read file ({exc})") from None
    rows: list[list[float]] = []
    width: int | None = None
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split("#", 1)[0].replace(",", " ").split()
        if not fields:
            continue
        try:
            values = [float(field) for field in fields]
        except ValueError:
            raise DatasetError(
                f"{path}: line {number}: not a row of numbers: {line.strip()!r}"
            ) from None
        if len(values) not in widths:
            expected = " or ".join(str(w) for w in widths)
            raise DatasetError(
                f"{path}: line {number}: expected {expected} numbers, got {len(values)}"
            )
        if width is not None and len(values) != width:
            raise DatasetError(
                f"{path}: line {number}: {len(values)} numbers, earlier rows have {width}"
            )
        width = len(values)
        if not all(np.isfinite(values)) and not (allow_nan and all(np.isnan(values))):
            raise DatasetError(f"{path}: line {number}: value is NaN or infinite")
        rows.append(values)
    if not rows:
        raise DatasetError(f"{path}: file is empty")
    return np.asarray(rows, dtype=np.float64)


def read_lp(path: Path) -> tuple[list[str], np.ndarray]:
    """Read a RelightLab / RTIBuilder ``.lp`` light file.

    The first line is the number of images, then one line ``filename x y z`` per image (the
    direction toward the light, in the same frame as ``light_directions.txt``).

    Returns
    -------
    names : list of str
        The image file names as written (a path; compare by base name).
    directions : ndarray of shape (n, 3), float64, unit rows
    """
    try:
        lines = [line.strip() for line in path.read_text(encoding="utf-8").splitlines()]
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read file ({exc})") from None
    lines = [line for line in lines if line and not line.startswith("#")]
    try:
        count = int(lines[0].split()[0])
    except (IndexError, ValueError):
        raise DatasetError(f"{path}: first line must be the number of images") from None
    if len(lines) - 1 != count:
        raise DatasetError(f"{path}: says {count} images but lists {len(lines) - 1}")
    names: list[str] = []
    rows = np.empty((count, 3))
    for number, line in enumerate(lines[1:], start=2):
        fields = line.rsplit(maxsplit=3)
        try:
            rows[number - 2] = [float(v) for v in fields[1:]]
        except (ValueError, IndexError):
            raise DatasetError(f"{path}: line {number}: expected 'filename x y z'") from None
        if len(fields) != 4 or not np.all(np.isfinite(rows[number - 2])):
            raise DatasetError(f"{path}: line {number}: expected 'filename x y z'")
        names.append(fields[0])
    norms = np.linalg.norm(rows, axis=1)
    if np.any(norms < 1e-12):
        raise DatasetError(f"{path}: a light direction has zero length")
    return names, rows / norms[:, None]


def write_lp(path: Path, names: list[str], directions: np.ndarray) -> None:
    """Write a RelightLab / RTIBuilder ``.lp`` file: the count, then ``filename x y z`` lines."""
    directions = np.atleast_2d(np.asarray(directions, dtype=np.float64))
    if len(names) != len(directions):
        raise ValueError(f"{len(names)} names for {len(directions)} directions")
    lines = [str(len(names))]
    lines += [f"{name} {x:.9f} {y:.9f} {z:.9f}" for name, (x, y, z) in zip(names, directions)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def lp_directions_for(path: Path, image_names: list[str]) -> np.ndarray:
    """Directions of an ``.lp`` file in the order of ``image_names`` (matched by base name)."""
    names, directions = read_lp(path)
    by_name = {Path(name.replace("\\", "/")).name: i for i, name in enumerate(names)}
    order = []
    for image in image_names:
        key = Path(image).name
        if key not in by_name:
            raise DatasetError(f"{path}: no light for image {key}")
        order.append(by_name[key])
    return directions[order]
