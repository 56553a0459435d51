"""Colour albedo: one normal map, a Lambertian-equivalent reflectance per colour channel.

The normals are solved on one channel (``--channel``); the three channels of every frame are
staged beside it (:class:`ps_lab.io.bands.ObservationStore` with ``colours=3``), each divided by
the light's intensity for that channel, and after the normals of a band are known each channel's
albedo is the least-squares scale of the Lambertian shading over the observations the solver kept
(:func:`colour_albedo`). The result's ``albedo.npy`` is then (H, W, 3) linear RGB; ``albedo.png``
is its sRGB picture (:func:`colour_albedo_picture`) and ``albedo.exr`` the float values.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
from numba import njit

from ps_lab.io.encoding import linear_to_srgb
from ps_lab.io.normal_maps import write_rgb_exr

# Pixels per block of the kernel (its float64 accumulators and shading rows stay in the L2 cache):
# directional lights, and near lights (whose (P, n, 3) vectors a block re-reads per light group).
COLOUR_BLOCK = 2048
NEAR_COLOUR_BLOCK = 512
# Lights added per pass over a block's accumulators (the kernel's sums are written out for 4).
_GROUP = 4
# Helpers inlined into the kernels (as in _kernels.py).
INLINE = {"inline": "always"}
# Image rows per block of colour_albedo_picture's work arrays.
PICTURE_ROWS = 256
# sRGB table buckets: float32 bit patterns shifted right by this (see _srgb_table).
_SRGB_SHIFT = 12

__all__ = [
    "colour_albedo",
    "colour_albedo_picture",
    "grey_albedo",
    "write_albedo_exr",
]


def colour_albedo(
    normals: np.ndarray,
    inliers: np.ndarray,
    observations: np.ndarray,
    lights: np.ndarray,
    intensities: np.ndarray | None = None,
) -> np.ndarray:
    """Per-channel Lambertian-equivalent albedo of pixels whose normals are known.

    For pixel p and channel c, with shading ``s_c,i = e_c,i · max(n_p · l_i, 0)`` over the
    inlier observations ``i`` of the pixel::

        albedo_c = Σ_i y_c,i · s_c,i / Σ_i s_c,i²

    the least-squares scale of the Lambertian model ``y = albedo · s`` on the observations the
    solver kept (attached shadows, ``s = 0``, add nothing to either sum). Pure and exact: with
    noise-free Lambertian data it returns the rendered albedo.

    One pass of a compiled kernel (:func:`_far_kernel`, :func:`_near_kernel`) over the
    observations as they are (float32 stays float32; each value is widened to float64 as it is
    read): the sums are float64 and add the lights in order, as ``numpy``'s sums over the lights
    did; the shading ``n · l`` is the plain three-term float64 sum (BLAS and ``einsum`` may fuse
    a multiply-add, a difference within float64 rounding).

    Parameters
    ----------
    normals : ndarray of shape (P, 3)
        Unit normals (zeros where unsolved).
    inliers : ndarray of shape (n, P), bool
        Observations the solver used (valid, not outliers, not shadows).
    observations : ndarray of shape (n, P, C)
        The colour observations (non-finite ones are skipped).
    lights : ndarray of shape (n, 3) or (n, P, 3)
        Light vectors: directions, or directions times relative intensities (the solver's
        vectors); per pixel for near lights.
    intensities : ndarray of shape (n, C) or None
        Each light's intensity per channel (None: ones, the observations are already divided).

    Returns
    -------
    ndarray of shape (P, C), float32
        Zero where a pixel has no inlier with positive shading.

    """
    observations = np.asarray(observations)
    if observations.dtype not in (np.float32, np.float64):
        observations = observations.astype(np.float64)
    n, p, c = observations.shape
    albedo = np.zeros((p, c), np.float32)
    if n == 0 or p == 0 or c == 0:
        return albedo
    values = np.ascontiguousarray(observations).reshape(n, p * c)
    unit = np.ascontiguousarray(normals, np.float64)
    used = np.ascontiguousarray(inliers, np.bool_)
    scale = np.ones((n, c)) if intensities is None else np.ascontiguousarray(
        np.asarray(intensities, np.float64).reshape(n, c)
    )
    lights = np.asarray(lights, np.float64)
    out = albedo.reshape(-1)
    if lights.ndim == 2:
        _far_kernel(unit, used, values, np.ascontiguousarray(lights), scale, out, COLOUR_BLOCK)
    else:  # (n, P, 3), usually a view of the solver's (P, n, 3): the kernel reads that one
        per_pixel = np.ascontiguousarray(lights.transpose(1, 0, 2))
        _near_kernel(unit, used, values, per_pixel, scale, out, NEAR_COLOUR_BLOCK)
    return albedo


@njit(**INLINE)
def _load_normals(normals, a, m, nb):
    """``nb[k, q] = normals[a + q, k]`` for the block's m pixels (components as rows)."""
    for q in range(m):
        nb[0, q] = normals[a + q, 0]
        nb[1, q] = normals[a + q, 1]
        nb[2, q] = normals[a + q, 2]


