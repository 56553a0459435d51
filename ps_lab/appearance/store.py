"""The ``appearance.npz`` file of a result folder: write, read, validate.

One appearance model per pixel (:mod:`ps_lab.appearance.models` defines them): an uncompressed
npz of ``model`` (a name), ``meta`` (a JSON object), ``coefficients`` (H, W, C, K) float32 and
``extra_<name>`` arrays (the model's training lights, basis, visibility, ...). The reader checks
every array and number the evaluation reads, so a damaged or hostile file is one ``error:`` line.
"""

from __future__ import annotations

import json
import math
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from ps_lab.appearance.models import (
    APPEARANCE_FILE,
    APPEARANCE_MODELS,
    BASIS_TERMS,
    FIT_SPACES,
    MAX_LOBE_POWER,
    MAX_STORED,
    RBF_SIGMA_RANGE,
    SMOOTHER_MODELS,
    VISIBILITY_TERMS,
    Appearance,
)
from ps_lab.errors import DatasetError
from ps_lab.io.files import PARTIAL_PREFIX, json_safe, publish_file

__all__ = ["ps_term_problem", "read_appearance", "write_appearance"]

def write_appearance(folder: Path, appearance: Appearance) -> Path:
    """Write ``folder/appearance.npz`` (an uncompressed npz) atomically; return its path.

    The coefficients are streamed into the archive in blocks (they may be a memory map of a
    large capture's fit); the file appears under its name only when complete.
    """
    path = Path(folder) / APPEARANCE_FILE
    temp = path.with_name(PARTIAL_PREFIX + path.name)
    arrays: dict[str, np.ndarray] = {
        "model": np.array(appearance.model),
        "meta": np.array(json.dumps(json_safe(appearance.meta))),
        "coefficients": appearance.coefficients,
    }
    for name, value in appearance.extra.items():
        arrays[f"extra_{name}"] = np.asarray(value)
    try:
        with zipfile.ZipFile(temp, "w", zipfile.ZIP_STORED, allowZip64=True) as archive:
            for name, value in arrays.items():
                if name == "coefficients" and value.dtype != np.float32:
                    value = value.astype(np.float32)
                with archive.open(name + ".npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)
        publish_file(temp, path)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise
    return path


def read_appearance(folder: Path) -> Appearance | None:
    """Read ``folder/appearance.npz`` (None when absent), validated.

    Raises
    ------
    DatasetError
        The file is unreadable or inconsistent (naming the file).

    """
    path = Path(folder) / APPEARANCE_FILE
    if not path.is_file():
        return None
    try:  # the file opened here: numpy leaves it open when the archive is damaged
        with open(path, "rb") as handle:
            data = np.load(handle, allow_pickle=False)
            if not isinstance(data, np.lib.npyio.NpzFile):
                raise ValueError("a single array, not an .npz archive")
            with data:
                model = str(data["model"])
                coefficients = np.asarray(data["coefficients"])
                meta = json.loads(str(data["meta"]))
                extra = {k[6:]: np.asarray(data[k]) for k in data.files
                         if k.startswith("extra_")}
    except RecursionError:
        raise DatasetError(f"{path}: not a readable appearance file (its meta is nested too "
                           "deeply)") from None
    except MemoryError:
        raise DatasetError(f"{path}: not a readable appearance file (an array too large to "
                           "read)") from None
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError, zlib.error,
            NotImplementedError) as exc:
        raise DatasetError(f"{path}: not a readable appearance file ({exc})") from None
    _validate(path, model, coefficients, meta, extra)
    return Appearance(model, coefficients, meta, extra)


