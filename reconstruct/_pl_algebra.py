"""Small per-pixel algebra of the PL kernels (:mod:`._pl_kernels`), inlined into them.

A selection for the break points, a Cholesky inverse of the (K+2)x(K+2) normal equations, and a
sum of logs by running products.
"""

from __future__ import annotations

import math

from numba import njit

from ._kernels import INLINE


@njit(**INLINE)
def _select(a, lo, hi, kth):
    """The value of rank ``kth`` of ``a[lo:hi]`` (Hoare's selection, in place, O(n) expected).

    Afterwards ``a[lo:kth] <= a[kth] <= a[kth + 1:hi]``, so a larger rank can be selected in
    ``a[kth:hi]``. The pivot is the median of three (deterministic); the value equals a sort's.
    """
    left = lo
    right = hi - 1
    while right > left:
        mid = (left + right) // 2
        p0, p1, p2 = a[left], a[mid], a[right]
        if p0 > p1:
            p0, p1 = p1, p0
        if p1 > p2:
            p1 = p2
            if p0 > p1:
                p1 = p0
        i = left
        j = right
        while i <= j:
            while a[i] < p1:
                i += 1
            while a[j] > p1:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if kth <= j:
            right = j
        elif kth >= i:
            left = i
        else:
            break
    return a[kth]


@njit(**INLINE)
def _cholesky_inverse(mat, inv, low, u):
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


@njit(**INLINE)
def _sum_log(st, w_row, a_row, b_row, n):
    """``sum_i log(st[a_row, i] + st[b_row, i])`` over the usable observations.

    As the log of running products, renormalised before they leave [1e-150, 1e150]: a log per
    observation would cost more than an SBL iteration.
    """
    acc = 0.0
    prod = 1.0
    for i in range(n):
        if st[w_row, i] > 0.0:
            prod *= st[a_row, i] + st[b_row, i]
            if prod > 1e150 or prod < 1e-150:
                acc += math.log(prod)
                prod = 1.0
    return acc + math.log(prod)
