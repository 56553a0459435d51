"""``ps-lab view RESULT --export DIR --format relight``: a result in RelightLab's web layout.

The format itself (``info.json``, ``plane_N.jpg``, quantisation) is :mod:`ps_lab.io.relightlab`;
this module gathers what a result folder holds (its PTM / HSH fit from ``appearance.npz``, its
captured lights, its normal and albedo pictures) and writes the folder staged (complete or
absent). :func:`result_lights` is also what the viewer's light disc shows;
:func:`load_view_result` and :func:`result_appearance` let the viewer open such a folder.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import cv2
import numpy as np

from ps_lab.errors import DatasetError, OutputError, PsLabError
from ps_lab.io.appearance import Appearance, evaluate_appearance, read_appearance
from ps_lab.io.encoding import srgb_to_linear
from ps_lab.io.files import output_target, staged_folder
from ps_lab.io.light_files import find_lp, read_light_directions, read_lp
from ps_lab.io.relight import read_relight_source, relight_picture
from ps_lab.io.relightlab import (
    EXPORT_MODELS,
    INFO,
    is_relightlab_folder,
    read_info,
    read_relightlab,
    write_relightlab,
    write_relightlab_rbf,
)
from ps_lab.view.export_rbf import convert_to_rbf, grey_psnr
from ps_lab.view.result import CHANNELS, ViewResult, load_result

__all__ = [
    "export_relightlab",
    "load_view_result",
    "relightlab_lights",
    "result_appearance",
    "result_lights",
]


def result_lights(root: Path) -> np.ndarray | None:
    """The captured light directions of a result (n, 3), or None when none can be found.

    The result's own ``light_directions.txt`` (refined lights) first, else the dataset's that
    ``metrics.json`` names (its ``light_directions.txt`` or RelightLab ``.lp`` file).
    """
    try:
        return captured_lights(root)
    except PsLabError:
        return None


def captured_lights(root: Path) -> np.ndarray | None:
    """:func:`result_lights`, strict: None only when the result names no lights at all.

    Raises
    ------
    DatasetError
        The dataset ``metrics.json`` names is gone (moved or deleted) or holds no readable
        light file, and the result has none of its own (the message names the dataset).

    """
    root = Path(root)
    lights = relightlab_lights(root)
    if lights is not None:
        return lights
    own = root / "light_directions.txt"
    if own.is_file():
        return read_light_directions(own)
    try:
        metrics = json.loads((root / "metrics.json").read_text(encoding="utf-8"))
        named = metrics.get("dataset") if isinstance(metrics, dict) else None
    except (OSError, ValueError, RecursionError):
        named = None
    if not isinstance(named, str) or not named:
        return None
    dataset = Path(named)
    if not dataset.is_dir():
        raise DatasetError(
            f"{dataset}: the dataset this result was made from ({root / 'metrics.json'}) is "
            "missing, and its light directions go into the export: put the dataset back there"
        )
    if (dataset / "light_directions.txt").is_file():
        return read_light_directions(dataset / "light_directions.txt")
    lp = find_lp(dataset)
    if lp is None:
        raise DatasetError(f"{dataset}: no light_directions.txt or .lp file (the result's lights)")
    return np.asarray(read_lp(lp)[1], np.float64)


#: The files a ``--format relight`` export writes (any other file makes a folder foreign).
_EXPORT_FILE = re.compile(r"(?:info\.json|plane_\d+\.jpg|normals\.png|albedo\.png)")


def check_export_folder(folder: Path) -> None:
    """Refuse ``folder`` unless it is absent, empty, or an earlier ps-lab relight export.

    An earlier export holds only the files one writes and an ``info.json`` with a ``ps_lab``
    object; anything else is the user's, and is never replaced.

    Raises
    ------
    OutputError
        Naming the folder and the files ps-lab did not write.

    """
    folder = Path(folder)
    if not folder.exists() and not folder.is_symlink():
        return
    if not folder.is_dir():
        raise OutputError(f"{folder}: exists and is not a folder (choose a new or empty folder)")
    try:
        names = sorted(entry.name for entry in folder.iterdir())
    except OSError as exc:
        raise OutputError(f"{folder}: cannot list the folder ({exc.strerror})") from None
    if not names:
        return
    foreign = [name for name in names if not _EXPORT_FILE.fullmatch(name)]
    if not foreign and INFO in names:
        try:
            info = json.loads((folder / INFO).read_text(encoding="utf-8"))
            ours = isinstance(info, dict) and isinstance(info.get("ps_lab"), dict)
        except (OSError, UnicodeDecodeError, ValueError, RecursionError):
            ours = False
        if not ours:
            foreign = [INFO]
    elif not foreign:
        foreign = names  # planes without info.json: not an export ps-lab finished
    if foreign:
        more = f" and {len(foreign) - 5} more" if len(foreign) > 5 else ""
        shown = ", ".join(foreign[:5]) + more
        raise OutputError(
            f"{folder}: holds files ps-lab did not write ({shown}); it is replaced only when "
            "empty or an earlier ps-lab export: choose a new or empty folder"
        )


def export_relightlab(result: Path, out: Path) -> tuple[dict, str]:
    """Write the result's appearance model into ``out`` in RelightLab's web layout.

    A PTM or HSH fit in linear light is written as it is; any other model (``ps``, ``gp``,
    ``bln``, ``rbf``, Lambertian, a fit in the sRGB space, ...) is converted to the ``rbf``
    layout (:mod:`ps_lab.view.export_rbf`) and the conversion's PSNR against the model is
    measured on the written files. ``out`` must be absent, empty or an earlier such export
    (:func:`check_export_folder`); it is replaced only when the new folder is complete.

    Returns
    -------
    info : dict
        The ``info.json`` written.
    line : str
        One line saying what was written.

    Raises
    ------
    DatasetError
        Not a result, or a file of it (or its moved dataset) cannot be read.
    OutputError
        ``out`` cannot be written, or holds files ps-lab did not write.

    """
    result, out = Path(result), Path(out)
    if not (result / "normals.npy").is_file():
        raise DatasetError(f"{result}: not a ps-lab result (no normals.npy)")
    check_export_folder(output_target(out, OutputError))
    appearance = read_appearance(result)
    lights = captured_lights(result)
    pictures = {}
    for name in ("normal.png", "albedo.png"):
        picture = cv2.imread(str(result / name), cv2.IMREAD_COLOR)
        pictures[name] = None if picture is None else picture[..., ::-1]
    # RelightLab's PTM and HSH layouts hold linear coefficients: a fit in the sRGB-encoded space
    # (``meta["space"]``) is converted like every other model
    direct = (appearance is not None and appearance.model in EXPORT_MODELS
              and appearance.meta.get("space", "linear") == "linear")
    source = None if direct else read_relight_source(
        result, "fitted" if appearance is not None else "lambertian"
    )
    with staged_folder(out, check=check_export_folder, error=OutputError) as stage:
        if direct:
            info = write_relightlab(
                stage, appearance, np.zeros((0, 3)) if lights is None else lights,
                normal_picture=pictures["normal.png"], albedo_picture=pictures["albedo.png"],
            )
            line = f"RelightLab {info['type']} ({info['nplanes']} planes) written to {out}"
        else:
            info, line = _write_converted(stage, out, source, lights, pictures)
    return info, line


def _write_converted(stage: Path, out: Path, source, lights, pictures) -> tuple[dict, str]:
    """Convert ``source``'s model to the ``rbf`` layout in ``stage``; measure it read back."""
    normals = np.nan_to_num(np.asarray(source.normals, np.float32))
    h, w = normals.shape[:2]
    flat_normals = normals.reshape(-1, 3)
    flat_albedo = np.asarray(source.albedo, np.float32).reshape(h * w, -1)
    fit = source.appearance
    inside = np.linalg.norm(flat_normals, axis=1) > 0.5
    model = "lambertian" if fit is None else fit.model

    def take(pixels):
        if fit is None:
            return None
        extra = {
            name: np.asarray(value).reshape(h * w, *np.shape(value)[2:])[pixels][None]
            if np.ndim(value) >= 2 and np.shape(value)[:2] == (h, w) else value
            for name, value in fit.extra.items()
        }
        coefficients = np.asarray(fit.coefficients).reshape(h * w, *fit.coefficients.shape[2:])
        return Appearance(fit.model, coefficients[pixels][None], fit.meta, extra)

    def relight_raw(at: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        part = take(pixels)
        n, a = flat_normals[pixels][None], flat_albedo[pixels][None]
        out = np.empty((len(at), len(pixels), 3))
        for i, light in enumerate(at):
            picture = relight_picture(n, a, light, part)[0]
            out[i] = picture if picture.shape[1] == 3 else picture[:, :1]
        return np.nan_to_num(out)

    everything = np.arange(h * w)
    probe = everything[inside] if inside.any() else everything
    top = relight_raw(np.array([[0.0, 0.0, 1.0]]), probe[:: max(1, len(probe) // 20000)])
    peak = float(np.percentile(top, 99)) if top.size else 0.0
    exposure = 1.0 / peak if math.isfinite(peak) and peak > 0 else 1.0

    def relight(at: np.ndarray, pixels: np.ndarray | None) -> np.ndarray:
        return relight_raw(at, everything if pixels is None else pixels) * exposure

    conversion = convert_to_rbf(relight, h * w, inside, lights)
    coefficients = np.empty((h * w, len(conversion.eigen)))
    step = max(1, 2_000_000 // (len(conversion.lights) * w * 3))  # rows per block
    for r0 in range(0, h, step):
        block = everything[r0 * w : min(h, r0 + step) * w]
        coefficients[block] = conversion.coefficients(relight(conversion.lights, block))
    coefficients = coefficients.reshape(h, w, -1)
    info = write_relightlab_rbf(
        stage, conversion.lights, conversion.sigma, conversion.mean_bytes,
        conversion.eigen_bytes, conversion.ranges, coefficients, exposure=exposure, source=model,
        normal_picture=pictures["normal.png"], albedo_picture=pictures["albedo.png"],
    )
    # The conversion measured as OpenLIME reads it: the written planes against the model.
    written, _ = read_relightlab(stage)
    pixels = np.flatnonzero(inside) if inside.any() else everything
    pixels = pixels[:: max(1, len(pixels) // 20000)]
    test = conversion.test_lights
    predicted = np.stack([
        evaluate_appearance(_flat(written, pixels), light, np.zeros((1, len(pixels), 3)),
                            np.zeros((1, len(pixels))))[0] for light in test
    ]) * exposure
    psnr = grey_psnr(predicted, relight(test, pixels))
    info["ps_lab"]["conversion"] = {  # psnr_db null: exact (JSON has no infinity)
        "from": model, "psnr_db": round(psnr, 2) if math.isfinite(psnr) else None,
        "lights": conversion.lights_source, "test_lights": len(test),
    }
    try:
        (stage / INFO).write_text(json.dumps(info, indent=1) + "\n", encoding="utf-8")
    except OSError as exc:
        raise OutputError(f"{out / INFO}: cannot write ({exc.strerror or exc})") from None
    line = (
        f"RelightLab rbf ({info['nplanes']} planes, {len(conversion.lights)} "
        f"{conversion.lights_source} lights, sigma {conversion.sigma:.3f}) written to {out}: "
        + (f"{model} converted at {psnr:.1f} dB PSNR against the model" if math.isfinite(psnr)
           else f"{model} converted exactly (no error against the model)")
        + f" ({len(test)} lights it was not sampled at)"
    )
    return info, line


def _flat(appearance: Appearance, pixels: np.ndarray) -> Appearance:
    """An appearance's pixels ``pixels`` (flat indices) as a 1 × N picture."""
    h, w = appearance.coefficients.shape[:2]
    coefficients = appearance.coefficients.reshape(h * w, *appearance.coefficients.shape[2:])
    return Appearance(appearance.model, coefficients[pixels][None], appearance.meta,
                      appearance.extra)


# --- the viewer's side: a result's fit, and a RelightLab folder as a result -----------------


def result_appearance(root: Path) -> Appearance | None:
    """The appearance fit the viewer relights: a RelightLab folder's, else ``appearance.npz``."""
    root = Path(root)
    if is_relightlab_folder(root) and not (root / "normals.npy").exists():
        return read_relightlab(root)[0]
    return read_appearance(root)


def load_view_result(root: Path, name: str | None = None) -> ViewResult:
    """:func:`ps_lab.view.result.load_result`, or a RelightLab folder read as a result.

    A RelightLab folder (``info.json``, ``plane_N.jpg``) gives its normals from ``normals.png``
    ((n + 1)/2, black outside the object; a flat normal (0, 0, 1) where it has none) and its
    albedo layer from ``albedo.png`` (sRGB decoded); ``albedo_scale`` is ``1 / exposure`` of
    ``info.json`` (the fit relit from above, 99th percentile), which the page divides the
    coefficients by.
    """
    root = Path(root)
    if not (is_relightlab_folder(root) and not (root / "normals.npy").exists()):
        return load_result(root, name)
    appearance, info = read_relightlab(root)
    h, w = appearance.coefficients.shape[:2]
    normals = np.zeros((h, w, 3), np.float32)
    normals[..., 2] = 1.0
    picture = cv2.imread(str(root / "normals.png"), cv2.IMREAD_COLOR)
    if picture is not None and picture.shape[:2] == (h, w):
        rgb = picture[..., ::-1].astype(np.float32)
        decoded = rgb / 127.5 - 1.0
        length = np.linalg.norm(decoded, axis=2, keepdims=True)
        inside = rgb.any(axis=2)
        normals = np.where(inside[..., None], decoded / np.maximum(length, 1e-6), 0.0)
    mask = np.linalg.norm(normals, axis=2) > 0.5
    layers = np.zeros((h, w, len(CHANNELS)), np.float32)
    layers[..., 0:3] = normals
    layers[..., 5:8] = np.nan
    albedo = cv2.imread(str(root / "albedo.png"), cv2.IMREAD_COLOR)
    if albedo is not None and albedo.shape[:2] == (h, w):
        grey = srgb_to_linear(albedo[..., ::-1].astype(np.float32) / 255.0).mean(axis=2)
        layers[..., 3] = np.where(mask, grey, 0.0)
    else:
        layers[..., 3] = mask
    exposure = float(info.get("ps_lab", {}).get("exposure", 1.0))
    has = {"outliers": False, "error": False, "depth": False, "mesh": False}
    metrics = {
        "method": f"RelightLab {info.get('type')}",
        "lights": len(info.get("lights", [])) // 3,
        "pixels": int(mask.sum()),
    }
    return ViewResult(root, name or root.name, layers, 1.0 / exposure, has, metrics, None)


def relightlab_lights(root: Path) -> np.ndarray | None:
    """A RelightLab folder's lights (``info.json``'s ``lights``), or None (not such a folder,
    or no lights).

    Raises
    ------
    DatasetError
        A malformed ``info.json`` (naming it and the field).

    """
    root = Path(root)
    if not is_relightlab_folder(root):
        return None
    lights = np.asarray(read_info(root).get("lights", []), np.float64).reshape(-1, 3)
    return lights if lights.size else None
