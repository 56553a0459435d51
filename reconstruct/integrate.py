"""Normal integration: depth maps from normal maps, least-squares or discontinuity-preserving.

Both methods fit depth differences between 4-neighbouring pixels ``p, q`` to the differences the
normals predict, over the pixels of the mask that carry a normal, with no condition at the mask's
outline (natural boundary conditions):

    E(g) = sum over neighbour pairs e = (p, q) of c_e (g_q - g_p - t_e)^2.

The normal equations are a weighted graph Laplacian ``L g = b``, solved by conjugate gradients
preconditioned with a multigrid V-cycle whose levels aggregate 2 x 2 blocks of pixels
(:mod:`ps_lab.reconstruct._multigrid`; half the time and memory of classical algebraic multigrid
on these systems, and no BLAS call that could spin threads on a busy machine). Each 4-connected
component of the pixels is integrated on its own; its offset (orthographic) or scale (perspective)
cannot be known from normals and is fixed by convention (:class:`Integration`).

Camera frame (the frame of the normals): x right, y up, z toward the camera; the row index grows
downward. ``depth`` is the distance along the viewing axis, away from the camera (``z = -depth``).

Orthographic camera (one pixel = one length unit), ``g = depth``:

    d depth / d col = n_x / n_z,        d depth / d row = -n_y / n_z.

Perspective camera (focal length ``f`` in pixels, principal point ``(c_x, c_y)``),
``g = log depth``, with ``u = col - c_x``, ``v = row - c_y`` and ``m = f n_z - u n_x + v n_y``
(``f`` times the cosine between the normal and the line of sight, > 0 on every visible surface):

    d log depth / d col = n_x / m,      d log depth / d row = -n_y / m,

from the surface point ``P = depth / f (u, -v, -f)`` and ``n . dP = 0`` along both pixel axes.

``poisson``: ``c_e = 1`` and ``t_e`` the trapezoid rule (mean of the two pixels' gradients, second
order on smooth surfaces): the classical least-squares integration (Quéau, Durou & Aujol 2018).

``bilateral``: Bilateral Normal Integration (BiNI; Cao, Santo, Shi, Okura & Matsushita 2022), with
one change to its weight rule. Every pixel ``p`` has, along each axis, a forward and a backward
one-sided equation, BiNI's ``n_z D+ z + n_x`` and ``n_z D- z + n_x`` (perspective: log depth,
``n_z`` replaced by ``m / f``), with weights ``w_p`` and ``1 - w_p``:

    E = sum_p  w_p n_z(p)^2 (D+ g - t_p)^2 + (1 - w_p) n_z(p)^2 (D- g - t_p)^2,

``t_p`` the pixel's own gradient (first order, as published). A pair ``e = (p, q)`` carries ``p``'s
forward and ``q``'s backward equation, so ``E`` is the pair energy above with
``c_e = a + b``, ``t_e = (a t_p + b t_q) / (a + b)``, ``a = w_p n_z(p)^2``,
``b = (1 - w_q) n_z(q)^2`` (plus a constant): the same Laplacian and solver as ``poisson``. The
weights start at 1/2 and are re-estimated from the last solution (iteratively reweighted least
squares) until the energy has changed by less than ``tolerance`` (1e-3) for the second time
(BiNI stops at the first such change, which here also happened while a step was still forming):

    w_p = sigmoid(k (m_-(p)^2 - m_+(p)^2)),

the weight going to the side without the discontinuity. **The departure from the paper:** BiNI
compares the one-sided depth differences themselves, ``m_± = D± z`` with ``k = 2``; here ``m_±``
are their misfits to the normals, ``D± g - t_e`` (``t_e`` the trapezoid prediction of that pair), in
pixels of depth (perspective: log depth times ``f``), with ``k = 50`` per square pixel
(``sharpness``). At an occluding edge the smooth side of the lip is itself steep (the normal turns
away from the camera), so its depth difference is as large as the not-yet-formed jump's and BiNI's
own rule cuts the wrong side or none (measured, ``docs/results.md``); the misfit is small on the
smooth side at any slope. A pixel with a single neighbour along an axis keeps its one equation
(``w = 1`` or ``0``). Smooth surfaces: weights stay near 1/2 and the depth is ``poisson``'s to
within the first-order error of the own-gradient targets.

References
----------
.. [1] Y. Quéau, J.-D. Durou, J.-F. Aujol, "Normal Integration: A Survey", JMIV 60, 2018.
.. [2] X. Cao, H. Santo, B. Shi, F. Okura, Y. Matsushita, "Bilateral Normal Integration",
   ECCV 2022.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp

from ps_lab.errors import DatasetError
from ps_lab.reconstruct._multigrid import GridMultigrid, conjugate_gradients

__all__ = [
    "BILATERAL_MAX_ITERATIONS",
    "INTEGRATION_METHODS",
    "Integration",
    "IntegrationInputError",
    "integrate",
    "valid_normals",
]

INTEGRATION_METHODS = ("poisson", "bilateral")
#: Most reweighting iterations of ``bilateral`` by default.
BILATERAL_MAX_ITERATIONS = 150

# Normals at grazing angles (cosine to the line of sight below this) are treated as missing: their
# gradients are unbounded and a single such pixel would dominate its neighbourhood.
_MIN_COSINE = 1e-3
# Smallest weight of a pair of pixels: keeps the system definite when steps cut a region off.
_MIN_WEIGHT = 1e-6
# A pair of pixels counts as a discontinuity when both its one-sided equations weigh less than this.
_CUT = 0.1
# Conjugate-gradient iterations per linear solve at most (10-25 are needed).
_MAX_SOLVER_ITERATIONS = 500


class IntegrationInputError(DatasetError, ValueError):
    """Normals, mask or camera parameters that cannot be integrated (one CLI line, and a
    ``ValueError`` for library callers, as the solvers' ``SolverInputError``)."""


@dataclass(frozen=True)
class Integration:
    """Depth integrated from a normal map.

    Attributes
    ----------
    depth : ndarray of shape (H, W), float32
        Distance along the viewing axis (away from the camera), NaN where nothing was integrated.
        Orthographic: in pixels, each component's median set to 0. Perspective: each component
        scaled so that its median depth equals the focal length, which makes a pixel one unit wide
        at that depth, as in the orthographic case.
    method : str
        ``'poisson'`` or ``'bilateral'``.
    camera : str
        ``'orthographic'`` or ``'perspective'``.
    components : int
        4-connected components integrated separately, each with its own unknown offset (or scale).
    pixels : int
        Pixels integrated.
    iterations : int
        Reweighting iterations (1 for ``poisson``).
    solver_iterations : int
        Conjugate-gradient iterations over all linear solves.
    residual : float
        Root-mean-square misfit of the equations (``poisson``: the pairs' ``g_q - g_p - t_e``;
        ``bilateral``: the one-sided equations, weighted by their weights): in pixels per pixel
        (orthographic) or log-depth per pixel (perspective); 0 for an integrable field.
    discontinuities : int
        Pairs of neighbours both of whose one-sided equations weigh less than 0.1 (``bilateral``;
        0 for ``poisson``): the pixel boundaries that carry a depth step.
    converged : bool
        Whether every linear solve and, for ``bilateral``, the reweighting reached its tolerance.
    energy_change : float
        ``bilateral``: relative change of the energy at the last iteration (0 for ``poisson``).
    alternating : bool
        ``bilateral``: the last three energies alternate (the first and the last agree to within
        ``tolerance`` while the middle one differs by more): the side weights flip between two
        states, and further iterations do not settle them.
    """

    depth: np.ndarray
    method: str
    camera: str
    components: int
    pixels: int
    iterations: int
    solver_iterations: int
    residual: float
    discontinuities: int
    converged: bool
    energy_change: float = 0.0
    alternating: bool = False


def valid_normals(normals: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Pixels that carry a usable normal.

    Parameters
    ----------
    normals : ndarray of shape (H, W, 3)
        Normals (any length) in the camera frame: x right, y up, z toward the camera.
    mask : ndarray of shape (H, W), optional
        Pixels to consider (non-zero); default all.

    Returns
    -------
    ndarray of shape (H, W), bool
        Inside ``mask``, finite, non-zero and facing the camera (``n_z > 0.001 |n|``; a
        perspective camera applies its own test in :func:`integrate`).
    """
    normals = np.asarray(normals)
    finite = np.all(np.isfinite(normals), axis=-1)
    clean = np.where(finite[..., None], normals, 0)
    length = np.sqrt(np.einsum("...i,...i->...", clean, clean, dtype=np.float64))
    valid = finite & (length > 0)
    if mask is not None:
        valid &= np.asarray(mask) != 0
    return valid & (clean[..., 2] > _MIN_COSINE * length)


def integrate(
    normals: np.ndarray,
    mask: np.ndarray | None = None,
    method: str = "poisson",
    *,
    focal_length: float | None = None,
    principal_point: tuple[float, float] | None = None,
    sharpness: float = 50.0,
    max_iterations: int = BILATERAL_MAX_ITERATIONS,
    tolerance: float = 1e-3,
    solver_tolerance: float | None = None,
    progress: Callable[..., None] | None = None,
) -> Integration:
    """Integrate a normal map into a depth map.

    Parameters
    ----------
    normals : ndarray of shape (H, W, 3)
        Surface normals in the camera frame (x right, y up, z toward the camera; the row index
        grows downward), any length. Zero or non-finite normals are skipped.
    mask : ndarray of shape (H, W), optional
        Pixels to integrate (non-zero); default every pixel with a normal.
    method : {'poisson', 'bilateral'}
        Least squares, or discontinuity-preserving (bilateral normal integration; module
        docstring).
    focal_length : float, optional
        Focal length in pixels: perspective camera. Default orthographic (one pixel = one unit).
    principal_point : (x, y), optional
        Principal point in pixels (column, row), origin at the centre of the top-left pixel;
        default the image centre ``((W - 1) / 2, (H - 1) / 2)``. Perspective only.
    sharpness : float
        ``bilateral``: ``k`` of the side weights ``sigmoid(k (m_-^2 - m_+^2))``, per square pixel of
        depth misfit (module docstring): a side whose depth difference disagrees with the normals
        by 0.2 px, the other side agreeing, keeps 12 % of the weight; by 0.3 px, 1 %.
    max_iterations : int
        ``bilateral``: most reweighting iterations.
    tolerance : float
        ``bilateral``: stop when the energy has changed by at most this share between two
        iterations for the second time.
    solver_tolerance : float, optional
        Relative residual of each linear solve; default 1e-6 (the depth of the benchmark relief
        agrees with a 1e-8 solve to 4 digits of its error).
    progress : callable, optional
        ``progress(1)`` after each reweighting iteration (``bilateral``: at most
        ``max_iterations`` calls) or after the one solve (``poisson``), e.g. the ``advance`` of a
        progress bar.

    Returns
    -------
    Integration
        The depth map and how it was obtained.

    Raises
    ------
    IntegrationInputError
        Wrong shapes, an unknown method, bad camera or solver parameters.
    """
    normals = np.asarray(normals)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise IntegrationInputError(f"normals must be (H, W, 3), got {normals.shape}")
    shape = normals.shape[:2]
    if mask is not None and np.shape(mask) != shape:
        raise IntegrationInputError(f"mask must be {shape}, got {np.shape(mask)}")
    if method not in INTEGRATION_METHODS:
        raise IntegrationInputError(
            f"unknown integration method {method!r}; expected one of {INTEGRATION_METHODS}"
        )
    if focal_length is not None and not (np.isfinite(focal_length) and focal_length > 0):
        raise IntegrationInputError(f"focal length must be positive, got {focal_length}")
    if principal_point is not None and focal_length is None:
        raise IntegrationInputError("a principal point needs a focal length (perspective camera)")
    if solver_tolerance is None:
        solver_tolerance = 1e-6
    if not (sharpness > 0 and max_iterations >= 1 and tolerance > 0 and solver_tolerance > 0):
        raise IntegrationInputError(
            "need sharpness > 0, max_iterations >= 1, tolerance > 0 and solver_tolerance > 0"
        )

    if normals.dtype == bool or not (
        np.issubdtype(normals.dtype, np.floating) or np.issubdtype(normals.dtype, np.integer)
    ):
        raise IntegrationInputError(f"normals must be real numbers, got dtype {normals.dtype}")
    valid = valid_normals(normals, mask)
    if not valid.any():
        raise IntegrationInputError(
            "no pixel carries a normal facing the camera (all zero, NaN or turned away)"
        )
    n = normals[valid].astype(np.float64)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    if focal_length is not None:
        h, w = shape
        cx, cy = principal_point if principal_point is not None else ((w - 1) / 2, (h - 1) / 2)
        rows, cols = np.nonzero(valid)
        u = cols - cx
        v = rows - cy
        del rows, cols
        focal_length = float(focal_length)
        m = focal_length * n[:, 2] - u * n[:, 0] + v * n[:, 1]
        facing = m > _MIN_COSINE * np.hypot(focal_length, np.hypot(u, v))
        del u, v
        if not facing.any():
            raise IntegrationInputError(
                f"no normal faces the camera at a focal length of {focal_length:g} px "
                "(--focal-length: in pixels, about the image width for a normal lens)"
            )
        if not facing.all():
            valid[valid] = facing
            n, m = n[facing], m[facing]
    else:
        m = n[:, 2]
    gradient_col = n[:, 0] / m
    gradient_row = -n[:, 1] / m
    del n
    graph = _Graph(valid)
    if graph.tail.size == 0:
        raise IntegrationInputError(
            f"no two neighbouring pixels carry a normal ({graph.size} isolated pixel(s)): "
            "depth needs 4-connected pixels to integrate"
        )
    if method == "poisson":
        del m
        t = graph.trapezoid_targets(gradient_col, gradient_row)
        del gradient_col, gradient_row
        g, info = _least_squares(graph, t, solver_tolerance)
        if progress is not None:
            progress(1)
    else:
        # BiNI's residuals are the normal equations n_z D z + n_x (orthographic) and their
        # perspective form, m / f times the log-depth ones: each one-sided equation of a pixel is
        # weighted by the square of that factor. Misfits are measured in pixels of depth:
        # log-depth misfits times the normalised depth (the focal length).
        unit = 1.0 if focal_length is None else float(focal_length)
        factor = m if focal_length is None else m / unit
        del m
        g, info = _bilateral(
            graph, gradient_col, gradient_row, factor**2, sharpness * unit**2,
            max_iterations, tolerance, solver_tolerance, progress,
        )
    depth = np.full(shape, np.nan, dtype=np.float32)
    with np.errstate(over="ignore"):  # beyond float32: infinite, refused by the caller
        depth[valid] = _fix_gauge(g, graph, focal_length)
    return Integration(
        depth=depth,
        method=method,
        camera="orthographic" if focal_length is None else "perspective",
        components=graph.components,
        pixels=graph.size,
        **info,
    )


class _Graph:
    """The valid pixels (nodes, raster order) and their pairs of 4-neighbours (edges).

    Edges come first all horizontal ones (pixel to its right neighbour), then all vertical ones
    (pixel to the one below), each in raster order; ``tail`` and ``head`` are their node indices.
    Also holds the CSR pattern of the graph Laplacian, so that a new set of edge weights costs only
    a gather.
    """

    def __init__(self, valid: np.ndarray) -> None:
        h, w = valid.shape
        self.valid = valid
        self.size = int(np.count_nonzero(valid))
        index = np.full(valid.shape, -1, dtype=np.int32)
        index[valid] = np.arange(self.size, dtype=np.int32)
        right = valid[:, :-1] & valid[:, 1:]
        down = valid[:-1, :] & valid[1:, :]
        self.tail = np.concatenate([index[:, :-1][right], index[:-1, :][down]])
        self.head = np.concatenate([index[:, 1:][right], index[1:, :][down]])
        self.horizontal = int(np.count_nonzero(right))
        labels, self.components = ndi.label(valid)
        self.labels = labels[valid]
        del labels
        # CSR pattern: row i holds, in column order, its up, left, diagonal, right, down entries.
        # up/left entries of row i are edges where i is the head; right/down where it is the tail.
        up = np.zeros(valid.shape, bool)
        up[1:] = down
        left = np.zeros(valid.shape, bool)
        left[:, 1:] = right
        has_right = np.zeros(valid.shape, bool)
        has_right[:, :-1] = right
        has_down = np.zeros(valid.shape, bool)
        has_down[:-1] = down
        slots = [up[valid], left[valid], None, has_right[valid], has_down[valid]]
        del up, left, has_right, has_down, index
        counts = np.ones(self.size, dtype=np.int64)
        for present in slots:
            if present is not None:
                counts += present
        nnz = int(counts.sum())
        # One index type for indptr and indices: scipy would otherwise copy both to int64.
        position_type = np.int32 if nnz < 2**31 else np.int64
        self.indptr = np.zeros(self.size + 1, dtype=position_type)
        np.cumsum(counts, out=self.indptr[1:])
        del counts
        offset = self.indptr[:-1].astype(position_type)  # next free slot of each row
        self.indices = np.empty(nnz, dtype=position_type)
        edge_count = self.tail.size
        vertical = np.arange(self.horizontal, edge_count)
        horizontal = np.arange(self.horizontal)
        # Edges sorted by head: their raster order is the order of the up/left slots (per row).
        # Position of each edge's entry in the head row and in the tail row.
        self.at_head = np.empty(edge_count, dtype=position_type)
        self.at_tail = np.empty(edge_count, dtype=position_type)
        # Slot order per row: up (vertical edge with head = row), left (horizontal, head = row),
        # diagonal, right (horizontal, tail = row), down (vertical, tail = row).
        for kind, edges, end in (
            ("up", vertical, "head"),
            ("left", horizontal, "head"),
            ("diag", None, None),
            ("right", horizontal, "tail"),
            ("down", vertical, "tail"),
        ):
            if kind == "diag":
                self.at_diagonal = offset.copy()
                self.indices[offset] = np.arange(self.size, dtype=np.int32)
                offset += 1
                continue
            rows = (self.head if end == "head" else self.tail)[edges]
            other = (self.tail if end == "head" else self.head)[edges]
            where = offset[rows]
            self.indices[where] = other
            (self.at_head if end == "head" else self.at_tail)[edges] = where
            offset[rows] += 1
        del offset
        # One node per component is pinned (a soft anchor) so that L is definite.
        first = ndi.minimum(
            np.arange(self.size), self.labels, np.arange(1, self.components + 1)
        )
        self.pinned = np.asarray(first, dtype=np.int64).reshape(-1)

    def trapezoid_targets(self, gradient_col: np.ndarray, gradient_row: np.ndarray) -> np.ndarray:
        """Predicted ``g_head - g_tail`` of every edge: the mean of its two ends' gradients."""
        k = self.horizontal
        t = np.empty(self.tail.size)
        t[:k] = 0.5 * (gradient_col[self.tail[:k]] + gradient_col[self.head[:k]])
        t[k:] = 0.5 * (gradient_row[self.tail[k:]] + gradient_row[self.head[k:]])
        return t

    def laplacian(self, weights: np.ndarray) -> sp.csr_matrix:
        """Weighted graph Laplacian ``sum_e c_e (e_head - e_tail)(e_head - e_tail)^T`` + anchors."""
        data = np.empty(self.indices.size)
        data[self.at_head] = -weights
        data[self.at_tail] = -weights
        diagonal = np.bincount(self.tail, weights, self.size).astype(np.float64)
        diagonal += np.bincount(self.head, weights, self.size)
        anchor = float(np.mean(diagonal)) if self.size else 1.0
        self.anchor = np.full(self.pinned.size, anchor if anchor > 0 else 1.0)
        diagonal[self.pinned] += self.anchor
        data[self.at_diagonal] = diagonal
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.size, self.size))

    def drop_pattern(self) -> None:
        """Free the entries' positions in the Laplacian (no reweighting will follow)."""
        self.at_head = self.at_tail = self.at_diagonal = None

    def sides(self, edges: slice) -> tuple[np.ndarray, np.ndarray]:
        """Per node, its forward and backward edge among ``edges`` (one axis); -1 where none."""
        index = np.arange(edges.start, edges.stop, dtype=np.int32)
        forward = np.full(self.size, -1, dtype=np.int32)
        forward[self.tail[edges]] = index
        backward = np.full(self.size, -1, dtype=np.int32)
        backward[self.head[edges]] = index
        return forward, backward

    def positions(self) -> tuple[np.ndarray, np.ndarray]:
        """Row and column (int32) of every node."""
        rows, cols = np.nonzero(self.valid)
        return rows.astype(np.int32), cols.astype(np.int32)

    def divergence(self, flow: np.ndarray) -> np.ndarray:
        """``D^T flow``: flow into each node minus flow out of it."""
        return np.bincount(self.head, flow, self.size) - np.bincount(self.tail, flow, self.size)

    def differences(self, g: np.ndarray) -> np.ndarray:
        """``g_head - g_tail`` for every edge."""
        return g[self.head] - g[self.tail]


