"""RelightLab's web layout for PTM and HSH fits, as OpenLIME's RTI layer reads it.

A folder holds ``info.json`` and ``plane_0.jpg``, ``plane_1.jpg``, … (the ``image`` layout of
OpenLIME's ``LayerRTI``), here with ps-lab's ``normals.png`` and ``albedo.png`` beside them.

``info.json`` (the fields OpenLIME's ``ShaderRTI`` reads, RelightLab's names)::

    {"width": W, "height": H, "format": "jpg", "type": "ptm" | "hsh",
     "colorspace": "rgb", "nplanes": 3·K, "quality": Q,
     "lights": [x0, y0, z0, x1, ...],            # the captured light directions
     "materials": [{"scale": [...], "bias": [...], "range": [...]}],   # one per plane
     "ps_lab": {"model": "ptm" | "hsh2" | "hsh3", "exposure": g}}

Colour space ``rgb``: plane ``p = 3k + c`` is the coefficient of basis term ``k`` for channel
``c``; JPEG ``k`` carries planes ``3k, 3k+1, 3k+2`` as its R, G, B. Each plane is quantised to
8 bits by its own scale and bias, ``byte = round((coefficient / scale + bias) · 255)``, and read
back as OpenLIME's shader does, ``coefficient = (byte / 255 − bias) · scale``, with
``scale = max − min`` and ``bias = −min / scale`` over the plane. The basis terms are those of
:mod:`ps_lab.io.appearance` (RelightLab's order and normalisation). The coefficients are
ps-lab's linear fit times ``exposure`` (so the brightest relit pixels are near 1 on screen);
:func:`read_relightlab` divides it out again.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np

from ps_lab.errors import DatasetError, OutputError
from ps_lab.io.appearance import Appearance, appearance_basis

__all__ = [
    "EXPORT_MODELS",
    "INFO",
    "export_error_bound",
    "is_relightlab_folder",
    "read_relightlab",
    "write_relightlab",
]

INFO = "info.json"
#: Appearance models RelightLab's layout can hold: ps-lab model -> (info.json type, terms).
EXPORT_MODELS = {"ptm": ("ptm", 6), "hsh2": ("hsh", 4), "hsh3": ("hsh", 9)}
#: JPEG quality of the planes (chroma kept at full resolution: every channel is a plane).
QUALITY = 100


def is_relightlab_folder(folder: Path) -> bool:
    """Whether ``folder`` looks like RelightLab's web layout (``info.json`` and ``plane_0.jpg``)."""
    folder = Path(folder)
    return (folder / INFO).is_file() and (folder / "plane_0.jpg").is_file()


def quantise_plane(values: np.ndarray) -> tuple[np.ndarray, float, float]:
    """One coefficient plane to bytes with RelightLab's scale and bias.

    Returns
    -------
    bytes : ndarray of uint8, the shape of ``values``
    scale, bias : float
        ``values ≈ (bytes / 255 − bias) · scale``.

    """
    values = np.nan_to_num(np.asarray(values, np.float64))
    low, high = float(values.min()), float(values.max())
    scale = high - low if high > low else 1.0
    bias = -low / scale
    q = np.clip(np.rint((values / scale + bias) * 255.0), 0, 255).astype(np.uint8)
    return q, scale, bias


