"""Small dense linear algebra of the per-pixel kernels, inlined into them, and its vectorised forms.

The one 3x3 symmetric inverse (closed form, by cofactors), scalar and vectorised over pixels.
A symmetric 3x3 matrix is stored as its six unique entries in the order
``(xx, yy, zz, xy, xz, yz)`` so that the per-pixel normal matrices ``sum_i w_i a_i a_i^T`` of a
whole tile are one matrix product ``w @ outer6(A)``. One rule for a singular matrix everywhere:
``det <= rel_eps (trace / 3)^3`` (or ``trace <= 0``), with ``rel_eps`` at least
:data:`SINGULAR_REL_DET`; its inverse is then zeros and ``ok`` False (callers choose what an
unsolvable fit means to them). :func:`inverse3` / :func:`solve3` are the numba scalar forms
(inlined into the kernels; :func:`weighted_sums3` forms their normal equations from a light
table), :func:`inverse6` the numpy one. For the piecewise-linear kernel: the 5x5 symmetric
inverse by blocks (:func:`inverse5`), the Cholesky inverse of a small symmetric positive
definite matrix (:func:`cholesky_inverse`) and a selection (:func:`select_kth`, an order
statistic without a sort). Also the robust per-pixel scale (:func:`pixel_scale`) that every
solver divides by.
"""

from __future__ import annotations

import math

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


@njit(inline="always")
def weighted_sums3(v, y, tab, n):
    """Normal equations of a weighted 3-unknown fit: ``sum_i v_i a_i a_i^T`` (6) and
    ``sum_i v_i y_i a_i`` (3), ``(xx, yy, zz, xy, xz, yz, t0, t1, t2)``.

    ``v``, ``y`` (n,) the weights and targets; ``tab`` (9, n) the light table of the kernels:
    ``a_i a_i^T`` on rows 0-5 (as :func:`outer6`), ``a_i`` on rows 6-8.
    """
    xx = yy = zz = xy = xz = yz = 0.0
    t0 = t1 = t2 = 0.0
    for i in range(n):
        vi = v[i]
        xx += vi * tab[0, i]
        yy += vi * tab[1, i]
        zz += vi * tab[2, i]
        xy += vi * tab[3, i]
        xz += vi * tab[4, i]
        yz += vi * tab[5, i]
        vy = vi * y[i]
        t0 += vy * tab[6, i]
        t1 += vy * tab[7, i]
        t2 += vy * tab[8, i]
    return xx, yy, zz, xy, xz, yz, t0, t1, t2


@njit(inline="always")
def inverse5(m00, m01, m02, m03, m04, m11, m12, m13, m14, m22, m23, m24, m33, m34, m44):
    """``M^-1`` of a symmetric 5x5 ``M`` (upper triangle given) and ``det M``, in scalars.

    The three-segment iteration's (slopes 0-1, normal 2-4) by blocks: ``N`` (rows 2-4) by
    cofactors, then the slopes' 2x2 Schur complement ``S = M_ss - C N^-1 C^T``; ``M^-1`` is
    ``S^-1`` on the slopes, ``-S^-1 C N^-1`` beside and ``N^-1 + (N^-1 C^T) S^-1 (C N^-1)``
    on the normal. ``M`` is positive definite exactly where ``N`` and ``S`` are (what
    :func:`cholesky_inverse` tests by its pivots); else NaN (and zeros). Two divisions, no
    square root and no log (the caller takes ``log det`` once): held in registers, 17 ns a call
    against the generic Cholesky's 131 ns (both with their log, one thread, Zen 4).

    Returns
    -------
    det : float
        ``det M = det N det S``; NaN where ``M`` is not positive definite.
    inverse : tuple of 15 floats
        The upper triangle of ``M^-1``, row-major.
    """
    z = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    # N's cofactors; N and S must be positive definite (the Cholesky pivots' test), not only
    # invertible (inverse3's rule)
    det_n, c22, c33, c44, c23, c24, c34 = cofactors3(m22, m33, m44, m23, m24, m34)
    if not det_n > 0.0:
        return math.nan, z
    r = 1.0 / det_n
    n22, n33, n44, n23, n24, n34 = c22 * r, c33 * r, c44 * r, c23 * r, c24 * r, c34 * r
    # P = C N^-1 (2x3; C = M[0:2, 2:5])
    p02 = m02 * n22 + m03 * n23 + m04 * n24
    p03 = m02 * n23 + m03 * n33 + m04 * n34
    p04 = m02 * n24 + m03 * n34 + m04 * n44
    p12 = m12 * n22 + m13 * n23 + m14 * n24
    p13 = m12 * n23 + m13 * n33 + m14 * n34
    p14 = m12 * n24 + m13 * n34 + m14 * n44
    s00 = m00 - (p02 * m02 + p03 * m03 + p04 * m04)
    s01 = m01 - (p02 * m12 + p03 * m13 + p04 * m14)
    s11 = m11 - (p12 * m12 + p13 * m13 + p14 * m14)
    det_s = s00 * s11 - s01 * s01
    if not (s00 > 0.0 and det_s > 0.0):
        return math.nan, z
    r = 1.0 / det_s
    i00 = s11 * r
    i11 = s00 * r
    i01 = -s01 * r
    i02 = -(i00 * p02 + i01 * p12)
    i03 = -(i00 * p03 + i01 * p13)
    i04 = -(i00 * p04 + i01 * p14)
    i12 = -(i01 * p02 + i11 * p12)
    i13 = -(i01 * p03 + i11 * p13)
    i14 = -(i01 * p04 + i11 * p14)
    i22 = n22 - (p02 * i02 + p12 * i12)
    i23 = n23 - (p02 * i03 + p12 * i13)
    i24 = n24 - (p02 * i04 + p12 * i14)
    i33 = n33 - (p03 * i03 + p13 * i13)
    i34 = n34 - (p03 * i04 + p13 * i14)
    i44 = n44 - (p04 * i04 + p14 * i14)
    return det_n * det_s, (i00, i01, i02, i03, i04, i11, i12, i13, i14, i22, i23, i24, i33, i34,
                           i44)


