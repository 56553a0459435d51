"""``ps-lab relight``: a result folder's object under any light, as EXR (linear) or PNG (sRGB).

:func:`relight_picture` is the pure part (normals, albedo and an optional fitted
:class:`ps_lab.io.appearance.Appearance` → a linear (H, W, C) picture);
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

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ps_lab.errors import DatasetError, OutputError
from ps_lab.geometry import Camera, near_light_vectors, scene_points
from ps_lab.io.appearance import Appearance, evaluate_appearance, lambertian, read_appearance
from ps_lab.io.codecs import imwrite
from ps_lab.io.encoding import linear_to_srgb
from ps_lab.io.files import staged_files
from ps_lab.io.normal_maps import write_rgb_exr
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
    """``"X,Y,Z"`` → the unit direction (3,) (or, ``position``, the point as given); raises
    :class:`OutputError` naming ``--light``."""
    try:
        values = np.array([float(v) for v in str(text).split(",")], np.float64)
    except ValueError:
        values = np.zeros(0)
    if values.shape != (3,) or not np.all(np.isfinite(values)):
        raise OutputError(f"--light {text!r}: expected three numbers X,Y,Z (e.g. 0.3,0.2,0.93)")
    norm = float(np.linalg.norm(values))
    if position:
        return values
    if norm < 1e-9:
        raise OutputError(f"--light {text!r}: the direction is zero")
    return values / norm


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
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise DatasetError(f"{folder / 'normals.npy'}: expected (H, W, 3), got {normals.shape}")
    if albedo.shape[:2] != normals.shape[:2] or albedo.ndim not in (2, 3):
        raise DatasetError(f"{folder / 'albedo.npy'}: shape {albedo.shape} does not match the "
                           f"normals {normals.shape}")
    albedo = albedo[..., None] if albedo.ndim == 2 else albedo
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
    return RelightSource(folder, normals.astype(np.float32), albedo.astype(np.float32),
                         appearance, metrics)


def _load(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing") from None
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: not a readable .npy file ({exc})") from None


def relight_outputs(out: Path, count: int) -> list[Path]:
    """The file of each light: ``out`` itself for one, ``STEM_light01.ext``... for several."""
    out = Path(out)
    if out.suffix.lower() not in _SUFFIXES:
        raise OutputError(f"--out {out}: the file must end in .exr (linear) or .png (sRGB)")
    if count == 1:
        return [out]
    return [out.with_name(f"{out.stem}_light{k + 1:02d}{out.suffix}") for k in range(count)]


def relight_result(
    result: Path, lights: list[str], out: Path, mode: str = "fitted"
) -> list[tuple[Path, np.ndarray]]:
    """Relight a result folder under each light and write one file per light.

    Parameters
    ----------
    result : Path
        A ``ps-lab reconstruct`` result folder.
    lights : list of str
        ``"X,Y,Z"`` directions in the dataset's light frame.
    out : Path
        ``.exr`` or ``.png``; several lights get ``_light01``, ``_light02``... before the suffix.
    mode : {"fitted", "lambertian"}

    Returns
    -------
    list of (Path, ndarray of shape (3,))
        Each file written and its unit light direction.

    """
    if not lights:
        raise OutputError("--light: give at least one direction X,Y,Z")
    for text in lights:
        parse_light(text, position=True)
    paths = relight_outputs(out, len(lights))
    if Path(out).is_dir():
        raise OutputError(f"--out {out}: is a folder; give a file name ending in .exr or .png")
    source = read_relight_source(result, mode)
    near = source.metrics.get("light_model") == "near"
    points = _near_points(source) if near else None
    given = [parse_light(text, position=near) for text in lights]
    parent = Path(out).parent if str(Path(out).parent) else Path(".")
    with staged_files(parent, prefix=".relight-", error=OutputError) as stage:
        for path, light in zip(paths, given, strict=True):
            if points is None:
                picture = relight_picture(source.normals, source.albedo, light, source.appearance)
            else:
                picture = _near_picture(source, points, light)
            _write_picture(stage / path.name, picture)
    return list(zip(paths, given, strict=True))


def _near_points(source: RelightSource) -> np.ndarray:
    """Scene-frame points (H, W, 3) of a near-light result (NaN where it has no depth)."""
    depth = _load(source.folder / "depth.npy")
    shape = source.normals.shape[:2]
    if depth.shape != shape:
        raise DatasetError(f"{source.folder / 'depth.npy'}: shape {depth.shape} does not match "
                           f"the normals {source.normals.shape}")
    record = source.metrics.get("camera")
    camera = None
    if isinstance(record, dict) and all(k in record for k in ("fx", "fy", "cx", "cy")):
        camera = Camera.from_intrinsics(record["fx"], record["fy"], record["cx"], record["cy"])
    rows, cols = np.indices(shape)
    heights = np.nan_to_num(np.asarray(depth, np.float64))
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
    rgb = picture if picture.shape[2] == 3 else np.repeat(picture[..., :1], 3, axis=2)
    rgb = np.ascontiguousarray(np.nan_to_num(rgb), dtype=np.float32)
    if path.suffix.lower() == ".png":
        encoded = np.rint(linear_to_srgb(np.clip(rgb, 0.0, 1.0)) * 255.0).astype(np.uint8)
        if not imwrite(path, np.ascontiguousarray(encoded[..., ::-1])):
            raise OutputError(f"{path}: OpenCV could not write the PNG")
        return
    write_rgb_exr(path, rgb)
