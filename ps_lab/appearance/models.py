"""Per-pixel appearance models: their bases and their evaluation.

A result folder may hold ``appearance.npz`` (:mod:`ps_lab.appearance.store`): the coefficients
of one appearance model per pixel, fitted by :mod:`ps_lab.appearance.fit` beside the normals
(``ps-lab reconstruct --appearance``), read by ``ps-lab relight``, the viewer and the RelightLab
export. This module defines the models (coefficients and basis functions, no fitting, no file);
every basis takes unit light directions in the dataset's light frame (x right, y up, z toward the
camera).

Models
------
``ptm`` (6 terms, Malzbender et al. 2001), in RelightLab's / OpenLIME's order::

    [1, lx, ly, lx², lx·ly, ly²]

``hsh2`` (4 terms) and ``hsh3`` (9 terms): the hemispherical harmonics of Gautron et al. 2004 as
RTIBuilder, RelightLab and OpenLIME define them, with θ = acos(lz) (clamped to [0, π/2]),
φ = atan2(ly, lx), c = cos θ, s = sqrt(c − c²)::

    h0 = 1/sqrt(2π)
    h1 = sqrt(6/π)  · cos φ · s
    h2 = sqrt(3/2π) · (2c − 1)
    h3 = sqrt(6/π)  · sin φ · s
    h4 = sqrt(30/π) · cos 2φ · (c² − c)
    h5 = sqrt(30/π) · cos φ · (2c − 1) · s
    h6 = sqrt(5/2π) · (6c² − 6c + 1)
    h7 = sqrt(30/π) · sin φ · (2c − 1) · s
    h8 = sqrt(30/π) · sin 2φ · (c² − c)

(order 2 is h0..h3, order 3 is h0..h8; OpenLIME also clamps θ ≤ π/2 − 0.15 when it displays.)

``rbf``: RelightLab's radial-basis interpolation over the ``n`` training lights ``L_i``, with
normalised Gaussian weights ``w_i(l) = exp(−|l − L_i|²/σ²) / Σ_j exp(−|l − L_j|²/σ²)``; each
channel's ``n`` training values are stored compressed on a per-channel basis ``B_c`` (n, K) (an
uncentred PCA of the observations), so that ``I_c(l) = w(l)ᵀ B_c x_c`` with the pixel's
coefficients ``x_c`` (K,). ``extra`` holds ``lights`` (n, 3) and ``basis`` (C, n, K); ``meta``
holds ``sigma``.

``ps`` (ps-lab's own): the solver's normal ``n`` and albedo ``ρ_c`` plus a few closed-form terms::

    I_c(l) = ρ_c · max(n·l, 0) + Σ_k C[c, k] · b_k(l, n)

with the view ``v = (0, 0, 1)``, ``h = normalise(l + v)``, and ``b_k`` named in
``meta["terms"]`` from this vocabulary (:func:`ps_term`):

- ``"lambert"``: ``max(n·l, 0)`` (a correction of the albedo where the fit disagrees);
- ``"lx"``, ``"ly"``, ``"lz"``: ``l_x · step(n·l)`` etc. (together: a Lambertian term of a
  corrected scaled normal ``ρn + (C_x, C_y, C_z)`` on the lit side of the solver's normal);
- ``"ambient"``: ``1`` (inter-reflection, ambient light);
- ``"lobe:P"``: ``max(n·h, 0)^P · step(n·l)``, a specular lobe of exponent ``P`` around the half
  vector, zero where the light is behind the surface (``step(x)`` is 1 for x > 0, else 0);
- ``"lobex:P"``, ``"lobey:P"``: ``max(n·h, 0)^(P−1) · h_x · step(n·l)`` (and ``h_y``): with
  ``lobe:P``, a lobe whose axis may move away from ``n`` (first order);
- ``"hsh:i"``: the HSH term ``h_i(l)`` above.

**Visibility** (cast shadows; ``extra["visibility"]``, (H, W, 4) float32, one per pixel shared by
the channels, ``meta["visibility"] = "clip-linear"``): a soft half-space of the light directions
from which the pixel is not shadowed by the rest of the object::

    V(l) = clamp(w_x·l_x + w_y·l_y + w_z·l_z + w_1, 0, 1)

multiplies the Lambertian term and every term lit by the light (``lambert``, ``lx``, ``ly``,
``lz``, ``lobe*``), not ``ambient`` nor ``hsh:i``::

    I_c(l) = V(l) · (ρ_c · max(n·l, 0) + Σ_direct C[c, k] · b_k) + Σ_other C[c, k] · b_k

(GLSL: ``float V = clamp(dot(vis, vec4(l, 1.0)), 0.0, 1.0);``). Without ``extra["visibility"]``,
``V = 1``. :func:`ps_visibility` evaluates it.

The default term list is :data:`PS_TERMS`: ``lx, ly, lz, ambient, lobe:4, lobe:32`` (6 per
channel) with the visibility (4 per pixel); with the normal's 2 and the albedo it is 27 numbers
per pixel in colour (13 in grey), as many as HSH order 3's 27 (9). Every term is bounded by 1
for any light, so the model cannot explode outside the captured range of lights (unlike PTM's and HSH's polynomials).

``bln`` and ``gp``: interpolating models stored as ``rbf`` is (``lights``, ``basis``,
coefficients), with other weights ``w(l)`` over the training lights
(:mod:`ps_lab.appearance.smoothers`): ``bln`` RelightLab's bilinear grid (``meta`` ``sigma`` and
``resolution``), ``gp`` kernel-ridge regression with a PTM mean (``meta`` ``sigma`` and ``ridge``,
``extra["solve"]`` (n + 6, n)).

**Fit space** (``meta["space"]``, any model but ``ps`` and ``none``; absent means ``"linear"``):
``"srgb"``: the coefficients model the sRGB-encoded observations (of the solver's units), and the
evaluation decodes its prediction (clipped to [0, 1]) to linear light.

``none``: Lambertian only, ``ρ_c · max(n·l, 0)``, no coefficients.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ps_lab.appearance.smoothers import bln_weights, gaussian_weights, gp_weights
from ps_lab.io.encoding import srgb_to_linear

__all__ = [
    "APPEARANCE_FILE",
    "APPEARANCE_MODELS",
    "BASIS_TERMS",
    "FIT_SPACES",
    "PS_TERMS",
    "SMOOTHER_MODELS",
    "VISIBILITY_TERMS",
    "Appearance",
    "appearance_basis",
    "coefficients_per_pixel",
    "evaluate_appearance",
    "hsh_basis",
    "is_direct",
    "lambertian",
    "ps_basis",
    "ps_term",
    "ps_visibility",
    "ptm_basis",
    "rbf_weights",
    "smoother_weights",
]

APPEARANCE_FILE = "appearance.npz"
APPEARANCE_MODELS = ("ps", "ptm", "hsh2", "hsh3", "rbf", "bln", "gp", "none")
#: Models that interpolate the training observations (stored with lights and a basis).
SMOOTHER_MODELS = ("rbf", "bln", "gp")
#: Spaces a model may be fitted in (``meta["space"]``).
FIT_SPACES = ("linear", "srgb")
#: Terms per channel of the fixed linear bases.
BASIS_TERMS = {"ptm": 6, "hsh2": 4, "hsh3": 9}
#: The ps model's default terms (see the module docstring).
PS_TERMS: tuple[str, ...] = ("lx", "ly", "lz", "ambient", "lobe:4", "lobe:32")

_VIEW = np.array([0.0, 0.0, 1.0])
#: ps terms that model light arriving directly (multiplied by the visibility).
DIRECT_KINDS = ("lambert", "lx", "ly", "lz", "lobe", "lobex", "lobey")
#: Numbers per pixel of the ps model's visibility.
VISIBILITY_TERMS = 4
#: Largest magnitude of a stored coefficient or model array (the solver's units are of order 1;
#: beyond this a picture would overflow float32).
MAX_STORED = 1e12
#: Largest exponent of a ps lobe term read from a file (a lobe narrower than 0.1° is a spike).
MAX_LOBE_POWER = 1e6
#: rbf widths read from a file (unit directions are at most 2 apart; the fit picks in
#: [0.03, 1]): narrower would divide by an underflowing σ², wider is a constant.
RBF_SIGMA_RANGE = (1e-3, 1e3)


@dataclass(frozen=True)
class Appearance:
    """One appearance model fitted per pixel.

    Attributes
    ----------
    model : str
        One of :data:`APPEARANCE_MODELS`.
    coefficients : ndarray of shape (H, W, C, K), float32
        ``C`` = 3 colour channels, or 1; ``K`` terms per channel (0 for ``none``).
    meta : dict
        JSON-safe: ``basis`` (the model), ``K``, ``terms`` (names), and for ``rbf`` ``sigma``.
    extra : dict of str to ndarray
        Model data shared by all pixels (``rbf``: ``lights`` (n, 3), ``basis`` (C, n, K)).

    """

    model: str
    coefficients: np.ndarray
    meta: dict[str, Any]
    extra: dict[str, np.ndarray] = field(default_factory=dict)


def coefficients_per_pixel(appearance: Appearance) -> int:
    """Stored numbers per pixel: ``C * K`` plus the visibility's 4 (the normal and albedo of
    ``ps`` are not counted)."""
    count = int(appearance.coefficients.shape[2] * appearance.coefficients.shape[3])
    return count + (VISIBILITY_TERMS if "visibility" in appearance.extra else 0)


def is_direct(term: str) -> bool:
    """Whether a ps term models direct light (multiplied by the visibility)."""
    return term.partition(":")[0] in DIRECT_KINDS


def ps_visibility(directions: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The ps model's visibility ``clamp(w·[l, 1], 0, 1)``.

    Parameters
    ----------
    directions : ndarray of shape (m, 3) or (m, P, 3)
        Unit light directions (per pixel for near lights).
    weights : ndarray of shape (P, 4)
        Per pixel ``(w_x, w_y, w_z, w_1)``.

    Returns
    -------
    ndarray of shape (m, P), float64

    """
    d = _unit(directions)
    w = np.asarray(weights, np.float64)
    if d.ndim == 2:
        value = d @ w[:, :3].T
    else:
        value = np.einsum("mpk,pk->mp", d, w[:, :3])
    return np.clip(value + w[:, 3], 0.0, 1.0)