def _solve(graph: _Graph, weights, rhs, x0, tolerance, last=False):
    """Conjugate gradients preconditioned with the pixel-grid aggregation multigrid.

    ``weights`` is dropped once the hierarchy is built (memory: pass a temporary array);
    ``last``: no other system of this graph follows, its assembly pattern is freed.
    """
    matrix = graph.laplacian(weights)
    if last:
        graph.drop_pattern()
    rows, cols = graph.positions()
    hierarchy = GridMultigrid(
        matrix, graph.tail, graph.head, weights, graph.pinned, graph.anchor, rows, cols
    )
    del rows, cols, weights
    x, iterations, converged = conjugate_gradients(
        matrix, rhs, x0, tolerance, _MAX_SOLVER_ITERATIONS, hierarchy
    )
    return x, iterations, converged


def _least_squares(graph: _Graph, t: np.ndarray, tolerance: float):
    rhs = graph.divergence(t)
    # Unit weights in float32: half the memory, exact.
    g, iterations, converged = _solve(
        graph, np.ones(t.size, dtype=np.float32), rhs, None, tolerance, last=True
    )
    del rhs
    misfit = graph.differences(g) - t
    residual = float(np.sqrt(np.mean(misfit**2))) if t.size else 0.0
    return g, {
        "iterations": 1,
        "solver_iterations": iterations,
        "residual": residual,
        "discontinuities": 0,
        "converged": converged,
    }


