"""The one 3x3 symmetric inverse (closed form, by cofactors), scalar and vectorised over pixels.

A symmetric 3x3 matrix is stored as its six unique entries in the order
``(xx, yy, zz, xy, xz, yz)`` so that the per-pixel normal matrices ``sum_i w_i a_i a_i^T`` of a
whole tile are one matrix product ``w @ outer6(A)``. One rule for a singular matrix everywhere:
``det <= rel_eps (trace / 3)^3`` (or ``trace <= 0``), with ``rel_eps`` at least
:data:`SINGULAR_REL_DET`; its inverse is then zeros and ``ok`` False (callers choose what an
unsolvable fit means to them). :func:`inverse3` / :func:`solve3` are the numba scalar forms
(inlined into the kernels), :func:`inverse6` the numpy one. Also the robust per-pixel scale
(:func:`pixel_scale`) that every solver divides by.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# A pixel needs a usable 3x3 normal matrix: det >= this * (trace/3)^3 (conditioning).
SOLVABLE_REL_DET = 1e-6
# Below this a symmetric 3x3 matrix counts as singular: det <= it * (trace/3)^3, a condition number
# of about 1e12, where a solve is mostly rounding.
SINGULAR_REL_DET = 1e-12


@njit(inline="always")
def cofactors3(xx, yy, zz, xy, xz, yz):
    """Determinant and cofactors of a symmetric 3x3: ``(det, c00, c11, c22, c01, c02, c12)``.

    Scalars in the kernels (inlined); ``cofactors3.py_func`` takes arrays (:func:`inverse6`).
    """
    c00 = yy * zz - yz * yz
    c11 = xx * zz - xz * xz
    c22 = xx * yy - xy * xy
    c01 = xz * yz - xy * zz
    c02 = xy * yz - xz * yy
    c12 = xy * xz - xx * yz
    return xx * c00 + xy * c01 + xz * c02, c00, c11, c22, c01, c02, c12


@njit(inline="always")
def inverse3(xx, yy, zz, xy, xz, yz, rel_eps):
    """Inverse of one symmetric 3x3 matrix by cofactors: ``(ok, i00, i11, i22, i01, i02, i12)``.

    Singular (``ok`` False, zeros) when ``det <= max(rel_eps, SINGULAR_REL_DET) (trace/3)^3``.
    """
    det, c00, c11, c22, c01, c02, c12 = cofactors3(xx, yy, zz, xy, xz, yz)
    tr = (xx + yy + zz) / 3.0
    rel = rel_eps if rel_eps > SINGULAR_REL_DET else SINGULAR_REL_DET
    if not (det > rel * tr * tr * tr and tr > 0.0):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    inv = 1.0 / det
    return True, c00 * inv, c11 * inv, c22 * inv, c01 * inv, c02 * inv, c12 * inv


@njit(inline="always")
def solve3(xx, yy, zz, xy, xz, yz, t0, t1, t2):
    """Solve one symmetric 3x3 system (:func:`inverse3`; zeros when it is singular).

    Returns ``(x0, x1, x2, i00, i11, i22, i01, i02, i12)``: the solution and the inverse.
    """
    ok, i00, i11, i22, i01, i02, i12 = inverse3(xx, yy, zz, xy, xz, yz, SINGULAR_REL_DET)
    return (i00 * t0 + i01 * t1 + i02 * t2, i01 * t0 + i11 * t1 + i12 * t2,
            i02 * t0 + i12 * t1 + i22 * t2, i00, i11, i22, i01, i02, i12)


def sym6(m: np.ndarray) -> np.ndarray:
    """Symmetric matrices (P, 3, 3) -> their six unique entries (P, 6)."""
    return m[:, [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]


def full3(m6: np.ndarray) -> np.ndarray:
    """Six unique entries (P, 6) -> the symmetric matrices (P, 3, 3)."""
    return m6[:, [[0, 3, 4], [3, 1, 5], [4, 5, 2]]]


def outer6(lights: np.ndarray) -> np.ndarray:
    """Unique entries of ``a a^T`` per light: (n, 3) -> (n, 6)."""
    x, y, z = lights[:, 0], lights[:, 1], lights[:, 2]
    return np.stack([x * x, y * y, z * z, x * y, x * z, y * z], axis=1)


def inverse6(m: np.ndarray, rel_eps: float = SINGULAR_REL_DET) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of symmetric 3x3 matrices by cofactors (:func:`inverse3`, vectorised).

    Parameters
    ----------
    m : ndarray of shape (P, 6)
        Matrices in ``(xx, yy, zz, xy, xz, yz)`` order.
    rel_eps : float
        A matrix counts as singular when ``det <= rel_eps * (trace / 3) ** 3`` (``rel_eps`` at
        least :data:`SINGULAR_REL_DET`).

    Returns
    -------
    inv : ndarray of shape (P, 6)
        Inverses (zeros for singular matrices).
    ok : ndarray of shape (P,), bool
        False for singular matrices.
    """
    xx, yy, zz, xy, xz, yz = (m[:, k] for k in range(6))
    det, c00, c11, c22, c01, c02, c12 = cofactors3.py_func(xx, yy, zz, xy, xz, yz)
    scale = (xx + yy + zz) / 3.0
    rel_eps = max(rel_eps, SINGULAR_REL_DET)
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
