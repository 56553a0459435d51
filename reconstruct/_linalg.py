"""Closed-form 3x3 symmetric algebra, vectorised over pixels.

A symmetric 3x3 matrix is stored as its six unique entries in the order
``(xx, yy, zz, xy, xz, yz)`` so that the per-pixel normal matrices ``sum_i w_i a_i a_i^T`` of a
whole tile are one matrix product ``w @ outer6(A)``. Also the robust per-pixel scale
(:func:`pixel_scale`) that every solver divides by.
"""

from __future__ import annotations

import numpy as np

# A pixel needs a usable 3x3 normal matrix: det >= this * (trace/3)^3 (conditioning).
SOLVABLE_REL_DET = 1e-6


def outer6(lights: np.ndarray) -> np.ndarray:
    """Unique entries of ``a a^T`` per light: (n, 3) -> (n, 6)."""
    x, y, z = lights[:, 0], lights[:, 1], lights[:, 2]
    return np.stack([x * x, y * y, z * z, x * y, x * z, y * z], axis=1)


def inverse6(m: np.ndarray, rel_eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of symmetric 3x3 matrices by cofactors.

    Parameters
    ----------
    m : ndarray of shape (P, 6)
        Matrices in ``(xx, yy, zz, xy, xz, yz)`` order.
    rel_eps : float
        A matrix counts as singular when ``det <= rel_eps * (trace / 3) ** 3``.

    Returns
    -------
    inv : ndarray of shape (P, 6)
        Inverses (zeros for singular matrices).
    ok : ndarray of shape (P,), bool
        False for singular matrices.
    """
    xx, yy, zz, xy, xz, yz = (m[:, k] for k in range(6))
    c00 = yy * zz - yz * yz
    c11 = xx * zz - xz * xz
    c22 = xx * yy - xy * xy
    c01 = xz * yz - xy * zz
    c02 = xy * yz - xz * yy
    c12 = xy * xz - xx * yz
    det = xx * c00 + xy * c01 + xz * c02
    scale = (xx + yy + zz) / 3.0
    ok = (det > rel_eps * scale * scale * scale) & (scale > 0)
    inv_det = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0).astype(m.dtype, copy=False)
    inv = np.stack([c00, c11, c22, c01, c02, c12], axis=1)
    inv *= inv_det[:, None]
    return inv, ok


def apply6(inv: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Product of symmetric matrices (P, 6) with vectors (P, 3)."""
    i00, i11, i22, i01, i02, i12 = (inv[:, k] for k in range(6))
    t0, t1, t2 = t[:, 0], t[:, 1], t[:, 2]
    return np.stack(
        [
            i00 * t0 + i01 * t1 + i02 * t2,
            i01 * t0 + i11 * t1 + i12 * t2,
            i02 * t0 + i12 * t1 + i22 * t2,
        ],
        axis=1,
    )


def pixel_scale(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Robust scale of each pixel: the median of its usable observations' magnitudes.

    Parameters
    ----------
    y : ndarray of shape (m, n)
    w : ndarray of shape (m, n), bool

    Returns
    -------
    ndarray of shape (m,), float64
        The median of ``|y|`` over usable observations; when that is zero (a pixel dark under most
        lights), the mean of ``|y|``; zero when the pixel has no usable non-zero observation.
    """
    a = np.abs(y).astype(np.float64, copy=False)  # a new array: sorted in place below
    a[~w] = np.inf
    a.sort(axis=1)
    k = w.sum(axis=1)
    lo = np.clip((k - 1) // 2, 0, None)
    hi = np.clip(k // 2, 0, None)
    rows = np.arange(y.shape[0])
    last = a.shape[1] - 1
    mid = 0.5 * (a[rows, np.minimum(lo, last)] + a[rows, np.minimum(hi, last)])
    scale = np.where(k > 0, mid, 0.0)
    dark = ~(scale > 0)  # the mean instead, over the same sorted rows
    if dark.any():
        a = a[dark]
        a[~np.isfinite(a)] = 0.0
        scale[dark] = a.sum(axis=1) / np.maximum(k[dark], 1)
    return scale