def _bilateral(graph, gradient_col, gradient_row, factor2, sharpness, max_iterations, tolerance,
               solver_tolerance, progress=None):
    """Bilateral normal integration in pair form (module docstring), from side weights 1/2."""
    k = graph.horizontal
    # Each edge (p, q) holds p's forward and q's backward one-sided equation of its direction;
    # their targets are the gradient of p and of q (first order, as in BiNI).
    own_tail = np.concatenate([gradient_col[graph.tail[:k]], gradient_row[graph.tail[k:]]])
    own_head = np.concatenate([gradient_col[graph.head[:k]], gradient_row[graph.head[k:]]])
    trapezoid = 0.5 * (own_tail + own_head)
    del gradient_col, gradient_row
    sides = [graph.sides(slice(0, k)), graph.sides(slice(k, graph.tail.size))]
    forward = [_one_sided(fwd, bwd, None, sharpness) for fwd, bwd in sides]
    g = None
    total = 0
    all_converged = True
    settled = False
    previous = None
    calm = 0
    iteration = 0
    energies: list[float] = []  # the last three
    for iteration in range(1, max_iterations + 1):
        tail_weight, head_weight = _equation_weights(graph, forward, factor2)
        pair = np.maximum(tail_weight + head_weight, _MIN_WEIGHT)
        g, its, converged = _solve(
            graph, pair, graph.divergence(tail_weight * own_tail + head_weight * own_head), g,
            solver_tolerance,
        )
        total += its
        all_converged &= converged
        difference = graph.differences(g)
        energy = float(
            np.sum(tail_weight * (difference - own_tail) ** 2)
            + np.sum(head_weight * (difference - own_head) ** 2)
        )
        energies = [*energies[-2:], energy]
        misfit = difference - trapezoid
        forward = [_one_sided(fwd, bwd, misfit, sharpness) for fwd, bwd in sides]
        # Settled at the second small energy change: a first one also happens while a step is
        # still forming (measured: k = 45 stopped at 11 iterations with 3 wrong columns). Two in a
        # row would be stricter, but on real shapes (DiLiGenT) the energy then rarely settled
        # within 150 iterations.
        if progress is not None:
            progress(1)
        small = previous is not None and abs(previous - energy) <= tolerance * previous
        calm += small
        if calm >= 2:
            settled = True
            break
        previous = energy
    total_weight = float(np.sum(tail_weight) + np.sum(head_weight))
    residual = float(np.sqrt(energy / total_weight)) if total_weight else 0.0
    # A pair both of whose equations are (nearly) dropped carries a step.
    cut = int(np.count_nonzero(_cut_pairs(graph, forward)))
    change, alternating = _last_change(energies, tolerance)
    return g, {
        "iterations": iteration,
        "solver_iterations": total,
        "residual": residual,
        "discontinuities": cut,
        "converged": bool(all_converged and settled),
        "energy_change": change,
        "alternating": alternating,
    }


