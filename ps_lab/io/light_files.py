"""Light tables: directions, intensities and, for LEDs at a finite distance, positions.

``light_positions.txt`` (+ ``light_anisotropy.txt``) come from a two-sphere calibration.

``light_directions.txt`` has n rows ``x y z``, ``light_intensities.txt`` n rows of 3 (or 1): the
DiLiGenT text format read by every command and written by calibration and light refinement.
"""

from __future__ import annotations

import json
import logging
import os
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ps_lab.errors import DatasetError
from ps_lab.io.images import check_is_file, is_supported

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
    norms = _checked_lengths(path, rows, lambda k: f"light {k + 1} (row {k + 1})")
    off = np.abs(norms - 1.0) > _UNIT_TOLERANCE
    if off.any():
        log.warning(
            "%s: %d light direction(s) not unit length (rows %s); normalised",
            path,
            int(off.sum()),
            ", ".join(str(i + 1) for i in np.flatnonzero(off)[:10]),
        )
    return _normalised(path, rows, norms)


def _checked_lengths(
    path: Path, rows: np.ndarray, place: Callable[[int], str], subject: str = ""
) -> np.ndarray:
    """The lengths (n,) of ``rows`` (n, 3); a :class:`DatasetError` where row k has zero length
    (``{path}: {place(k)}{subject} has zero length``) or overflows (``{path}: {place(k)}: ...``)."""
    with np.errstate(over="ignore", invalid="ignore"):
        norms = np.where(np.abs(rows).max(axis=1) > 1e150, np.inf, np.linalg.norm(rows, axis=1))
    for k, norm in enumerate(norms):
        if norm < 1e-12:
            raise DatasetError(f"{path}: {place(k)}{subject} has zero length")
        if not np.isfinite(norm):
            raise DatasetError(
                f"{path}: {place(k)}: light direction too long to normalise (a value beyond 1e150)"
            )
    return norms


def _normalised(path: Path, rows: np.ndarray, norms: np.ndarray) -> np.ndarray:
    """``rows`` divided by their lengths ``norms``; a :class:`DatasetError` where those unit
    directions cannot determine the normals (:func:`light_geometry_problem`)."""
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
    _check_range(path, rows, INTENSITY_RANGE, "intensities")
    return np.repeat(rows, 3, axis=1) if rows.shape[1] == 1 else rows


#: Light intensities (any unit) outside this range overflow the solver's weights (1 / I^2).
INTENSITY_RANGE = (1e-100, 1e100)
#: LED coordinates (pixels) beyond this are not a rig's: the model's arithmetic would overflow.
MAX_COORDINATE = 1e9
#: Beam exponents above this are not an LED's (``cos^mu`` narrower than about 2 degrees).
MAX_EXPONENT = 1000.0


def _check_range(path: Path, rows: np.ndarray, bounds: tuple[float, float], what: str) -> None:
    """A DatasetError naming ``path`` and the first row with a value outside ``bounds``."""
    low, high = bounds
    bad = np.flatnonzero(np.any((rows < low) | (rows > high), axis=1))
    if bad.size:
        raise DatasetError(f"{path}: row {bad[0] + 1}: {what} must lie in [{low:g}, {high:g}]")


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
    placed = np.isfinite(rows).all(axis=1)
    _check_range(path, np.where(placed[:, None], np.abs(rows), 0.0), (0.0, MAX_COORDINATE),
                 "|coordinates| (pixels)")
    return rows


def read_light_anisotropy(path: Path, count: int | None = None) -> np.ndarray:
    """Read ``light_anisotropy.txt``: each LED's ``cos^mu`` exponent, one value per row (>= 0)."""
    rows = _read_table(path, (1,))[:, 0]
    if count is not None and len(rows) != count:
        raise DatasetError(f"{path}: {len(rows)} values but the dataset has {count} images")
    _check_range(path, rows[:, None], (0.0, MAX_EXPONENT), "anisotropy exponents")
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
    _check_range(path, table, INTENSITY_RANGE, "LED intensities")
    return table


def write_light_table(path: Path, rows: np.ndarray) -> None:
    """Write a light table (directions or intensities) in the DiLiGenT text format."""
    rows = np.atleast_2d(np.asarray(rows, dtype=np.float64))
    np.savetxt(path, rows, fmt="%.9f")


def light_table_bytes(rows: np.ndarray) -> bytes:
    """The text of :func:`write_light_table` (one row of 9-decimal numbers a line), as bytes.

    For writers that publish the file atomically (a capture run's light files).
    """
    return "".join(" ".join(f"{v:.9f}" for v in row) + "\n" for row in np.asarray(rows)).encode()