@njit(inline="always")
def cholesky_inverse(mat, inv, low, u):
    """``inv = mat^-1`` (u x u, symmetric positive definite) and ``log det mat``; NaN if not."""
    for j in range(u):
        s = mat[j, j]
        for q in range(j):
            s -= low[j, q] * low[j, q]
        if not s > 0.0:
            return math.nan
        low[j, j] = math.sqrt(s)
        for r in range(j + 1, u):
            s = mat[r, j]
            for q in range(j):
                s -= low[r, q] * low[j, q]
            low[r, j] = s / low[j, j]
    logdet = 0.0
    for j in range(u):
        logdet += 2.0 * math.log(low[j, j])
    # inverse of the lower factor (in place of its upper part: use inv as scratch), then L^-T L^-1
    for c in range(u):
        for r in range(u):
            s = 1.0 if r == c else 0.0
            for q in range(r):
                s -= low[r, q] * inv[q, c]
            inv[r, c] = s / low[r, r] if r >= c else 0.0
    for r in range(u):
        for c in range(r, u):
            s = 0.0
            for q in range(c, u):
                s += inv[q, r] * inv[q, c]
            low[r, c] = s
    for r in range(u):
        for c in range(r, u):
            inv[r, c] = low[r, c]
            inv[c, r] = low[r, c]
    return logdet


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


@njit(inline="always")
def select_kth(a, lo, hi, kth):
    """The value of rank ``kth`` of ``a[lo:hi]`` (a selection, in place, O(n) expected).

    Afterwards ``a[lo:kth] <= a[kth] <= a[kth + 1:hi]``, so a larger rank can be selected in
    ``a[kth:hi]``. The pivot is the median of three (deterministic); the value equals a sort's.
    Each partition is Lomuto's without a branch on the data (a swap and a count per element:
    a mispredicted branch per element cost more than the rest of the selection), in two passes:
    the values below the pivot, then, if the rank lies right of them, those equal to it (ties:
    8-bit data).
    """
    while hi - lo > 2:
        mid = (lo + hi) // 2
        p0, p1, p2 = a[lo], a[mid], a[hi - 1]
        small = p0 if p0 < p1 else p1
        large = p1 if p0 < p1 else p0
        large = large if large < p2 else p2
        pivot = small if small > large else large  # the median of the three
        # a[lo:store] < pivot <= a[store:i]
        store = lo
        for i in range(lo, hi):
            t = a[i]
            a[i] = a[store]
            a[store] = t
            store += t < pivot
        if kth < store:
            hi = store
            continue
        # a[store:equal] == pivot < a[equal:i]
        equal = store
        for i in range(store, hi):
            t = a[i]
            a[i] = a[equal]
            a[equal] = t
            equal += t <= pivot
        if kth < equal or equal == store:  # (equal == store: only with a NaN pivot)
            return pivot
        lo = equal
    if hi - lo == 2 and a[lo] > a[lo + 1]:
        a[lo], a[lo + 1] = a[lo + 1], a[lo]
    return a[kth]