def write_relightlab(
    folder: Path,
    appearance: Appearance,
    lights: np.ndarray,
    *,
    normal_picture: np.ndarray | None = None,
    albedo_picture: np.ndarray | None = None,
    exposure: float | None = None,
) -> dict:
    """Write a PTM or HSH fit in RelightLab's web layout into ``folder`` (which must exist).

    Parameters
    ----------
    folder : Path
    appearance : Appearance
        Model ``ptm``, ``hsh2`` or ``hsh3``; coefficients (H, W, C, K), C = 3 or 1 (grey,
        written as three equal channels).
    lights : ndarray of shape (n, 3)
        The captured light directions (``info.json``'s ``lights``).
    normal_picture, albedo_picture : ndarray of shape (H, W, 3), uint8, RGB, optional
        Written as ``normals.png`` and ``albedo.png``.
    exposure : float or None
        Gain applied to the coefficients before quantising (default: 1 / the 99th percentile
        of the fit relit from above, so the picture fills the 8-bit display range).

    Returns
    -------
    dict
        The ``info.json`` written.

    Raises
    ------
    OutputError
        A model the layout cannot hold, or a file that cannot be written.

    """
    folder = Path(folder)
    if appearance.model not in EXPORT_MODELS:
        raise OutputError(
            f"--format relight: the result's appearance model is {appearance.model!r}; "
            f"RelightLab's layout holds {', '.join(EXPORT_MODELS)} (reconstruct with "
            "--appearance ptm, hsh2 or hsh3)"
        )
    kind, terms = EXPORT_MODELS[appearance.model]
    coefficients = np.asarray(appearance.coefficients, np.float32)
    height, width, channels, k = coefficients.shape
    if k != terms:
        raise OutputError(f"{appearance.model}: expected {terms} terms per channel, got {k}")
    if channels == 1:
        coefficients = np.repeat(coefficients, 3, axis=2)
    if exposure is None:
        top = appearance_basis(appearance.model, np.array([[0.0, 0.0, 1.0]]))[0]
        relit = np.einsum("hwck,k->hwc", coefficients.astype(np.float64), top)
        peak = float(np.percentile(relit, 99)) if relit.size else 0.0
        exposure = 1.0 / peak if math.isfinite(peak) and peak > 0 else 1.0
    scales, biases = [], []
    for term in range(k):
        jpeg = np.zeros((height, width, 3), np.uint8)
        for c in range(3):
            q, scale, bias = quantise_plane(coefficients[:, :, c, term] * exposure)
            jpeg[..., c] = q
            scales.append(scale)
            biases.append(bias)
        _write_image(folder / f"plane_{term}.jpg", jpeg)
    info = {
        "width": int(width),
        "height": int(height),
        "format": "jpg",
        "type": kind,
        "colorspace": "rgb",
        "nplanes": 3 * k,
        "quality": QUALITY,
        "lights": [float(x) for x in np.asarray(lights, np.float64).reshape(-1)],
        "materials": [{"scale": scales, "bias": biases, "range": scales}],
        "ps_lab": {"model": appearance.model, "exposure": float(exposure)},
    }
    if normal_picture is not None:
        _write_image(folder / "normals.png", normal_picture)
    if albedo_picture is not None:
        _write_image(folder / "albedo.png", albedo_picture)
    try:
        (folder / INFO).write_text(json.dumps(info, indent=1) + "\n", encoding="utf-8")
    except OSError as exc:
        raise OutputError(f"{folder / INFO}: cannot write ({exc.strerror or exc})") from None
    return info


