"""The viewer's appearance layers: a fitted model's coefficients as tiled half-float planes.

A result with ``appearance.npz`` (``ps-lab reconstruct --appearance``), or a RelightLab export,
gets a third tile set beside its layers, ``data/r{i}/a/{level}/{col}_{row}.bin``: the ``3·K``
coefficients of every pixel, term-major (coefficient ``3k + c`` is term ``k`` of channel ``c``),
divided by the result's ``albedo_scale`` (so the relit picture has the Lambertian layer's scale),
then, for a ``ps`` model with a visibility (``extra["visibility"]``), its four weights
``w_x, w_y, w_z, w_1`` (coefficients ``3K .. 3K + 3``, not scaled), packed four to an RGBA16F
plane and the planes stacked one under the other (a tile is one
``w × (h · planes)`` texture the shader reads with ``texelFetch``). Levels are those of
:mod:`ps_lab.view.tiles` (2 × 2 blocks averaged over their mask pixels: the linear models'
relit picture of a block is the block's mean picture).

The page's shader (``static/render.js``) evaluates the bases of :mod:`ps_lab.appearance.models`:
``ptm``, ``hsh2``, ``hsh3`` (weights of the light computed once per frame), ``ps`` (per pixel,
with the tile's normal) and the interpolating models ``rbf``, ``bln``, ``gp`` (per frame, the
page computes the model's weights over the training lights ``w(l)``
(:mod:`ps_lab.appearance.smoothers`) and sums them times each channel's basis,
``Σ_i w_i(l) B_c[i, k]``; the shader takes the dot product with the pixel's coefficients). An
interpolating fit whose channels share their coefficients (a grey fit, or a RelightLab / OpenLIME
``mrgb`` layout read back) is tiled with ``K`` coefficients per pixel instead of ``3·K``
(``shared`` in the manifest).

A fit in sRGB-encoded space (``meta["space"] == "srgb"``) predicts encoded values of the solver's
units: its coefficients are tiled as they are (not divided by ``albedo_scale``), and the shader
decodes the prediction as :func:`ps_lab.appearance.models.evaluate_appearance` does (clipped to
[0, 1], then sRGB to linear) and multiplies it by ``gain = 1 / albedo_scale`` (the manifest's
``space`` and ``gain``). Its coarser levels average the encoded coefficients (the decoded
picture of a block is then close to, not exactly, the block's mean picture).
"""

from __future__ import annotations

import numpy as np

from ps_lab.appearance.models import BASIS_TERMS, SMOOTHER_MODELS, Appearance
from ps_lab.view.tiles import TILE, Pyramid, block_sum, half_float, pad_even

__all__ = ["VIEW_MODELS", "AppearanceTiles", "appearance_entry", "appearance_tiles"]

#: Models the page relights with their own basis (the others are Lambertian there).
VIEW_MODELS = ("ptm", "hsh2", "hsh3", "ps", "rbf", "bln", "gp")
#: Most terms per channel the shader takes (its uniform arrays; the interpolating models have
#: their own).
MAX_TERMS = 16
MAX_RBF_TERMS = 32


class AppearanceTiles(Pyramid):
    """The levels of one result's coefficients, float16 (H_k, W_k, 3K), with tile access."""

    def __init__(self, levels: list[np.ndarray], gain: float = 1.0) -> None:
        super().__init__(levels)
        #: What the page multiplies an sRGB-space fit's decoded prediction by (1 for linear fits,
        #: whose coefficients carry the scale).
        self.gain = gain