# ---------------------------------------------------------------------------------------------
# Bases


def _unit(directions: np.ndarray) -> np.ndarray:
    d = np.asarray(directions, dtype=np.float64)
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    return d / np.where(norm > 0, norm, 1.0)


def ptm_basis(directions: np.ndarray) -> np.ndarray:
    """PTM's six terms ``[1, lx, ly, lx², lx·ly, ly²]``.

    Parameters
    ----------
    directions : ndarray of shape (..., 3)
        Unit light directions.

    Returns
    -------
    ndarray of shape (..., 6), float64

    """
    d = _unit(directions)
    x, y = d[..., 0], d[..., 1]
    return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=-1)


def hsh_basis(directions: np.ndarray, order: int = 3) -> np.ndarray:
    """Hemispherical harmonics (Gautron et al. 2004) as RTIBuilder/RelightLab define them.

    Parameters
    ----------
    directions : ndarray of shape (..., 3)
        Unit light directions; those below the horizon are evaluated at the horizon.
    order : {2, 3}
        Order 2: 4 terms; order 3: 9 terms (module docstring).

    Returns
    -------
    ndarray of shape (..., order²), float64

    """
    if order not in (2, 3):
        raise ValueError(f"HSH order must be 2 or 3, not {order}")
    d = _unit(directions)
    c = np.clip(d[..., 2], 0.0, 1.0)
    phi = np.arctan2(d[..., 1], d[..., 0])
    s = np.sqrt(np.maximum(c - c * c, 0.0))
    cp, sp = np.cos(phi), np.sin(phi)
    terms = [
        np.full_like(c, 1.0 / math.sqrt(2 * math.pi)),
        math.sqrt(6 / math.pi) * cp * s,
        math.sqrt(3 / (2 * math.pi)) * (2 * c - 1),
        math.sqrt(6 / math.pi) * sp * s,
    ]
    if order == 3:
        k = math.sqrt(30 / math.pi)
        terms += [
            k * np.cos(2 * phi) * (c * c - c),
            k * cp * (2 * c - 1) * s,
            math.sqrt(5 / (2 * math.pi)) * (6 * c * c - 6 * c + 1),
            k * sp * (2 * c - 1) * s,
            k * np.sin(2 * phi) * (c * c - c),
        ]
    return np.stack(terms, axis=-1)