@njit(**INLINE)
def _spread(t, q, s, inlier, scale, i, c):
    """Shading row ``t[q * c + ch] = s · e_i,ch`` of pixel q, 0 off the inliers."""
    if s <= 0.0:
        s = 0.0
    for ch in range(c):
        t[q * c + ch] = s * scale[i, ch] if inlier else 0.0


@njit(**INLINE)
def _shade_far(nb, use, l0, l1, l2, scale, i, c, t, m, rgb):
    """Row ``t`` (m c) of light i: ``max(n · l_i, 0) · e_i,c`` on its inliers ``use``, else 0.

    ``rgb``: c is 3 and the intensities are finite (0 · e is then 0, so the shading can be
    zeroed before it is scaled): the three stores are written out and the loop compiles to
    vector shuffles.
    """
    if rgb:
        e0, e1, e2 = scale[i, 0], scale[i, 1], scale[i, 2]
        for q in range(m):
            s = l0 * nb[0, q] + l1 * nb[1, q] + l2 * nb[2, q]
            if s <= 0.0:
                s = 0.0
            if not use[q]:
                s = 0.0
            t[3 * q] = s * e0
            t[3 * q + 1] = s * e1
            t[3 * q + 2] = s * e2
    else:
        for q in range(m):
            _spread(t, q, l0 * nb[0, q] + l1 * nb[1, q] + l2 * nb[2, q], use[q], scale, i, c)


@njit(**INLINE)
def _shade_near(nb, use, vectors, a, scale, i, c, t, m, rgb):
    """As :func:`_shade_far` with the pixels' own vectors ``vectors[a + q, i]`` (P, n, 3)."""
    if rgb:
        e0, e1, e2 = scale[i, 0], scale[i, 1], scale[i, 2]
        for q in range(m):
            s = (vectors[a + q, i, 0] * nb[0, q] + vectors[a + q, i, 1] * nb[1, q]
                 + vectors[a + q, i, 2] * nb[2, q])
            if s <= 0.0:
                s = 0.0
            if not use[q]:
                s = 0.0
            t[3 * q] = s * e0
            t[3 * q + 1] = s * e1
            t[3 * q + 2] = s * e2
    else:
        for q in range(m):
            s = (vectors[a + q, i, 0] * nb[0, q] + vectors[a + q, i, 1] * nb[1, q]
                 + vectors[a + q, i, 2] * nb[2, q])
            _spread(t, q, s, use[q], scale, i, c)


@njit(**INLINE)
def _term(y, t, num, den):
    """Add one observation: ``y t`` and ``t²``, nothing (zeros) when ``y`` is not finite."""
    finite = abs(y) < np.inf
    t = t if finite else 0.0
    y = y if finite else 0.0
    return num + y * t, den + t * t


@njit(**INLINE)
def _add_group(r0, r1, r2, r3, t, num, den, width):
    """Add lights i..i+3 (observation rows r0-r3, shading rows t[0-3]) in order."""
    for j in range(width):
        sn, sd = num[j], den[j]
        sn, sd = _term(np.float64(r0[j]), t[0, j], sn, sd)
        sn, sd = _term(np.float64(r1[j]), t[1, j], sn, sd)
        sn, sd = _term(np.float64(r2[j]), t[2, j], sn, sd)
        sn, sd = _term(np.float64(r3[j]), t[3, j], sn, sd)
        num[j], den[j] = sn, sd


@njit(**INLINE)
def _add_one(r0, t, num, den, width):
    """Add one light (observation row r0, shading row t[0])."""
    for j in range(width):
        num[j], den[j] = _term(np.float64(r0[j]), t[0, j], num[j], den[j])


@njit(**INLINE)
def _ratio(num, den, out, start, width):
    """``out[start + j] = num / den`` where ``den > 0``, else 0 (float32)."""
    for j in range(width):
        d = den[j]
        out[start + j] = num[j] / d if d > 0.0 else 0.0