def appearance_tiles(
    appearance: Appearance, mask: np.ndarray, albedo_scale: float
) -> AppearanceTiles | None:
    """The tiled coefficients of a model the page relights (None for the others).

    Parameters
    ----------
    appearance : Appearance
        Coefficients (H, W, C, K), C = 3 or 1 (repeated to three).
    mask : ndarray of shape (H, W), bool
        The result's solved pixels (the layers' mask).
    albedo_scale : float
        The result's ``albedo_scale``; the coefficients of a linear-space fit are divided by
        it, an sRGB-space fit's decoded prediction is (``AppearanceTiles.gain``).
    """
    if appearance.model not in VIEW_MODELS:
        return None
    coefficients = np.asarray(appearance.coefficients, np.float32)
    h, w, c, k = coefficients.shape
    smoother = appearance.model in SMOOTHER_MODELS
    limit = MAX_RBF_TERMS if smoother else MAX_TERMS
    if k == 0 or k > limit or (h, w) != mask.shape:
        return None
    if smoother and shared_coefficients(coefficients):
        flat = coefficients[:, :, 0, :]  # index k
    else:
        if c == 1:
            coefficients = np.repeat(coefficients, 3, axis=2)
        # term-major: index 3k + c
        flat = coefficients[:, :, :3, :].transpose(0, 1, 3, 2).reshape(h, w, 3 * k)
    srgb = appearance.meta.get("space") == "srgb"
    divisor = np.float32(1.0 if srgb else albedo_scale)
    flat = np.where(mask[..., None], np.nan_to_num(flat) / divisor, 0.0)
    vis = appearance.extra.get("visibility") if appearance.model == "ps" else None
    if vis is not None:  # V = clamp(w·[l, 1], 0, 1), shared by the channels, unscaled
        flat = np.concatenate([flat, np.asarray(vis, np.float32)], axis=2)
    levels = [half_float(flat)]
    current, inside = flat, mask.astype(np.float32)
    while max(current.shape[:2]) > TILE:
        current, inside = _halve(current, inside)
        levels.append(half_float(current))
    return AppearanceTiles(levels, 1.0 / float(albedo_scale) if srgb else 1.0)


def shared_coefficients(coefficients: np.ndarray) -> bool:
    """Whether every channel has the same coefficients (one channel, or equal channels)."""
    c = coefficients.shape[2]
    return c == 1 or all(
        np.array_equal(coefficients[:, :, 0], coefficients[:, :, i]) for i in range(1, c)
    )


def appearance_entry(appearance: Appearance | None, tiles: AppearanceTiles | None) -> dict | None:
    """The manifest's ``appearance`` entry: model, terms, planes, fit ``space`` and ``gain``, and
    a note when not relit.

    An ``rbf``, ``bln`` or ``gp`` entry adds ``rbf``: ``lights`` (n × 3, flat), ``sigma`` and
    ``basis`` (the per-channel basis (3, n, K), flat, a one-channel basis repeated), for ``bln``
    ``resolution``, for ``gp`` ``solve`` ((n + 6) × n, flat); and ``shared``.
    """
    if appearance is None:
        return None
    k = int(appearance.coefficients.shape[3])
    entry = {
        "model": appearance.model,
        "K": k,
        "terms": list(appearance.meta.get("terms", [])) if appearance.model == "ps" else [],
        "visibility": appearance.model == "ps" and "visibility" in appearance.extra,
        "planes": None if tiles is None else tiles.planes,
        "space": str(appearance.meta.get("space", "linear")),
        "gain": 1.0 if tiles is None else float(tiles.gain),
        "note": None,
    }
    if appearance.model in SMOOTHER_MODELS and tiles is not None:
        basis = np.asarray(appearance.extra["basis"], np.float64)
        basis = np.repeat(basis, 3, axis=0) if basis.shape[0] == 1 else basis[:3]
        entry["shared"] = bool(tiles.levels[0].shape[2] == k)
        entry["rbf"] = {
            "lights": [float(x) for x in np.asarray(appearance.extra["lights"]).reshape(-1)],
            "sigma": float(appearance.meta["sigma"]),
            "basis": [float(x) for x in np.nan_to_num(basis).reshape(-1)],
        }
        if appearance.model == "bln":
            entry["rbf"]["resolution"] = int(appearance.meta["resolution"])
        if appearance.model == "gp":
            solve = np.asarray(appearance.extra["solve"], np.float64).reshape(-1)
            entry["rbf"]["solve"] = [float(x) for x in solve]
    if tiles is None:
        entry["note"] = (
            f"the page relights {appearance.model} as Lambertian (it evaluates "
            f"{', '.join(VIEW_MODELS)}); ps-lab relight renders the fitted model"
        )
    elif appearance.model in BASIS_TERMS and k != BASIS_TERMS[appearance.model]:
        entry["note"] = f"{appearance.model} with {k} terms"
    return entry


def _halve(values: np.ndarray, inside: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """2 × 2 blocks averaged over their mask pixels; a block is inside when half of it is."""
    values, inside = pad_even(values), pad_even(inside)
    count = block_sum(inside)
    out = block_sum(values * inside[..., None]) / np.maximum(count, 1)[..., None]
    keep = count >= 2
    out[~keep] = 0.0
    return out.astype(np.float32), keep.astype(np.float32)