def _last_change(energies: list[float], tolerance: float) -> tuple[float, bool]:
    """Relative change of the last of ``energies``, and whether the last three alternate.

    Alternating: the first and the last agree to within ``tolerance`` while the last change is
    larger, i.e. the weights flip between two states.
    """
    if len(energies) < 2 or energies[-2] <= 0:
        return 0.0, False
    change = abs(energies[-1] - energies[-2]) / energies[-2]
    alternating = (
        len(energies) >= 3
        and change > tolerance
        and abs(energies[-1] - energies[-3]) <= tolerance * energies[-3]
    )
    return float(change), bool(alternating)


def _one_sided(fwd, bwd, misfit, sharpness):
    """Weight of each pixel's forward equation along one axis, ``sigmoid(k (m_-^2 - m_+^2))``.

    ``fwd``, ``bwd``: the pixel's forward and backward edge (-1: none); ``misfit`` per edge
    (None: the start, 1/2). A pixel with one neighbour on the axis keeps its one equation.
    """
    has_fwd, has_bwd = fwd >= 0, bwd >= 0
    if misfit is None:
        weight = np.full(fwd.size, 0.5)
    else:
        ahead = misfit[np.where(has_fwd, fwd, 0)]
        behind = misfit[np.where(has_bwd, bwd, 0)]
        # sigmoid(x) = (1 + tanh(x / 2)) / 2, without overflow.
        weight = 0.5 + 0.5 * np.tanh(0.5 * sharpness * (behind * behind - ahead * ahead))
    weight[~has_bwd] = 1.0
    weight[~has_fwd & has_bwd] = 0.0
    return weight