@njit(nogil=True, cache=True, error_model="numpy")
def _far_kernel(normals, inliers, values, lights, scale, out, block):
    """Colour albedo with one light vector per light (see :func:`colour_albedo`).

    Parameters
    ----------
    normals : (P, 3) float64;  inliers : (n, P) bool;  values : (n, P C) float32 or float64,
    the observations with each pixel's C channels side by side;  lights : (n, 3) float64;
    scale : (n, C) float64, the intensities;  out : (P C,) float32, written;  block : pixels
    per block.
    """
    n, p = inliers.shape
    c = scale.shape[1]
    rgb = c == 3 and np.all(np.abs(scale) < np.inf)
    nb = np.empty((3, block))
    t = np.empty((_GROUP, block * c))
    num = np.empty(block * c)
    den = np.empty(block * c)
    for a in range(0, p, block):
        m = min(block, p - a)
        lo, width = a * c, m * c
        _load_normals(normals, a, m, nb)
        num[:width] = 0.0
        den[:width] = 0.0
        i = 0
        while i + _GROUP <= n:
            for k in range(_GROUP):
                _shade_far(nb, inliers[i + k, a:a + m], lights[i + k, 0], lights[i + k, 1],
                           lights[i + k, 2], scale, i + k, c, t[k], m, rgb)
            _add_group(values[i, lo:lo + width], values[i + 1, lo:lo + width],
                       values[i + 2, lo:lo + width], values[i + 3, lo:lo + width], t, num, den,
                       width)
            i += _GROUP
        while i < n:
            _shade_far(nb, inliers[i, a:a + m], lights[i, 0], lights[i, 1], lights[i, 2], scale,
                       i, c, t[0], m, rgb)
            _add_one(values[i, lo:lo + width], t, num, den, width)
            i += 1
        _ratio(num, den, out, lo, width)


@njit(nogil=True, cache=True, error_model="numpy")
def _near_kernel(normals, inliers, values, vectors, scale, out, block):
    """:func:`_far_kernel` with per-pixel light vectors ``vectors`` (P, n, 3) float64."""
    n, p = inliers.shape
    c = scale.shape[1]
    rgb = c == 3 and np.all(np.abs(scale) < np.inf)
    nb = np.empty((3, block))
    t = np.empty((_GROUP, block * c))
    num = np.empty(block * c)
    den = np.empty(block * c)
    for a in range(0, p, block):
        m = min(block, p - a)
        lo, width = a * c, m * c
        _load_normals(normals, a, m, nb)
        num[:width] = 0.0
        den[:width] = 0.0
        i = 0
        while i + _GROUP <= n:
            for k in range(_GROUP):
                _shade_near(nb, inliers[i + k, a:a + m], vectors, a, scale, i + k, c, t[k], m,
                            rgb)
            _add_group(values[i, lo:lo + width], values[i + 1, lo:lo + width],
                       values[i + 2, lo:lo + width], values[i + 3, lo:lo + width], t, num, den,
                       width)
            i += _GROUP
        while i < n:
            _shade_near(nb, inliers[i, a:a + m], vectors, a, scale, i, c, t[0], m, rgb)
            _add_one(values[i, lo:lo + width], t, num, den, width)
            i += 1
        _ratio(num, den, out, lo, width)


def grey_albedo(albedo: np.ndarray, channel: str) -> np.ndarray:
    """The solve channel's albedo (H, W) from a colour one (H, W, 3); a grey one as it is.

    The colour albedo is linear in the observations, so the ``mean`` channel's albedo is the
    mean of the three.
    """
    albedo = np.asarray(albedo)
    if albedo.ndim == 2:
        return albedo
    if albedo.shape[-1] == 1:
        return albedo[..., 0]
    pick = {"r": 0, "g": 1, "b": 2}
    return albedo.mean(axis=-1) if channel not in pick else albedo[..., pick[channel]]


