"""``ps-lab relight``: a result folder's object under any light, as EXR (linear) or PNG (sRGB).

:func:`relight_picture` is the pure part (normals, albedo and an optional fitted
:class:`ps_lab.appearance.models.Appearance` → a linear (H, W, C) picture);
:func:`relight_result` reads a result folder, evaluates every requested light and writes the
files, all or none. Light directions are in the dataset's light frame (x right, y up, z toward
the camera), the values in the solver's units (decoded, each channel divided by its light's
intensity): an EXR holds them as float32 RGB, a PNG holds them sRGB-encoded, clipped to [0, 1].
A near-light result (``"light_model": "near"`` with its ``depth.npy``) takes ``--light`` as an LED
position in the scene frame of ``light_positions.txt`` (pixel units): each pixel is lit from its
own direction toward the LED, through the result's depth (heights above the spheres' plane) and
camera (perspective when ``metrics.json`` records one, else orthographic), and scaled by the
inverse-square falloff relative to the scene origin, as the solver modelled it
(:func:`ps_lab.geometry.near_light_vectors`, an isotropic LED of unit intensity at the origin).
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import OpenEXR

from ps_lab.appearance.models import MAX_STORED, Appearance, evaluate_appearance, lambertian
from ps_lab.appearance.store import read_appearance
from ps_lab.errors import DatasetError, OutputError
from ps_lab.geometry import Camera, near_light_vectors, scene_points
from ps_lab.io.encoding import linear_to_srgb
from ps_lab.io.files import fsync_path, is_no_space, staging_folder
from ps_lab.io.normal_maps import EXR_COMPRESSION
from ps_lab.io.result import read_result_metrics

__all__ = [
    "RELIGHT_MODES",
    "RelightSource",
    "parse_light",
    "read_relight_source",
    "relight_outputs",
    "relight_picture",
    "relight_result",
]

RELIGHT_MODES = ("fitted", "lambertian")
_SUFFIXES = (".exr", ".png")
#: Shortest ``--light`` direction and farthest LED (pixel units) or longest direction accepted.
MIN_LENGTH = 1e-6
MAX_LENGTH = 1e6
#: How far from 1 the length of a solved normal in ``normals.npy`` may be.
UNIT_TOLERANCE = 1e-2
_STAGE = ".relight-partial-"


@dataclass(frozen=True)
class RelightSource:
    """What relighting needs from a result folder.

    normals (H, W, 3) float32 (zero where unsolved), albedo (H, W, C) float32, the fitted
    appearance (or None) and the result's metrics.
    """

    folder: Path
    normals: np.ndarray
    albedo: np.ndarray
    appearance: Appearance | None
    metrics: dict[str, Any]


def parse_light(text: str, position: bool = False) -> np.ndarray:
    """``"X,Y,Z"`` → the unit direction (3,) (or, ``position``, the point as given).

    A direction must be finite, of a length in [:data:`MIN_LENGTH`, :data:`MAX_LENGTH`] (it is
    normalised) and above the object's horizon (``z > 0``: on the camera's side of the plane
    the object lies in, where the captured lights are); a position finite and at most
    :data:`MAX_LENGTH` from the scene origin. Raises :class:`OutputError` naming ``--light``.
    """
    values = _light_numbers(text)
    largest = float(np.max(np.abs(values)))
    # the length without overflow or underflow of the squares
    norm = largest * float(np.linalg.norm(values / largest)) if largest > 0 else 0.0
    if position:
        if norm > MAX_LENGTH:
            raise OutputError(f"--light {text!r}: the LED is {norm:.3g} pixels from the scene "
                              f"origin; at most {MAX_LENGTH:.0e} (farther is a direction)")
        return values
    if norm < MIN_LENGTH:
        raise OutputError(f"--light {text!r}: the direction is zero")
    if norm > MAX_LENGTH:
        raise OutputError(f"--light {text!r}: a direction of length {norm:.3g}; give one of "
                          f"length between {MIN_LENGTH:.0e} and {MAX_LENGTH:.0e} (it is normalised)")
    unit = (values / largest) / (norm / largest)
    if not unit[2] > 0:
        raise OutputError(f"--light {text!r}: not above the object's horizon (z must be > 0: "
                          "the light on the camera's side of the object's plane)")
    return unit


def _light_numbers(text: str) -> np.ndarray:
    """The three finite numbers of ``"X,Y,Z"`` (3,), or :class:`OutputError` naming ``--light``."""
    try:
        values = np.array([float(v) for v in str(text).split(",")], np.float64)
    except ValueError:
        values = np.zeros(0)
    if values.shape != (3,) or not np.all(np.isfinite(values)):
        raise OutputError(f"--light {text!r}: expected three numbers X,Y,Z (e.g. 0.3,0.2,0.93)")
    return values


def relight_picture(
    normals: np.ndarray,
    albedo: np.ndarray,
    light: np.ndarray,
    appearance: Appearance | None = None,
) -> np.ndarray:
    """The object under ``light``: the fitted model, or Lambertian without one.

    Parameters
    ----------
    normals : ndarray of shape (H, W, 3)
    albedo : ndarray of shape (H, W), (H, W, 1) or (H, W, C)
    light : ndarray of shape (3,) or (H, W, 3)
        Unit direction (or per-pixel unit directions).
    appearance : Appearance or None

    Returns
    -------
    ndarray of shape (H, W, C), float32, linear; 0 where the normal is unsolved

    """
    if appearance is None or appearance.model == "none":
        picture = lambertian(light, normals, albedo)
    else:
        picture = evaluate_appearance(appearance, light, normals, albedo)
    solved = np.linalg.norm(np.nan_to_num(normals), axis=-1) > 0.5
    picture[~solved] = 0.0
    return picture


def read_relight_source(folder: Path, mode: str = "fitted") -> RelightSource:
    """Read a result folder's normals, albedo and (``mode="fitted"``) appearance model.

    Every array is checked before use: the normals (H, W, 3) real, each pixel's either zero or
    not finite (unsolved) or of unit length (within :data:`UNIT_TOLERANCE`), the albedo
    (H, W) or (H, W, 1|3) real and finite where the normal is solved, the appearance model as
    :func:`ps_lab.appearance.store.read_appearance` validates it.

    Raises
    ------
    DatasetError
        Not a result folder, a file missing or inconsistent (naming it).

    """
    folder = Path(folder)
    if mode not in RELIGHT_MODES:
        raise OutputError(f"--appearance must be fitted or lambertian, got {mode!r}")
    metrics = read_result_metrics(folder)
    if metrics is None:
        raise DatasetError(f"{folder}: not a ps-lab reconstruct result (no metrics.json)")
    normals = _load(folder / "normals.npy")
    albedo = _load(folder / "albedo.npy")
    if normals.ndim != 3 or normals.shape[2] != 3 or 0 in normals.shape:
        raise DatasetError(f"{folder / 'normals.npy'}: expected (H, W, 3), got {normals.shape}")
    if (albedo.shape[:2] != normals.shape[:2] or albedo.ndim not in (2, 3)
            or (albedo.ndim == 3 and albedo.shape[2] not in (1, 3))):
        raise DatasetError(f"{folder / 'albedo.npy'}: shape {albedo.shape} does not match the "
                           f"normals {normals.shape} (H, W) or (H, W, 1|3)")
    normals = normals.astype(np.float32)
    albedo = albedo.astype(np.float32)
    albedo = albedo[..., None] if albedo.ndim == 2 else albedo
    finite = np.isfinite(normals).all(axis=2)
    length = np.linalg.norm(np.where(finite[..., None], normals, 0.0), axis=2)
    solved = finite & (length > 0.5)
    if np.any(finite & (length > 0) & (np.abs(length - 1) > UNIT_TOLERANCE)):
        raise DatasetError(f"{folder / 'normals.npy'}: normals must be unit vectors (or zero "
                           "where unsolved)")
    if not np.isfinite(albedo[solved]).all() or np.any(np.abs(albedo[solved]) > MAX_STORED):
        raise DatasetError(f"{folder / 'albedo.npy'}: not finite (or beyond ±{MAX_STORED:.0e}) "
                           "where the normals are solved")
    appearance = None
    if mode == "fitted":
        appearance = read_appearance(folder)
        if appearance is None:
            raise DatasetError(
                f"{folder}: no appearance.npz (reconstruct with --appearance ps|ptm|hsh2|hsh3|rbf, "
                "or relight with --appearance lambertian)"
            )
        if appearance.coefficients.shape[:2] != normals.shape[:2]:
            raise DatasetError(f"{folder / 'appearance.npz'}: size differs from normals.npy")
    return RelightSource(folder, normals, albedo, appearance, metrics)


def _load(path: Path) -> np.ndarray:
    """A real-valued ``.npy`` (integers or floats), or :class:`DatasetError` naming it."""
    try:  # mapped first: a header claiming more than the file holds is refused unread
        array = np.load(path, mmap_mode="r", allow_pickle=False)
        if isinstance(array, np.ndarray):
            array = np.array(array)
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing") from None
    except MemoryError:
        raise DatasetError(f"{path}: too large to read") from None
    except (OSError, ValueError, EOFError) as exc:
        raise DatasetError(f"{path}: not a readable .npy file ({exc})") from None
    if isinstance(array, np.lib.npyio.NpzFile):
        array.close()
        raise DatasetError(f"{path}: an .npz archive, not a .npy array")
    if array.dtype.kind not in "iuf":
        raise DatasetError(f"{path}: expected real numbers, not {getattr(array, 'dtype', '?')}")
    return array


def relight_outputs(out: Path, count: int) -> list[Path]:
    """The file of each light: ``out`` itself for one, ``STEM_light01.ext``... for several."""
    out = Path(out)
    if out.suffix.lower() not in _SUFFIXES:
        raise OutputError(f"--out {out}: the file must end in .exr (linear) or .png (sRGB)")
    if count == 1:
        return [out]
    return [out.with_name(f"{out.stem}_light{k + 1:02d}{out.suffix}") for k in range(count)]


def _check_outputs(out: Path, paths: list[Path]) -> None:
    """Refuse outputs that are folders, or whose folder is a file (before any work)."""
    for path in paths:
        if path.is_dir():
            raise OutputError(f"--out {out}: {path} is a folder; give a file name ending in "
                              ".exr or .png")
    folder = paths[0].parent
    while not folder.exists() and not folder.is_symlink() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise OutputError(f"--out {out}: {folder} is not a folder")


def relight_result(
    result: Path, lights: list[str], out: Path, mode: str = "fitted"
) -> list[tuple[Path, np.ndarray]]:
    """Relight a result folder under each light and write one file per light, all or none.

    Everything is checked before any picture is made (the lights, the output names, the
    result's arrays); the pictures are written into a hidden folder beside ``out`` and move
    to their names only when all are written (an earlier picture of the same name is put back
    if a move fails). Errors name ``--out``'s file, never the hidden folder.

    Parameters
    ----------
    result : Path
        A ``ps-lab reconstruct`` result folder.
    lights : list of str
        ``"X,Y,Z"`` directions in the dataset's light frame (LED positions for a near result).
    out : Path
        ``.exr`` or ``.png``; several lights get ``_light01``, ``_light02``... before the suffix.
    mode : {"fitted", "lambertian"}

    Returns
    -------
    list of (Path, ndarray of shape (3,))
        Each file written and its unit light direction (or LED position).

    """
    if not lights:
        raise OutputError("--light: give at least one direction X,Y,Z")
    for text in lights:
        _light_numbers(text)
    out = Path(out)
    paths = relight_outputs(out, len(lights))
    _check_outputs(out, paths)
    source = read_relight_source(result, mode)
    near = source.metrics.get("light_model") == "near"
    points = _near_points(source) if near else None
    given = [parse_light(text, position=near) for text in lights]
    if points is not None:
        for text, position in zip(lights, given, strict=True):
            _check_above(text, position, points, source.normals)
    current = paths[0]
    try:
        with staging_folder(paths[0].parent, _STAGE) as stage:
            staged = []
            for k, (path, light) in enumerate(zip(paths, given, strict=True)):
                current = path
                if points is None:
                    picture = relight_picture(source.normals, source.albedo, light,
                                              source.appearance)
                else:
                    picture = _near_picture(source, points, light)
                staged.append(stage / f"{k:04d}{path.suffix}")
                _write_picture(staged[-1], picture)
            for path, final in zip(staged, paths, strict=True):
                current = final
                fsync_path(path)
            _publish(stage, staged, paths)
    except OSError as exc:
        failed = Path(exc.filename) if exc.filename in {str(p) for p in paths} else current
        raise OutputError(_write_line(out, failed, exc)) from None
    return list(zip(paths, given, strict=True))


def _write_line(out: Path, path: Path, exc: OSError) -> str:
    """The error line of a failed write: the user's file, the reason, what is left."""
    reason = os.strerror(exc.errno) if exc.errno else str(exc)
    reason = reason[:1].lower() + reason[1:]
    remedy = "; free some space and run again" if is_no_space(exc) else ""
    return f"--out {path}: cannot write, {reason}; no picture written{remedy}"


def _publish(stage: Path, staged: list[Path], paths: list[Path]) -> Path:
    """Move every staged picture to its name, or none: an earlier file is put back on failure.

    Returns the last name (the one a failure concerns: the exception carries it as
    ``filename``); raises the ``OSError`` of a failed move after the rollback.
    """
    moved: list[Path] = []
    kept: list[tuple[Path, Path]] = []
    try:
        for k, (path, final) in enumerate(zip(staged, paths, strict=True)):
            if final.exists() or final.is_symlink():
                old = stage / f"old-{k:04d}"
                os.replace(final, old)
                kept.append((old, final))
            os.replace(path, final)
            moved.append(final)
    except OSError as exc:
        _roll_back(moved, kept)
        exc.filename = str(final)
        raise
    except BaseException:
        _roll_back(moved, kept)
        raise
    return final


def _roll_back(moved: list[Path], kept: list[tuple[Path, Path]]) -> None:
    """Remove the pictures moved so far and put the earlier files back (best effort)."""
    for final in moved:
        final.unlink(missing_ok=True)
    for old, final in kept:
        try:
            os.replace(old, final)
        except OSError:
            pass


def _check_above(text: str, position: np.ndarray, points: np.ndarray, normals: np.ndarray) -> None:
    """Refuse an LED that is not above every solved surface point (scene frame z)."""
    solved = np.isfinite(points[..., 2]) & (np.linalg.norm(normals, axis=2) > 0.5)
    top = float(np.max(points[..., 2][solved])) if solved.any() else 0.0
    if not position[2] >= top + 1.0:
        raise OutputError(f"--light {text!r}: the LED must be above the object, at least a "
                          f"pixel above its highest point (z >= {top + 1.0:.4g}, scene frame)")


def _near_points(source: RelightSource) -> np.ndarray:
    """Scene-frame points (H, W, 3) of a near-light result (NaN where it has no depth)."""
    path = source.folder / "depth.npy"
    depth = _load(path)
    shape = source.normals.shape[:2]
    if depth.shape != shape:
        raise DatasetError(f"{path}: shape {depth.shape} does not match "
                           f"the normals {source.normals.shape}")
    depth = np.asarray(depth, np.float64)
    if np.any(np.abs(depth[np.isfinite(depth)]) > MAX_LENGTH):
        raise DatasetError(f"{path}: heights beyond {MAX_LENGTH:.0e} pixels")
    record = source.metrics.get("camera")
    camera = None
    if isinstance(record, dict) and all(k in record for k in ("fx", "fy", "cx", "cy")):
        values = [record[k] for k in ("fx", "fy", "cx", "cy")]
        if not (all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
                and np.all(np.isfinite(values)) and values[0] >= 1 and values[1] >= 1
                and max(abs(v) for v in values) < MAX_LENGTH):
            raise DatasetError(f"{source.folder / 'metrics.json'}: camera fx, fy, cx, cy must "
                               f"be finite numbers below {MAX_LENGTH:.0e} (focal lengths >= 1 "
                               "pixel)")
        camera = Camera.from_intrinsics(*(float(v) for v in values))
    rows, cols = np.indices(shape)
    heights = np.nan_to_num(depth)
    points = scene_points(shape, rows.ravel(), cols.ravel(), heights.ravel(), camera)
    points = points.reshape(*shape, 3)
    points[~np.isfinite(depth)] = np.nan
    return points


def _near_picture(source: RelightSource, points: np.ndarray, position: np.ndarray) -> np.ndarray:
    """The picture under an isotropic LED at ``position`` (scene frame)."""
    flat = np.nan_to_num(points.reshape(-1, 3))
    vectors = near_light_vectors(flat, position[None], np.array([[0.0, 0.0, 1.0]]))[:, 0]
    strength = np.linalg.norm(vectors, axis=1)
    directions = vectors / np.where(strength > 0, strength, 1.0)[:, None]
    shape = source.normals.shape[:2]
    picture = relight_picture(source.normals, source.albedo, directions.reshape(*shape, 3),
                              source.appearance)
    picture *= strength.reshape(*shape, 1).astype(np.float32)
    picture[~np.isfinite(points[..., 0])] = 0.0
    return picture


def _write_picture(path: Path, picture: np.ndarray) -> None:
    """Encode in memory and write from Python (so that a failed write says why: ``OSError``)."""
    rgb = picture if picture.shape[2] == 3 else np.repeat(picture[..., :1], 3, axis=2)
    rgb = np.ascontiguousarray(np.nan_to_num(rgb), dtype=np.float32)
    if path.suffix.lower() == ".png":
        encoded = np.rint(linear_to_srgb(np.clip(rgb, 0.0, 1.0)) * 255.0).astype(np.uint8)
        ok, data = cv2.imencode(".png", np.ascontiguousarray(encoded[..., ::-1]))
        if not ok:
            raise OutputError(f"{path.name}: OpenCV could not encode the PNG")
        payload = data.tobytes()
    else:
        header = {"type": OpenEXR.scanlineimage, "compression": EXR_COMPRESSION}
        buffer = io.BytesIO()
        with OpenEXR.File(header, {"RGB": rgb}) as exr:
            exr.write(buffer)
        payload = buffer.getvalue()
    with open(path, "wb") as handle:
        handle.write(payload)
