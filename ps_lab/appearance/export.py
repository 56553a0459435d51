"""``ps-lab view RESULT --export DIR --format relight``: a result in RelightLab's web layout.

The format itself (``info.json``, ``plane_N.jpg``, quantisation) is
:mod:`ps_lab.appearance.relightlab`, the conversion of any other model to its ``rbf`` layout
:mod:`ps_lab.appearance.rbf_conversion`; this module gathers what a result folder holds (its
appearance fit from ``appearance.npz``, its captured lights, its normal and albedo pictures) and
writes the folder staged (complete or absent). :func:`result_lights` is also what the viewer's
light disc shows.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import cv2
import numpy as np

from ps_lab.appearance.models import Appearance, evaluate_appearance
from ps_lab.appearance.rbf_conversion import convert_to_rbf, grey_psnr
from ps_lab.appearance.relight import read_relight_source, relight_picture
from ps_lab.appearance.relightlab import (
    EXPORT_MODELS,
    INFO,
    read_relightlab,
    relightlab_lights,
    write_relightlab,
    write_relightlab_rbf,
)
from ps_lab.appearance.store import read_appearance
from ps_lab.errors import DatasetError, OutputError, PsLabError
from ps_lab.io.files import output_target, staged_folder
from ps_lab.io.light_files import find_lp, read_light_directions, read_lp

__all__ = ["captured_lights", "check_export_folder", "export_relightlab", "result_lights"]


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
    layout (:mod:`ps_lab.appearance.rbf_conversion`) and the conversion's PSNR against the model is
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
