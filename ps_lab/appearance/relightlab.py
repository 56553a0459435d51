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
:mod:`ps_lab.appearance.models` (RelightLab's order and normalisation). The coefficients are
ps-lab's linear fit times ``exposure`` (so the brightest relit pixels are near 1 on screen);
:func:`read_relightlab` divides it out again.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np

from ps_lab.appearance.models import Appearance, appearance_basis
from ps_lab.errors import DatasetError, OutputError

__all__ = [
    "EXPORT_MODELS",
    "INFO",
    "export_error_bound",
    "is_relightlab_folder",
    "quantise_rbf_basis",
    "rbf_appearance",
    "read_info",
    "read_relightlab",
    "relightlab_lights",
    "write_relightlab",
    "write_relightlab_rbf",
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
    if appearance.model not in EXPORT_MODELS or appearance.meta.get("space", "linear") != "linear":
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
    _write_extras(folder, info, normal_picture, albedo_picture)
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


def _field(path: Path, info: dict, name: str, check, what: str):
    """``info[name]`` when ``check`` accepts it, else a :class:`DatasetError` naming the field."""
    value = info.get(name)
    try:
        good = check(value)
    except (TypeError, ValueError):
        good = False
    if not good:
        raise DatasetError(f"{path}: {name!r} must be {what}, got {_short(value)}")
    return value


def _short(value) -> str:
    text = json.dumps(value) if not isinstance(value, float) else repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _numbers(value, count: int | None = None, multiple: int = 1) -> bool:
    """A list of finite numbers (``count`` long, or a multiple of ``multiple``)."""
    if not isinstance(value, list) or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value
    ):
        return False
    return len(value) == count if count is not None else len(value) % multiple == 0


def _is_size(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 < value <= 1 << 16


def read_info(folder: Path) -> dict:
    """``folder/info.json`` read and validated field by field (every field ps-lab reads).

    Raises
    ------
    DatasetError
        Unreadable, not an object, or a field of the wrong type or value (naming info.json and
        the field).

    """
    path = Path(folder) / INFO
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise DatasetError(f"{path}: cannot read RelightLab info ({reason})") from None
    if not isinstance(info, dict):
        raise DatasetError(f"{path}: expected a JSON object")
    kind, colorspace = info.get("type"), info.get("colorspace")
    if (kind, colorspace) not in (("ptm", "rgb"), ("hsh", "rgb"), ("rbf", "mrgb")):
        raise DatasetError(
            f"{path}: type {_short(kind)}, colorspace {_short(colorspace)}: ps-lab reads ptm and "
            "hsh in the rgb colour space and rbf in mrgb"
        )
    _field(path, info, "width", _is_size, "a positive whole number of pixels")
    _field(path, info, "height", _is_size, "a positive whole number of pixels")
    nplanes = _field(path, info, "nplanes", lambda v: _is_size(v) and v <= 96,
                     "a whole number of planes (1 to 96)")
    if kind in ("ptm", "hsh"):
        k = nplanes // 3
        model = {("ptm", 6): "ptm", ("hsh", 4): "hsh2", ("hsh", 9): "hsh3"}.get((kind, k))
        if model is None or nplanes != 3 * k:
            raise DatasetError(
                f"{path}: {kind} with {nplanes} planes is not PTM 6 / HSH 4 or 9 terms"
            )
    lights = info.get("lights", [])
    if not _numbers(lights, multiple=3):
        raise DatasetError(
            f"{path}: 'lights' must be a list of x, y, z numbers, got {_short(lights)}"
        )
    materials = _field(path, info, "materials",
                       lambda v: isinstance(v, list) and v and isinstance(v[0], dict),
                       "a list holding one object of scale and bias")
    for name in ("scale", "bias") + (("range",) if kind == "rbf" else ()):
        if not _numbers(materials[0].get(name), nplanes):
            raise DatasetError(f"{path}: materials[0].{name} must be {nplanes} finite numbers")
    if kind == "rbf":
        n = len(lights) // 3
        if n == 0:
            raise DatasetError(f"{path}: an rbf layout needs its lights")
        _field(path, info, "sigma", lambda v: isinstance(v, (int, float)) and
               not isinstance(v, bool) and math.isfinite(v) and v > 0, "a positive number")
        _field(path, info, "basis", lambda v: _numbers(v, (nplanes + 1) * n * 3) and all(
            0 <= b <= 255 for b in v), f"{(nplanes + 1) * n * 3} numbers 0..255")
        if not all(r != 0 for r in materials[0]["range"]):
            raise DatasetError(f"{path}: materials[0].range must not hold 0")
    own = info.get("ps_lab", {})
    if not isinstance(own, dict):
        raise DatasetError(f"{path}: 'ps_lab' must be an object, got {_short(own)}")
    exposure = own.get("exposure", 1.0)
    if isinstance(exposure, bool) or not isinstance(exposure, (int, float)) or not (
        math.isfinite(exposure) and exposure > 0
    ):
        raise DatasetError(f"{path}: ps_lab.exposure must be a positive number")
    return info


def _planes(folder: Path, info: dict) -> np.ndarray:
    """The dequantised planes (H, W, nplanes), float64, ``(byte / 255 − bias) · scale``."""
    nplanes, width, height = info["nplanes"], info["width"], info["height"]
    pictures = []
    for j in range(-(-nplanes // 3)):
        file = folder / f"plane_{j}.jpg"
        picture = cv2.imread(str(file), cv2.IMREAD_COLOR)
        if picture is None:
            raise DatasetError(f"{file}: missing or not a JPEG")
        if (width, height) != (picture.shape[1], picture.shape[0]):
            raise DatasetError(
                f"{file}: {picture.shape[1]}x{picture.shape[0]}, info.json says {width}x{height}"
            )
        pictures.append(picture[..., ::-1].astype(np.float64) / 255.0)
    stack = np.concatenate(pictures, axis=2)[..., :nplanes]  # plane p: JPEG p // 3, channel p % 3
    material = info["materials"][0]
    return (stack - np.asarray(material["bias"])) * np.asarray(material["scale"])


def read_relightlab(folder: Path) -> tuple[Appearance, dict]:
    """Read a RelightLab web layout: PTM or HSH (``rgb``) or RBF (``mrgb``).

    An ``rbf`` layout becomes ps-lab's ``rbf`` model exactly (see :func:`rbf_appearance`).

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
    info = read_info(folder)
    planes = _planes(folder, info)
    exposure = float(info.get("ps_lab", {}).get("exposure", 1.0))
    if info["type"] == "rbf":
        appearance = rbf_appearance(info, planes)
        coefficients = appearance.coefficients / exposure
        return Appearance("rbf", coefficients.astype(np.float32), appearance.meta,
                          appearance.extra), info
    k = info["nplanes"] // 3
    model = {("ptm", 6): "ptm", ("hsh", 4): "hsh2", ("hsh", 9): "hsh3"}[(info["type"], k)]
    h, w = planes.shape[:2]
    coefficients = planes.reshape(h, w, k, 3).transpose(0, 1, 3, 2) / exposure  # (H, W, 3, K)
    meta = {"basis": model, "K": k, "terms": [f"{model}:{i}" for i in range(k)]}
    return Appearance(model, coefficients.astype(np.float32), meta), info


# --- RBF (mrgb): RelightLab's PCA of the relit pictures, interpolated over the lights ----------


def quantise_rbf_basis(
    mean: np.ndarray, eigen: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The ``basis`` bytes of an ``rbf`` layout and what OpenLIME decodes from them.

    Parameters
    ----------
    mean : ndarray of shape (n, 3)
        The mean picture's colour at each light (exposed; clipped to 0..1).
    eigen : ndarray of shape (P, n, 3)
        The principal components.

    Returns
    -------
    mean_bytes : ndarray of shape (n, 3), uint8
        ``round(mean · 255)``, decoded ``byte / 255``.
    eigen_bytes : ndarray of shape (P, n, 3), uint8
        ``round(E_p · range_p + 127)``, decoded ``(byte − 127) / range_p``.
    ranges : ndarray of shape (P,)
        ``127 / max |E_p|`` (``materials[0].range``).
    decoded_mean, decoded_eigen : the decoded values (shapes as given), float64

    """
    mean = np.clip(np.nan_to_num(np.asarray(mean, np.float64)), 0.0, 1.0)
    eigen = np.nan_to_num(np.asarray(eigen, np.float64))
    mean_bytes = np.rint(mean * 255.0).astype(np.uint8)
    peak = np.abs(eigen).reshape(len(eigen), -1).max(axis=1) if eigen.size else np.zeros(0)
    ranges = 127.0 / np.where(peak > 0, peak, 1.0)
    eigen_bytes = np.clip(np.rint(eigen * ranges[:, None, None] + 127.0), 0, 255).astype(np.uint8)
    decoded = (eigen_bytes.astype(np.float64) - 127.0) / ranges[:, None, None]
    return mean_bytes, eigen_bytes, ranges, mean_bytes / 255.0, decoded


def rbf_appearance(info: dict, planes: np.ndarray) -> Appearance:
    """An ``rbf`` layout as ps-lab's ``rbf`` model, exactly.

    OpenLIME relights pixel coefficients ``x`` (P,) at light ``l`` as
    ``I_c(l) = Σ_i w_i(l) (μ_{i,c} + Σ_p x_p E_{p,i,c})`` with the normalised Gaussian weights
    ``w_i`` of width ``sigma`` over the lights: ps-lab's ``rbf`` with ``K = P + 1`` terms per
    channel, coefficients ``(1, x_1 … x_P)`` (the same for every channel) and per-channel basis
    ``B_c = [μ_{·,c}, E_{1,·,c} … E_{P,·,c}]`` (n, K).

    Parameters
    ----------
    info : dict
        A validated ``info.json`` of type ``rbf`` (:func:`read_info`).
    planes : ndarray of shape (H, W, P)
        The dequantised coefficients.

    Returns
    -------
    Appearance
        Model ``rbf``, coefficients (H, W, 3, P + 1) float32 (not divided by the exposure).

    """
    nplanes = info["nplanes"]
    lights = np.asarray(info["lights"], np.float64).reshape(-1, 3)
    n = len(lights)
    raw = np.asarray(info["basis"], np.float64).reshape(nplanes + 1, n, 3)
    ranges = np.asarray(info["materials"][0]["range"], np.float64)
    basis = np.empty((3, n, nplanes + 1))
    basis[:, :, 0] = raw[0].T / 255.0
    basis[:, :, 1:] = ((raw[1:] - 127.0) / ranges[:, None, None]).transpose(2, 1, 0)
    h, w = planes.shape[:2]
    coefficients = np.ones((h, w, 3, nplanes + 1), np.float32)
    coefficients[..., 1:] = planes[:, :, None, :]
    meta = {"basis": "rbf", "K": nplanes + 1, "sigma": float(info["sigma"])}
    return Appearance("rbf", coefficients, meta, {"lights": lights, "basis": basis})


def write_relightlab_rbf(
    folder: Path,
    lights: np.ndarray,
    sigma: float,
    mean_bytes: np.ndarray,
    eigen_bytes: np.ndarray,
    ranges: np.ndarray,
    coefficients: np.ndarray,
    *,
    exposure: float,
    source: str,
    normal_picture: np.ndarray | None = None,
    albedo_picture: np.ndarray | None = None,
    extra: dict | None = None,
) -> dict:
    """Write an ``rbf`` layout (RelightLab's ``mrgb`` colour space) into ``folder``.

    Parameters
    ----------
    folder : Path
        Must exist.
    lights : ndarray of shape (n, 3)
        Unit directions the basis is sampled at.
    sigma : float
        Width of the Gaussian weights.
    mean_bytes, eigen_bytes, ranges
        From :func:`quantise_rbf_basis`.
    coefficients : ndarray of shape (H, W, P)
        Each pixel's coefficients on the decoded basis (exposed units).
    exposure : float
        The gain the pictures were multiplied by (``ps_lab.exposure``).
    source : str
        The ps-lab model converted (``ps_lab.model``).
    normal_picture, albedo_picture : ndarray of shape (H, W, 3), uint8, optional
    extra : dict, optional
        More ``ps_lab`` fields (JSON-safe).

    Returns
    -------
    dict
        The ``info.json`` written.

    """
    folder = Path(folder)
    coefficients = np.asarray(coefficients, np.float64)
    height, width, nplanes = coefficients.shape
    scales, biases = [], []
    for j in range(-(-nplanes // 3)):
        jpeg = np.zeros((height, width, 3), np.uint8)
        for c in range(3):
            p = 3 * j + c
            if p < nplanes:
                jpeg[..., c], scale, bias = quantise_plane(coefficients[..., p])
                scales.append(scale)
                biases.append(bias)
        _write_image(folder / f"plane_{j}.jpg", jpeg)
    basis = np.concatenate([mean_bytes[None], eigen_bytes]).reshape(-1)
    info = {
        "width": int(width),
        "height": int(height),
        "format": "jpg",
        "type": "rbf",
        "colorspace": "mrgb",
        "sigma": float(sigma),
        "lights": [round(float(x), 6) for x in np.asarray(lights, np.float64).reshape(-1)],
        "nplanes": int(nplanes),
        "quality": QUALITY,
        "basis": [int(b) for b in basis],
        "materials": [{"range": [float(r) for r in ranges], "scale": scales, "bias": biases}],
        "ps_lab": {"model": source, "exposure": float(exposure), **(extra or {})},
    }
    _write_extras(folder, info, normal_picture, albedo_picture)
    return info


def _write_extras(folder: Path, info: dict, normal_picture, albedo_picture) -> None:
    if normal_picture is not None:
        _write_image(folder / "normals.png", normal_picture)
    if albedo_picture is not None:
        _write_image(folder / "albedo.png", albedo_picture)
    try:
        (folder / INFO).write_text(json.dumps(info, indent=1) + "\n", encoding="utf-8")
    except OSError as exc:
        raise OutputError(f"{folder / INFO}: cannot write ({exc.strerror or exc})") from None


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