def _read_text(path: Path) -> str:
    """The text of a light file (UTF-8, a byte-order mark dropped); a :class:`DatasetError`
    where it is missing or unreadable."""
    try:
        return path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read file ({exc})") from None


def _read_table(path: Path, widths: tuple[int, ...], *, allow_nan: bool = False) -> np.ndarray:
    """Parse a whitespace (or comma) separated numeric table; ``#`` starts a comment."""
    text = _read_text(path)
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


def find_lp(folder: Path) -> Path | None:
    """The one ``.lp`` light file of ``folder`` (suffix in any case: ``dirs.LP``), or None.

    Raises
    ------
    DatasetError
        The folder holds two or more (they are named: which one is meant cannot be guessed).
    """
    found = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() == ".lp" and p.is_file())
    if len(found) > 1:
        raise DatasetError(
            f"{folder}: {len(found)} .lp light files ({', '.join(p.name for p in found)}): "
            "keep one, or write light_directions.txt"
        )
    return found[0] if found else None


def read_lp(path: Path) -> tuple[list[str], np.ndarray]:
    """Read a RelightLab / RTIBuilder / AliceVision ``.lp`` light file: (names, directions).

    See :func:`read_lp_rows`, which also gives each row's line number.
    """
    names, directions, _ = read_lp_rows(path)
    return names, directions


