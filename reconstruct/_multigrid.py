"""Aggregation multigrid for weighted graph Laplacians on the pixel grid (normal integration).

The systems of :mod:`ps_lab.reconstruct.integrate` are graph Laplacians of 4-neighbouring pixels,
``L = sum_e c_e (e_head - e_tail)(e_head - e_tail)^T`` plus a few diagonal anchors. This module
builds a multigrid hierarchy for them from the pixel grid itself rather than from the matrix graph
(as classical AMG does):

* aggregates are 2 x 2 blocks of pixels (of coarse nodes, on the coarser levels), split into their
  strongly connected parts: a pair whose weight is small next to its two nodes' diagonals (a pixel
  pair cut at a depth step, :mod:`~ps_lab.reconstruct.integrate`'s ``bilateral``) never joins
  two nodes, so that each side of a step keeps its own coarse unknowns;
* interpolation is piecewise constant (a node takes its aggregate's value), so the Galerkin coarse
  operator ``P^T L P`` is again a weighted graph Laplacian: the weight between two aggregates is
  the sum of the weights of the pixel pairs between them, and an anchor goes to its aggregate;
  a level costs a quarter of the one above (operator complexity about 1.3, against 2.2 for
  Ruge-Stuben AMG on these matrices);
* a V-cycle with one forward Gauss-Seidel sweep before and one backward sweep after the coarse
  correction (a symmetric preconditioner), the coarse correction over-corrected by a fixed factor
  1.8, the usual remedy for the too-smooth piecewise-constant interpolation (Braess 1995; Notay
  2010); a sparse direct solve on the coarsest level.

Measured on the benchmark relief (``docs/results.md``, "Normal integration"): conjugate gradients
with this preconditioner need 10-15 iterations for a relative residual of 1e-6 from 1 to 12 MP,
against 8-10 with Ruge-Stuben AMG, but the set-up costs a tenth and the hierarchy a fifth of the
memory.

References
----------
.. [1] D. Braess, "Towards algebraic multigrid for elliptic problems of second order",
   Computing 55, 1995.
.. [2] Y. Notay, "An aggregation-based algebraic multigrid method", ETNA 37, 2010.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from pyamg.relaxation.relaxation import gauss_seidel
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

__all__ = ["GridMultigrid", "conjugate_gradients", "graph_laplacian"]

# A pair joins its two nodes in an aggregate when its weight is at least this share of the
# geometric mean of their diagonals (a quarter for the unit weights of an interior pixel).
_STRENGTH = 0.1
# Over-correction of the piecewise-constant coarse correction (iterations on the 1 MP relief:
# 1.0 -> 52, 1.5 -> 16 with two sweeps, 1.8 -> 10-12, 2.0 -> 10; 2 is the limit for a two-level
# V-cycle to stay a positive definite preconditioner).
_OVER_CORRECTION = 1.8
# Stop coarsening at this size, or when a level no longer shrinks by a third.
_MAX_COARSE = 1000
_MIN_REDUCTION = 1.5


def graph_laplacian(
    size: int,
    tail: np.ndarray,
    head: np.ndarray,
    weights: np.ndarray,
    anchors: np.ndarray,
    anchor_weights: np.ndarray,
) -> sp.csr_matrix:
    """Weighted graph Laplacian plus diagonal anchors, as a CSR matrix.

    Parameters
    ----------
    size : int
        Nodes ``N``.
    tail, head : ndarray of shape (E,), int
        The two nodes of each edge (no edge twice, no loop).
    weights : ndarray of shape (E,)
        Edge weights, non-negative.
    anchors : ndarray of shape (K,), int
        Nodes with an anchor (repeats add up).
    anchor_weights : ndarray of shape (K,)
        Their diagonal terms.

    Returns
    -------
    csr_matrix of shape (N, N), float64
    """
    diagonal = np.bincount(tail, weights, size) + np.bincount(head, weights, size)
    np.add.at(diagonal, anchors, anchor_weights)
    nodes = np.arange(size, dtype=tail.dtype)
    matrix = sp.csr_matrix(
        (
            np.concatenate([-weights, -weights, diagonal]),
            (np.concatenate([tail, head, nodes]), np.concatenate([head, tail, nodes])),
        ),
        shape=(size, size),
    )
    matrix.sum_duplicates()
    return matrix


def _coarsen(size, tail, head, weights, anchors, rows, cols):
    """Aggregates of one level (2 x 2 blocks of ``rows, cols`` split by strength), coarse graph.

    ``rows`` and ``cols`` are halved in place (memory: they become the block indices).
    """
    diagonal = np.bincount(tail, weights, size) + np.bincount(head, weights, size)
    block_row = np.floor_divide(rows, 2, out=rows)
    block_col = np.floor_divide(cols, 2, out=cols)
    inside = (block_row[tail] == block_row[head]) & (block_col[tail] == block_col[head])
    inner = np.flatnonzero(inside)
    del inside
    strong = inner[
        weights[inner] >= _STRENGTH * np.sqrt(diagonal[tail[inner]] * diagonal[head[inner]])
    ]
    del inner, diagonal
    joins = sp.csr_matrix(
        (np.ones(strong.size, np.int8), (tail[strong], head[strong])), shape=(size, size)
    )
    del strong
    coarse_size, aggregate = connected_components(joins, directed=False)
    del joins
    aggregate = aggregate.astype(np.int32)
    coarse_rows = np.empty(coarse_size, np.int32)
    coarse_rows[aggregate] = block_row
    coarse_cols = np.empty(coarse_size, np.int32)
    coarse_cols[aggregate] = block_col
    a, b = aggregate[tail], aggregate[head]
    between = np.flatnonzero(a != b)
    a, b, w = a[between], b[between], weights[between]
    del between
    # Pairs between the same two aggregates add up (summed duplicates of a CSR matrix).
    edges = sp.csr_matrix((w, (np.minimum(a, b), np.maximum(a, b))), shape=(coarse_size,) * 2)
    del a, b, w
    edges.sum_duplicates()
    coarse_tail = np.repeat(np.arange(coarse_size, dtype=np.int32), np.diff(edges.indptr))
    coarse_head = edges.indices.astype(np.int32, copy=False)
    return (
        aggregate,
        coarse_size,
        coarse_tail,
        coarse_head,
        edges.data.astype(np.float64, copy=False),
        aggregate[anchors],
        coarse_rows,
        coarse_cols,
    )


class GridMultigrid:
    """Aggregation multigrid V-cycle for a pixel-graph Laplacian (module docstring).

    Parameters
    ----------
    matrix : csr_matrix of shape (N, N)
        The Laplacian with anchors, ``graph_laplacian(N, tail, head, weights, anchors,
        anchor_weights)`` (or the same matrix assembled otherwise).
    tail, head : ndarray of shape (E,), int32
        Node pairs of its edges.
    weights : ndarray of shape (E,)
        Edge weights.
    anchors : ndarray of shape (K,), int
        Anchored nodes; ``anchor_weights`` their diagonal terms.
    anchor_weights : ndarray of shape (K,)
    rows, cols : ndarray of shape (N,), int32
        Pixel position of each node; overwritten (pass temporaries).

    Calling the object with a residual ``r`` (N,) returns ``M r``, one V-cycle from zero.
    """

    def __init__(self, matrix, tail, head, weights, anchors, anchor_weights, rows, cols):
        self.matrices = [matrix]
        self.aggregates: list[np.ndarray] = []
        size = matrix.shape[0]
        anchors = np.asarray(anchors, dtype=np.int32)
        while size > _MAX_COARSE:
            aggregate, coarse_size, tail, head, weights, anchors, rows, cols = _coarsen(
                size, tail, head, weights, anchors, rows, cols
            )
            if coarse_size * _MIN_REDUCTION > size:
                break
            self.aggregates.append(aggregate)
            size = coarse_size
            self.matrices.append(
                graph_laplacian(size, tail, head, weights, anchors, anchor_weights)
            )
        del tail, head, weights, rows, cols
        # The coarsest level (or a small matrix) is solved directly.
        self._coarse = splu(self.matrices[-1].tocsc())

    @property
    def levels(self) -> int:
        """Number of levels, the coarsest solved directly (1: a direct solve)."""
        return len(self.matrices)

    def __call__(self, residual: np.ndarray) -> np.ndarray:
        return self._cycle(0, residual)

    def _cycle(self, level: int, rhs: np.ndarray) -> np.ndarray:
        if level == len(self.matrices) - 1:
            return self._coarse.solve(rhs)
        matrix = self.matrices[level]
        aggregate = self.aggregates[level]
        x = np.zeros_like(rhs)
        gauss_seidel(matrix, x, rhs, iterations=1, sweep="forward")
        residual = matrix @ x
        np.subtract(rhs, residual, out=residual)
        coarse_rhs = np.bincount(aggregate, residual, self.matrices[level + 1].shape[0])
        del residual
        correction = self._cycle(level + 1, coarse_rhs)
        correction *= _OVER_CORRECTION
        x += correction[aggregate]
        del correction, coarse_rhs
        gauss_seidel(matrix, x, rhs, iterations=1, sweep="backward")
        return x


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """Inner product without BLAS: OpenBLAS threads its ``ddot`` on long vectors, and on a busy
    machine its spinning threads made a 1 MP solve take 50 % more CPU and twice the wall time
    (measured with ``OPENBLAS_NUM_THREADS`` unset against 1)."""
    return float(np.einsum("i,i->", a, b))


def conjugate_gradients(matrix, rhs, x0, tolerance, max_iterations, preconditioner):
    """Preconditioned conjugate gradients for a symmetric positive definite system.

    Parameters
    ----------
    matrix : sparse matrix of shape (N, N)
    rhs : ndarray of shape (N,)
    x0 : ndarray of shape (N,) or None
        Starting point (default zero).
    tolerance : float
        Stop when ``|rhs - matrix x| <= tolerance |rhs|``.
    max_iterations : int
    preconditioner : callable
        ``r -> M r``, symmetric positive definite.

    Returns
    -------
    x : ndarray of shape (N,)
    iterations : int
    converged : bool
    """
    norm = float(np.sqrt(_dot(rhs, rhs)))
    if norm == 0:
        return np.zeros_like(rhs), 0, True
    if x0 is None:
        x = np.zeros_like(rhs)
        r = rhs.copy()
    else:
        x = np.array(x0, dtype=rhs.dtype)
        r = rhs - matrix @ x
    goal = tolerance * norm
    if np.sqrt(_dot(r, r)) <= goal:
        return x, 0, True
    p = preconditioner(r)
    rz = _dot(r, p)
    for iteration in range(1, max_iterations + 1):
        # In place: x, r, p and one work vector q (memory at 12 MP).
        q = matrix @ p
        step = rz / _dot(p, q)
        q *= step
        r -= q
        np.multiply(p, step, out=q)
        x += q
        del q
        if np.sqrt(_dot(r, r)) <= goal:
            return x, iteration, True
        z = preconditioner(r)
        rz, previous = _dot(r, z), rz
        p *= rz / previous
        p += z
        del z
    return x, max_iterations, False