def _equation_weights(graph, forward, factor2):
    """Per edge: weight of its tail's forward and its head's backward equation."""
    k = graph.horizontal
    tail_weight = np.empty(graph.tail.size)
    head_weight = np.empty(graph.tail.size)
    for axis, edges in enumerate((slice(0, k), slice(k, graph.tail.size))):
        tail, head = graph.tail[edges], graph.head[edges]
        tail_weight[edges] = forward[axis][tail] * factor2[tail]
        head_weight[edges] = (1.0 - forward[axis][head]) * factor2[head]
    return tail_weight, head_weight


def _cut_pairs(graph, forward):
    """Edges whose two one-sided equations both weigh less than ``_CUT``."""
    k = graph.horizontal
    cut = np.empty(graph.tail.size, dtype=bool)
    for axis, edges in enumerate((slice(0, k), slice(k, graph.tail.size))):
        cut[edges] = (forward[axis][graph.tail[edges]] < _CUT) & (
            forward[axis][graph.head[edges]] > 1.0 - _CUT
        )
    return cut


def _fix_gauge(g: np.ndarray, graph: _Graph, focal_length: float | None) -> np.ndarray:
    """Each component's median to 0 (orthographic) or its median depth to ``f`` (perspective)."""
    if graph.components == 1:
        g = g - np.median(g)  # a partial sort: a quarter of ndi.median's time
    else:
        medians = ndi.median(g, graph.labels, np.arange(1, graph.components + 1))
        shift = np.concatenate([[0.0], np.asarray(medians, dtype=np.float64).reshape(-1)])
        g = g - shift[graph.labels]
    if focal_length is None:
        return g
    return focal_length * np.exp(g)