def appearance_basis(model: str, directions: np.ndarray) -> np.ndarray:
    """The basis of a linear RTI model (``ptm``, ``hsh2``, ``hsh3``).

    Parameters
    ----------
    model : {"ptm", "hsh2", "hsh3"}
    directions : ndarray of shape (m, 3) (or (..., 3))
        Unit light directions in the dataset frame.

    Returns
    -------
    ndarray of shape (m, K) (or (..., K)), float64

    """
    if model == "ptm":
        return ptm_basis(directions)
    if model == "hsh2":
        return hsh_basis(directions, 2)
    if model == "hsh3":
        return hsh_basis(directions, 3)
    raise ValueError(f"{model!r} has no light-only basis (one of ptm, hsh2, hsh3)")


def ps_term(term: str, directions: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """One term ``b_k(l, n)`` of the ps model (vocabulary in the module docstring).

    Parameters
    ----------
    term : str
    directions : ndarray of shape (..., 3)
        Unit light directions, broadcastable against ``normals``.
    normals : ndarray of shape (..., 3)
        Unit normals.

    Returns
    -------
    ndarray of the broadcast shape without the last axis, float64

    """
    d, n = np.broadcast_arrays(np.asarray(directions, np.float64), np.asarray(normals, np.float64))
    half = _unit(d + _VIEW)
    shade = np.einsum("...k,...k->...", d, n)
    nh = np.einsum("...k,...k->...", half, n)
    return _term(term, d, half, shade, nh)


def _term(term: str, d, half, shade, nh) -> np.ndarray:
    """One term from the light ``d``, half vector ``half`` (broadcastable to ``shade``'s shape
    plus 3), ``shade = n·l`` and ``nh = n·h``."""
    lit = shade > 0
    if term == "lambert":
        return np.maximum(shade, 0.0)
    if term == "ambient":
        return np.ones_like(shade)
    if term in ("lx", "ly", "lz"):
        return d[..., "xyz".index(term[1])] * lit
    if term.startswith("lobe"):
        kind, _, power_text = term.partition(":")
        power = float(power_text)
        base = np.maximum(nh, 0.0)
        if kind == "lobe":
            return base**power * lit
        if kind in ("lobex", "lobey"):
            return base ** (power - 1) * half[..., "xy".index(kind[-1])] * lit
    if term.startswith("hsh:"):
        index = int(term[4:])
        if 0 <= index < 9:
            return np.broadcast_to(hsh_basis(d, 3)[..., index], shade.shape).copy()
    raise ValueError(f"unknown ps term {term!r}")


def ps_basis(
    directions: np.ndarray, normals: np.ndarray, terms: tuple[str, ...] | list[str] = PS_TERMS
) -> np.ndarray:
    """The ps model's terms at every light and pixel.

    Parameters
    ----------
    directions : ndarray of shape (m, 3) or (m, P, 3)
        Unit light directions (per pixel for near lights).
    normals : ndarray of shape (P, 3)
        Unit normals.
    terms : sequence of str
        Term names (module docstring).

    Returns
    -------
    ndarray of shape (m, P, K), float64

    """
    d = _unit(directions)
    n = np.asarray(normals, np.float64)
    half = _unit(d + _VIEW)
    if d.ndim == 2:
        shade = d @ n.T  # (m, P)
        nh = half @ n.T
        d, half = d[:, None, :], half[:, None, :]
    else:
        shade = np.einsum("mpk,pk->mp", d, n)
        nh = np.einsum("mpk,pk->mp", half, n)
    # Terms first in memory (each term one contiguous (m, P) plane), viewed as (m, P, K).
    out = np.empty((len(terms), *shade.shape))
    for k, term in enumerate(terms):
        out[k] = _term(term, d, half, shade, nh)
    return np.moveaxis(out, 0, -1)


#: RelightLab's normalised Gaussian weights over the training lights (the ``rbf`` model):
#: :func:`ps_lab.appearance.smoothers.gaussian_weights`, the one definition.
rbf_weights = gaussian_weights


def smoother_weights(appearance: Appearance, directions: np.ndarray) -> np.ndarray:
    """Weights (..., n) over the training lights of an ``rbf``, ``bln`` or ``gp`` model."""
    lights = appearance.extra["lights"]
    sigma = float(appearance.meta["sigma"])
    if appearance.model == "bln":
        return bln_weights(directions, lights, sigma, int(appearance.meta["resolution"]))
    if appearance.model == "gp":
        return gp_weights(directions, lights, sigma, appearance.extra["solve"])
    return rbf_weights(directions, lights, sigma)


# ---------------------------------------------------------------------------------------------
# Evaluation


def lambertian(light: np.ndarray, normals: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """``ρ_c · max(n·l, 0)`` as an (H, W, C) picture.

    Parameters
    ----------
    light : ndarray of shape (3,) or (H, W, 3)
    normals : ndarray of shape (H, W, 3)
        Non-finite normals (outside the mask) give 0.
    albedo : ndarray of shape (H, W), (H, W, 1) or (H, W, C)

    Returns
    -------
    ndarray of shape (H, W, C), float32

    """
    n = np.nan_to_num(np.asarray(normals, np.float64))
    shade = np.maximum(np.einsum("...k,...k->...", _unit(light) * np.ones_like(n), n), 0.0)
    rho = _albedo3(albedo)
    return (np.nan_to_num(rho) * shade[..., None]).astype(np.float32)


def _albedo3(albedo: np.ndarray) -> np.ndarray:
    a = np.asarray(albedo, np.float64)
    return a[..., None] if a.ndim == 2 else a


def evaluate_appearance(
    appearance: Appearance, light: np.ndarray, normals: np.ndarray, albedo: np.ndarray
) -> np.ndarray:
    """The picture a fitted model predicts under one light.

    Parameters
    ----------
    appearance : Appearance
    light : ndarray of shape (3,) or (H, W, 3)
        Unit light direction, or per-pixel unit directions (near lights).
    normals : ndarray of shape (H, W, 3)
        The result's normals (non-finite outside the mask: 0 there).
    albedo : ndarray of shape (H, W), (H, W, 1) or (H, W, C)
        The result's albedo (used by ``ps`` and ``none``).

    Returns
    -------
    ndarray of shape (H, W, C), float32, linear (the solver's units)

    """
    coeffs = appearance.coefficients.astype(np.float64)
    height, width = coeffs.shape[:2]
    light = np.asarray(light, np.float64)
    per_pixel = light.ndim == 3
    model = appearance.model
    if model in BASIS_TERMS:
        basis = appearance_basis(model, light)  # (K,) or (H, W, K)
        out = np.einsum("hwck,...k->hwc", coeffs, basis) if not per_pixel else np.einsum(
            "hwck,hwk->hwc", coeffs, basis
        )
    elif model in SMOOTHER_MODELS:
        weights = smoother_weights(appearance, light)  # (n,) or (H, W, n)
        rbf_basis = appearance.extra["basis"].astype(np.float64)  # (C, n, K)
        if per_pixel:
            planes = np.einsum("hwn,cnk->hwck", weights, rbf_basis)
            out = np.einsum("hwck,hwck->hwc", coeffs, planes)
        else:
            planes = np.einsum("n,cnk->ck", weights, rbf_basis)
            out = np.einsum("hwck,ck->hwc", coeffs, planes)
    elif model in ("ps", "none"):
        out = lambertian(light, normals, albedo).astype(np.float64)
        d = light.reshape(1, -1, 3) if per_pixel else light.reshape(1, 3)
        vis = appearance.extra.get("visibility") if model == "ps" else None
        if vis is not None:
            v = ps_visibility(d, vis.reshape(-1, VISIBILITY_TERMS))[0].reshape(height, width)
            out = out * v[..., None]
        if model == "ps" and coeffs.shape[3]:
            n = np.nan_to_num(np.asarray(normals, np.float64)).reshape(-1, 3)
            terms = tuple(appearance.meta["terms"])
            basis = ps_basis(d, n, terms)[0]  # (P, K)
            if vis is not None:
                direct = np.array([is_direct(t) for t in terms])
                basis = np.where(direct, basis * v.reshape(-1, 1), basis)
            extra = np.einsum("pck,pk->pc", coeffs.reshape(height * width, -1, coeffs.shape[3]),
                              basis).reshape(height, width, -1)
            out = out + extra
    else:
        raise ValueError(f"unknown appearance model {model!r}")
    if appearance.meta.get("space") == "srgb":
        out = srgb_to_linear(np.clip(out, 0.0, 1.0))
    return out.astype(np.float32)