def _validate(path: Path, model: str, coeffs: np.ndarray, meta: Any, extra: dict) -> None:
    """Every array and number the evaluation reads: shapes, dtypes, finite values, sane
    parameters (the lobe exponents in [1, :data:`MAX_LOBE_POWER`], rbf's σ in
    :data:`RBF_SIGMA_RANGE`, its training lights unit vectors)."""
    def fail(why: str) -> None:
        raise DatasetError(f"{path}: {why}")

    if model not in APPEARANCE_MODELS:
        fail(f"unknown appearance model {model!r}")
    if coeffs.dtype != np.float32 or coeffs.ndim != 4 or coeffs.shape[2] not in (1, 3):
        fail(f"coefficients must be float32 (H, W, 1|3, K), not {coeffs.dtype} {coeffs.shape}")
    if not np.all(np.isfinite(coeffs)):
        fail("coefficients are not all finite")
    if coeffs.size and float(np.max(np.abs(coeffs))) > MAX_STORED:
        fail(f"coefficients beyond ±{MAX_STORED:.0e} (the solver's units are of order 1)")
    if not isinstance(meta, dict):
        fail("meta is not a JSON object")
    for name, value in extra.items():
        if value.dtype.kind != "f" or not np.all(np.isfinite(value)):
            fail(f"extra_{name} must hold finite floats, not {value.dtype} {value.shape}")
        if value.size and float(np.max(np.abs(value))) > MAX_STORED:
            fail(f"extra_{name} holds values beyond ±{MAX_STORED:.0e}")
    k = coeffs.shape[3]
    if model in BASIS_TERMS and k != BASIS_TERMS[model]:
        fail(f"{model} has {BASIS_TERMS[model]} terms, the file {k}")
    if model == "ps":
        terms = meta.get("terms")
        if not isinstance(terms, list) or len(terms) != k:
            fail("ps terms missing or not matching the coefficients")
        for term in terms:
            why = ps_term_problem(term)
            if why:
                fail(why)
    vis = extra.get("visibility")
    if vis is not None and (model != "ps" or vis.dtype != np.float32
                            or vis.shape != (*coeffs.shape[:2], VISIBILITY_TERMS)):
        fail(f"visibility must be a finite float32 (H, W, 4) of a ps model, not {vis.dtype} "
             f"{vis.shape}")
    if meta.get("space", "linear") not in FIT_SPACES or (
            model in ("ps", "none") and meta.get("space", "linear") != "linear"):
        fail(f"fit space {meta.get('space')!r} is not one of {', '.join(FIT_SPACES)} for {model}")
    if model in SMOOTHER_MODELS:
        lights, basis = extra.get("lights"), extra.get("basis")
        if (lights is None or basis is None or lights.ndim != 2 or lights.shape[1] != 3
                or not 1 <= k <= lights.shape[0]):
            fail(f"{model} needs its training lights (n, 3) and basis (C, n, K), 1 <= K <= n")
        if basis.shape != (coeffs.shape[2], lights.shape[0], k):
            fail(f"{model} basis shape {basis.shape} does not match the coefficients")
        if not (np.all(np.isfinite(lights)) and np.all(np.isfinite(basis))):
            fail(f"{model} lights or basis not finite")
        if np.any(np.abs(np.linalg.norm(lights.astype(np.float64), axis=1) - 1) > 1e-3):
            fail(f"{model} training lights must be unit directions")
        sigma = meta.get("sigma")
        low, high = RBF_SIGMA_RANGE
        if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not (
                low <= sigma <= high):
            fail(f"{model} sigma must be a number in [{low:g}, {high:g}], not {sigma!r}")
        resolution = meta.get("resolution")
        if model == "bln" and not (isinstance(resolution, int) and not isinstance(resolution, bool)
                                   and 2 <= resolution <= 1024):
            fail("bln resolution missing or not an integer in [2, 1024]")
        solve = extra.get("solve")
        if model == "gp" and (solve is None or solve.shape != (lights.shape[0] + 6, lights.shape[0])
                              or not np.all(np.isfinite(solve))):
            fail("gp needs its finite solve matrix (n + 6, n)")


def ps_term_problem(term: Any) -> str | None:
    """Why ``term`` is not a ps term this module evaluates (None when it is)."""
    if not isinstance(term, str):
        return f"ps term {term!r} is not a name"
    kind, _, argument = term.partition(":")
    if kind in ("lambert", "ambient", "lx", "ly", "lz") and not argument:
        return None
    if kind in ("lobe", "lobex", "lobey"):
        try:
            power = float(argument)
        except ValueError:
            power = math.nan
        if not 1.0 <= power <= MAX_LOBE_POWER:
            return (f"ps term {term!r}: the lobe exponent must be a number in "
                    f"[1, {MAX_LOBE_POWER:g}]")
        return None
    if kind == "hsh" and argument in tuple(str(i) for i in range(9)):
        return None
    return f"unknown ps term {term!r}"