def colour_albedo_picture(
    albedo: np.ndarray, mask: np.ndarray, top: float | None = None
) -> np.ndarray:
    """An 8-bit sRGB picture of a linear colour albedo (H, W, 3).

    One scale for the three channels (so the hue is kept): ``top`` (default the 99th percentile
    of the brightest channel inside the mask) maps to 1, then the sRGB transfer curve
    (:func:`srgb_codes`, NaN black). The codes come from a table (:func:`_srgb_table`) that
    gives each float32 value the code of :func:`srgb_codes`.

    Returns
    -------
    ndarray of shape (H, W, 3), uint8, RGB; black outside the mask

    """
    albedo = np.asarray(albedo, np.float32)
    if top is None:
        inside = albedo[mask].max(axis=-1) if mask.any() else np.zeros(0)
        top = float(np.percentile(inside, 99)) if inside.size else 0.0
    picture = np.zeros((*mask.shape, 3), np.uint8)
    if not np.isfinite(top) or top <= 0:
        return picture
    codes, thresholds = _srgb_table()
    for start in range(0, mask.shape[0], PICTURE_ROWS):  # bounded work arrays on large images
        rows = slice(start, start + PICTURE_ROWS)
        with np.errstate(over="ignore", invalid="ignore"):
            scaled = albedo[rows] / top  # float32 for a Python float top, as before
        if scaled.dtype == np.float32:  # a division's NaN is quiet: never in the inf bucket
            bucket = scaled.view(np.uint32) >> _SRGB_SHIFT
            block = codes.take(bucket)
            block += scaled >= thresholds.take(bucket)
        else:  # a numpy float64 top: float64 values, the curve itself
            block = srgb_codes(np.where(np.isnan(scaled), 0.0, scaled))
        block[~mask[rows]] = 0
        picture[rows] = block
    return picture


def srgb_codes(scaled: np.ndarray) -> np.ndarray:
    """8-bit sRGB codes of linear values scaled so that 1 is white (clipped to 0..255).

    ``rint(255 · linear_to_srgb(v))``, the float64 curve of :func:`ps_lab.io.encoding
    .linear_to_srgb` (NaN gives an undefined code: callers zero it first).

    Returns
    -------
    ndarray of the shape of ``scaled``, uint8

    """
    with np.errstate(invalid="ignore"):
        return np.clip(np.rint(linear_to_srgb(scaled) * 255.0), 0, 255).astype(np.uint8)


@functools.cache
def _srgb_table() -> tuple[np.ndarray, np.ndarray]:
    """:func:`srgb_codes` of every float32 value, as a table over its bit pattern.

    The code is a non-decreasing function of a float32 value ``v`` (the float64 curve's
    rounding errors, ~1e-16, are far below the 6e-8 relative gap between neighbouring float32
    values). Its 255 steps, the smallest float32 values with code k = 1..255, are found by
    bisection over the bit patterns of [0, 1] with :func:`srgb_codes` itself. The table has one
    entry per bucket of 2^12 consecutive bit patterns (relative width 2^-11, finer than the
    steps, so a bucket holds at most one): its code at the bucket's start and the step inside
    it (NaN: none). ``code(v) = codes[b] + (v >= thresholds[b])`` with ``b = bits(v) >> 12``.
    Negative values, -inf and NaN give 0, +inf 255 (its bucket also holds signalling NaNs,
    which no division returns).

    Returns
    -------
    codes : ndarray of shape (2^20,), uint8
    thresholds : ndarray of shape (2^20,), float32

    """
    level = np.arange(1, 256)
    below = np.zeros(255, np.int64)  # bit patterns with code < k ...
    above = np.full(255, int(np.float32(1.0).view(np.int32)), np.int64)  # ... and >= k
    while np.any(above - below > 1):
        middle = (below + above) // 2
        up = srgb_codes(middle.astype(np.int32).view(np.float32)) >= level
        above = np.where(up, middle, above)
        below = np.where(up, below, middle)
    steps = above.astype(np.int32).view(np.float32)
    if np.unique(steps.view(np.uint32) >> _SRGB_SHIFT).size != steps.size:
        raise AssertionError("two sRGB steps in one table bucket")  # not with 2^12 patterns
    first = np.arange(1 << (32 - _SRGB_SHIFT), dtype=np.uint32) << _SRGB_SHIFT
    last = (first | np.uint32((1 << _SRGB_SHIFT) - 1)).view(np.float32)
    first = first.view(np.float32)
    codes = np.searchsorted(steps, first, side="right")
    codes[np.isnan(first)] = 0
    following = np.append(steps, np.float32(np.nan))[codes]
    with np.errstate(invalid="ignore"):
        thresholds = np.where(following <= last, following, np.float32(np.nan))
    return codes.astype(np.uint8), thresholds.astype(np.float32)


def write_albedo_exr(path: Path, albedo: np.ndarray) -> None:
    """Write a linear colour albedo (H, W, 3) as OpenEXR float channels R, G, B."""
    write_rgb_exr(path, albedo)