def read_lp_rows(path: Path) -> tuple[list[str], np.ndarray, list[int]]:
    """Read a RelightLab / RTIBuilder / AliceVision ``.lp`` light file.

    The first line is the number of images, then one line ``filename x y z`` per image (the
    direction toward the light, in the same frame as ``light_directions.txt``). Read as those
    tools read it: a UTF-8 byte-order mark is skipped, ``#`` lines are comments, the file name may
    contain spaces and a folder (``jpg/Name_0001.jpg``, relative to the ``.lp``), and lines after
    the counted ones are ignored (with a logged warning).

    Returns
    -------
    names : list of str
        The image file names as written (a path; see :func:`lp_image_files`).
    directions : ndarray of shape (n, 3), float64, unit rows
    line_numbers : list of int
        The line of each row in the file (1-based), for messages.

    Raises
    ------
    DatasetError
        Fewer rows than the count, a malformed row, a zero-length direction, or lights that
        cannot determine a normal (fewer than 3, collinear or coplanar); the message names the
        ``.lp`` file.
    """
    text = _read_text(path)
    lines = [
        (number, line.strip())
        for number, line in enumerate(text.splitlines(), start=1)
        if line.strip() and not line.strip().startswith("#")
    ]
    if not lines:
        raise DatasetError(f"{path}: file is empty (the first line must be the number of images)")
    first, head = lines[0]
    try:
        count = int(head.split()[0])
    except ValueError:
        raise DatasetError(
            f"{path}: line {first}: the first line must be the number of images, not {head[:40]!r}"
        ) from None
    if count < 1:
        raise DatasetError(f"{path}: line {first}: says {count} images")
    rows_given = len(lines) - 1
    if rows_given < count:
        raise DatasetError(f"{path}: says {count} images but lists {rows_given}")
    if rows_given > count:
        log.warning(
            "%s: %d line(s) after the %d counted images ignored (from line %d)",
            path,
            rows_given - count,
            count,
            lines[count + 1][0],
        )
    names: list[str] = []
    rows = np.empty((count, 3))
    for k, (number, line) in enumerate(lines[1 : count + 1]):
        fields = line.rsplit(maxsplit=3)
        try:
            if len(fields) != 4:
                raise ValueError
            rows[k] = [float(v) for v in fields[1:]]
        except ValueError:
            raise DatasetError(
                f"{path}: line {number}: expected 'filename x y z', got {line[:60]!r}"
            ) from None
        if not np.all(np.isfinite(rows[k])):
            raise DatasetError(f"{path}: line {number}: a value is NaN or infinite (or overflows)")
        head, _, last = fields[0].rpartition(" ")
        if head and is_supported(Path(head)) and _is_number(last):  # 'a.png 1 0 1 5'
            raise DatasetError(f"{path}: line {number}: expected 'filename x y z', got 4 numbers")
        names.append(fields[0])
    norms = _checked_lengths(path, rows, lambda k: f"line {lines[k + 1][0]}", ": light direction")
    return names, _normalised(path, rows, norms), [number for number, _ in lines[1 : count + 1]]


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def write_lp(path: Path, names: list[str], directions: np.ndarray) -> None:
    """Write a RelightLab / RTIBuilder ``.lp`` file: the count, then ``filename x y z`` lines."""
    directions = np.atleast_2d(np.asarray(directions, dtype=np.float64))
    if len(names) != len(directions):
        raise ValueError(f"{len(names)} names for {len(directions)} directions")
    lines = [str(len(names))]
    lines += [f"{name} {x:.9f} {y:.9f} {z:.9f}" for name, (x, y, z) in zip(names, directions)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def lp_image_files(
    path: Path,
    names: list[str],
    supported: Callable[[Path], bool],
    line_numbers: list[int] | None = None,
) -> list[Path]:
    """The image file of each ``.lp`` entry, found as RelightLab and AliceVision find them.

    Each name is taken as written, relative to the ``.lp`` file's folder (backslashes read as
    slashes): ``a/001.png`` and ``b/001.png`` are two files. When that file does not exist, that
    folder and then the ``.lp``'s own are searched for the name in another letter case, then for
    the same stem with any extension ``supported`` accepts (an ``.lp`` written for
    ``image01.jpg`` finds ``image01.png``), taken only when exactly one file matches; a Windows
    or absolute path is looked up by its file name beside the ``.lp``.

    Raises
    ------
    DatasetError
        Images not found (one line: how many, and the first few names); a name that matches
        several files (``001.png`` and ``001.tif`` for ``001.jpg``); two entries that find the
        same file. The message names the ``.lp`` file and the line.
    """
    files = _resolve_lp_names(path, names, supported, line_numbers)
    missing = [name for name, file in zip(names, files, strict=True) if file is None]
    if missing:
        raise DatasetError(
            f"{path}: lists {len(names)} images but {len(missing)} are not in {Path(path).parent} "
            f"({', '.join(missing[:3])}{', ...' if len(missing) > 3 else ''})"
        )
    return [file for file in files if file is not None]


def _resolve_lp_names(
    path: Path, names: list[str], supported: Callable[[Path], bool], line_numbers: list[int] | None
) -> list[Path | None]:
    """Each entry's file (None: not found); DatasetError for an ambiguous name or a file twice."""
    base = Path(path).parent
    lines = line_numbers or [k + 2 for k in range(len(names))]
    listings: dict[Path, list[Path]] = {}
    files: list[Path | None] = []
    for name, line in zip(names, lines, strict=True):
        written = name.replace("\\", "/")
        relative = Path(written)
        # A Windows or absolute path (C:/rti/a.png) is looked up by its name beside the .lp.
        portable = not (relative.is_absolute() or re.match(r"^[A-Za-z]:/", written))
        if portable and (base / relative).is_file():
            files.append(base / relative)
            continue
        folders = [base / relative.parent] if portable and relative.parent != Path(".") else []
        found = None
        for folder in [*folders, base]:
            if folder not in listings:
                listings[folder] = sorted(folder.iterdir()) if folder.is_dir() else []
            entries = listings[folder]
            same_name = [p for p in entries if p.name.lower() == relative.name.lower()]
            same_stem = [
                p for p in entries if p.stem.lower() == relative.stem.lower() and supported(p)
            ]
            candidates = same_name or same_stem
            if len(candidates) > 1:
                shown = ", ".join(str(p.relative_to(base)) for p in candidates[:4])
                raise DatasetError(
                    f"{path}: line {line}: {name} is not there and matches {len(candidates)} "
                    f"files ({shown}): write the file's name as it is"
                )
            if candidates:
                found = candidates[0]
                break
        files.append(found)
    seen: dict[str, tuple[int, str]] = {}
    for name, line, file in zip(names, lines, files, strict=True):
        if file is None:
            continue
        key = os.path.normcase(os.path.abspath(file))
        if key in seen:
            first_line, first_name = seen[key]
            raise DatasetError(
                f"{path}: lines {first_line} and {line} ({first_name} and {name}) are both the "
                f"image {Path(file).relative_to(base) if file.is_relative_to(base) else file}"
            )
        seen[key] = (line, name)
    return files


def lp_directions_for(path: Path, image_files: list[Path]) -> np.ndarray:
    """Directions of an ``.lp`` file in the order of ``image_files``.

    Each image is the light of the row that names it (:func:`lp_image_files`: the path as
    written, ``a/001.png`` and ``b/001.png`` being two lights); an image no row resolves to
    (a file the ``.lp`` does not see) is matched by file name, then by stem, in any letter case,
    when exactly one row has it (``jpg/Image01.JPG`` is the light of ``image01.png``).

    Raises
    ------
    DatasetError
        An ``.lp`` file that lists more lights than the dataset has images, an image with no
        entry in it or with several, two images with the same entry; the message names the
        ``.lp`` file and the line.
    """
    names, directions, lines = read_lp_rows(path)
    if len(names) > len(image_files):
        raise DatasetError(
            f"{path}: lists {len(names)} lights but the dataset has {len(image_files)} images"
        )
    resolved = _resolve_lp_names(path, names, is_supported, lines)
    by_file = {os.path.normcase(os.path.abspath(f)): k for k, f in enumerate(resolved) if f}
    order: list[int] = []
    for image in map(Path, image_files):
        index = by_file.get(os.path.normcase(os.path.abspath(image)))
        if index is None:
            index = _lp_row_by_name(path, names, lines, image)
        if index in order:
            other = Path(image_files[order.index(index)]).name
            raise DatasetError(
                f"{path}: line {lines[index]} ({names[index]}) is the light of both {other} and "
                f"{image.name}: write each image's path as it is"
            )
        order.append(index)
    return directions[order]


def _lp_row_by_name(path: Path, names: list[str], lines: list[int], image: Path) -> int:
    """The one row naming ``image`` by file name, else by stem (any letter case)."""
    written = [Path(n.replace("\\", "/")) for n in names]
    for key in (lambda p: p.name.lower(), lambda p: p.stem.lower()):
        rows = [k for k, w in enumerate(written) if key(w) == key(image)]
        if len(rows) > 1:
            shown = ", ".join(f"line {lines[k]} ({names[k]})" for k in rows[:4])
            raise DatasetError(f"{path}: image {image.name} matches {len(rows)} rows: {shown}")
        if rows:
            return rows[0]
    raise DatasetError(f"{path}: no light for image {image.name}")


def write_dome(
    path: Path,
    positions: np.ndarray,
    directions: np.ndarray,
    image_width: int,
    label: str = "ps-lab",
    *,
    led_model: dict | None = None,
) -> None:
    """Write LED positions as a RelightLab dome file (``.dome``, JSON, ``lights3d``).

    RelightLab's dome format (relightlab/docs/formats/dome.md and its ``Dome::fromJson``):
    ``imageWidth``, ``domeDiameter``, ``verticalOffset``, ``lightConfiguration`` and per light
    ``{"x", "y", "z"}`` objects in ``directions``, ``positionsSphere`` and ``positions3d``; origin
    at the image centre, x right, y toward the top of the image, z up toward the camera (ps-lab's
    scene frame, :mod:`ps_lab.geometry`). Only lengths relative to ``imageWidth`` matter to
    RelightLab, so positions stay in pixel units and ``imageWidth`` is the width in pixels.

    Parameters
    ----------
    path : Path
        The ``.dome`` file.
    positions : ndarray of shape (n, 3)
        LED positions in pixels; a NaN row (a light too far to place) is put on the dome along
        its direction.
    directions : ndarray of shape (n, 3)
        Unit directions toward each light (used for the NaN rows and written as ``directions``).
    image_width : int
        Image width in pixels.
    label : str
        The dome's name.
    led_model : dict, optional
        The LEDs' fitted emission (``ps-lab calibrate --flat-field``): ``axes`` (n, 3), ``mu``
        (n,), ``outputs`` (n,). Written as ``ledModel`` (``{"axis", "mu", "output"}`` per light,
        an extension RelightLab ignores; ``ledAdjust`` stays empty).
    """
    positions = np.asarray(positions, np.float64)
    directions = np.asarray(directions, np.float64)
    placed = np.isfinite(positions).all(axis=1)
    radius = float(np.median(np.linalg.norm(positions[placed], axis=1))) if placed.any() else 1.0
    full = np.where(placed[:, None], positions, directions * radius)
    toward = full / np.linalg.norm(full, axis=1, keepdims=True)
    sphere = toward * radius

    def points(rows: np.ndarray) -> list[dict[str, float]]:
        return [{"x": float(x), "y": float(y), "z": float(z)} for x, y, z in rows]

    dome = {
        "label": label,
        "notes": "written by ps-lab calibrate from two chrome spheres; lengths in image pixels "
        "(imageWidth is the image width in pixels); origin at the image centre in the spheres' "
        f"plane; {int((~placed).sum())} light(s) too far to place put on the dome",
        "imageWidth": float(image_width),
        "domeDiameter": 2.0 * radius,
        "verticalOffset": 0.0,
        "lightConfiguration": "lights3d",
        "directions": points(toward),
        "positionsSphere": points(sphere),
        "positions3d": points(full),
        "ledAdjust": [],
    }
    if led_model is not None:
        axes = np.asarray(led_model["axes"], np.float64)
        dome["ledModel"] = [
            {"axis": {"x": float(a[0]), "y": float(a[1]), "z": float(a[2])}, "mu": float(m),
             "output": float(o)}
            for a, m, o in zip(axes, led_model["mu"], led_model["outputs"], strict=True)
        ]
    path.write_text(json.dumps(dome, indent=1) + "\n", encoding="utf-8")