def _write_image(path: Path, rgb: np.ndarray) -> None:
    bgr = np.ascontiguousarray(np.asarray(rgb)[..., ::-1])
    if path.suffix == ".jpg":
        params = [cv2.IMWRITE_JPEG_QUALITY, QUALITY,
                  cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
        ok, data = cv2.imencode(".jpg", bgr, params)
    else:
        ok, data = cv2.imencode(".png", bgr)
    if not ok:
        raise OutputError(f"{path}: cannot encode the image")
    try:
        path.write_bytes(data.tobytes())
    except OSError as exc:
        raise OutputError(f"{path}: cannot write ({exc.strerror or exc})") from None


def read_relightlab(folder: Path) -> tuple[Appearance, dict]:
    """Read a PTM or HSH fit in RelightLab's web layout (``rgb`` colour space).

    Returns
    -------
    appearance : Appearance
        Coefficients (H, W, 3, K) float32, dequantised as OpenLIME does and divided by the
        ``ps_lab`` exposure when the folder has one.
    info : dict
        ``info.json``.

    Raises
    ------
    DatasetError
        A missing or malformed ``info.json`` or plane (the message names the file).

    """
    folder = Path(folder)
    path = folder / INFO
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read RelightLab info ({exc})") from None
    if not isinstance(info, dict):
        raise DatasetError(f"{path}: expected a JSON object")
    kind, colorspace = info.get("type"), info.get("colorspace")
    nplanes = info.get("nplanes")
    if colorspace != "rgb" or kind not in ("ptm", "hsh") or not isinstance(nplanes, int):
        raise DatasetError(
            f"{path}: type {kind!r}, colorspace {colorspace!r}: ps-lab reads ptm and hsh in the "
            "rgb colour space"
        )
    k = nplanes // 3
    model = {("ptm", 6): "ptm", ("hsh", 4): "hsh2", ("hsh", 9): "hsh3"}.get((kind, k))
    if model is None or nplanes != 3 * k:
        raise DatasetError(f"{path}: {kind} with {nplanes} planes is not PTM 6 / HSH 4 or 9 terms")
    try:
        material = info["materials"][0]
        scales = np.asarray(material["scale"], np.float64)
        biases = np.asarray(material["bias"], np.float64)
    except (KeyError, IndexError, TypeError, ValueError):
        raise DatasetError(f"{path}: materials[0] needs scale and bias lists") from None
    if scales.shape != (nplanes,) or biases.shape != (nplanes,) or not (
        np.all(np.isfinite(scales)) and np.all(np.isfinite(biases))
    ):
        raise DatasetError(f"{path}: scale and bias must be {nplanes} finite numbers each")
    width, height = info.get("width"), info.get("height")
    planes = []
    for term in range(k):
        file = folder / f"plane_{term}.jpg"
        picture = cv2.imread(str(file), cv2.IMREAD_COLOR)
        if picture is None:
            raise DatasetError(f"{file}: missing or not a JPEG")
        if (width, height) != (picture.shape[1], picture.shape[0]):
            raise DatasetError(
                f"{file}: {picture.shape[1]}x{picture.shape[0]}, info.json says {width}x{height}"
            )
        planes.append(picture[..., ::-1].astype(np.float64) / 255.0)
    stack = np.stack(planes, axis=-1)  # (H, W, 3, K): channel c of JPEG k = plane 3k + c
    index = 3 * np.arange(k)[None, :] + np.arange(3)[:, None]  # (3, K)
    coefficients = (stack - biases[index]) * scales[index]
    exposure = (info.get("ps_lab") or {}).get("exposure", 1.0)
    if not isinstance(exposure, (int, float)) or not math.isfinite(exposure) or exposure <= 0:
        raise DatasetError(f"{path}: ps_lab.exposure must be a positive number")
    coefficients /= exposure
    meta = {"basis": model, "K": k, "terms": [f"{model}:{i}" for i in range(k)]}
    return Appearance(model, coefficients.astype(np.float32), meta), info


def export_error_bound(info: dict, light: np.ndarray, levels: float = 1.0) -> np.ndarray:
    """Bound of a relit value's error from the 8-bit quantisation, per channel (3,).

    ``Σ_k |b_k(l)| · scale_{3k+c} · levels / 255 / exposure``: each plane's byte is within
    ``levels`` of the exact quantised value (0.5 for rounding alone; JPEG adds its own).
    """
    model = info["ps_lab"]["model"] if "ps_lab" in info else (
        "ptm" if info["type"] == "ptm" else ("hsh3" if info["nplanes"] == 27 else "hsh2")
    )
    basis = np.abs(appearance_basis(model, np.asarray(light, np.float64).reshape(1, 3))[0])
    k = basis.size
    scales = np.asarray(info["materials"][0]["scale"], np.float64).reshape(k, 3)
    exposure = float((info.get("ps_lab") or {}).get("exposure", 1.0))
    return (basis[:, None] * scales).sum(axis=0) * levels / 255.0 / exposure


