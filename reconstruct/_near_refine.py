"""Near lights: the LEDs' relative intensities from the object's own images.

The 2012 paper's light refinement (directional lights, alternating with the normals) extended
to lights at a finite distance whose positions are known: one intensity factor per light, fitted
with every pixel's albedo-normal eliminated (:func:`fit_near_intensities`). Measurements of when
it is well posed: ``docs/solvers.md``.
"""

from __future__ import annotations

import numpy as np

from ._linalg import full3, inverse6, sym6
from ._solution import SolverInputError

__all__ = ["fit_near_intensities"]


def fit_near_intensities(
    observations: np.ndarray, use: np.ndarray, light_vectors: np.ndarray
) -> tuple[np.ndarray, float]:
    """Relative light intensities from the object's own images (near lights, points known).

    With light j's unknown factor ``f_j`` on its light vectors, pixel p sees
    ``y_jp = f_j v_jp . x_p``; with ``g_j = 1 / f_j`` the model ``g_j y_jp = v_jp . x_p`` is linear
    in ``g`` and ``x_p`` together. Eliminating each pixel's ``x_p`` (least squares on its inlier
    rows, hat matrix ``H_p``) leaves ``min_g g^T M g`` with ``M = sum_p D(y_p) (I - H_p) D(y_p)``,
    whose solution, up to the scale the albedo absorbs, is the eigenvector of M's smallest
    eigenvalue. An alternation (normals, then each light's least-squares factor given them, as
    the 2012 paper refines directional lights) converges slowly here, since the normals absorb
    much of an intensity error at each step; the eliminated form does not (docs/solvers.md).

    Parameters
    ----------
    observations : ndarray of shape (n, m)
        Observations of m (sample) pixels, divided by the current intensities.
    use : ndarray of shape (n, m), bool
        Inliers (usable and not flagged by the solver).
    light_vectors : ndarray of shape (m, n, 3)
        The pixels' light vectors at their current points (current factors applied).

    Returns
    -------
    factors : ndarray of shape (n,)
        Multiply the current intensities by these (mean 1).
    conditioning : float
        Ratio of M's second-smallest to smallest eigenvalue: how well ``g`` is determined (large:
        well posed; near 1: another ``g`` explains the images as well).
    """
    y = np.asarray(observations, dtype=np.float64)
    use = np.asarray(use, dtype=bool) & np.isfinite(y)
    y = np.where(use, y, 0.0)
    weighted = light_vectors * use.T[:, :, None]
    normal = np.einsum("mni,mnj->mij", weighted, light_vectors)
    inverse, ok = inverse6(sym6(normal))
    if ok.sum() < 3:
        raise SolverInputError("too few solvable pixels to fit the light intensities")
    inverse = full3(inverse[ok])
    rows = weighted[ok]
    hat = np.einsum("mni,mij,mkj->mnk", rows, inverse, rows)
    dy = y.T[ok]
    # D(y) (I - H) D(y), summed over the pixels (outlier rows are zero in both terms)
    m = np.einsum("mn,mn->n", dy, dy * use.T[ok])
    system = np.diag(m) - np.einsum("mn,mnk,mk->nk", dy, hat, dy)
    values, vectors = np.linalg.eigh(system)
    g = vectors[:, 0]
    g = g / g.mean()
    if np.any(g <= 0):
        raise SolverInputError("the light intensities are not determined by these pixels")
    factors = 1.0 / g
    return factors / factors.mean(), float(values[1] / max(values[0], 1e-300))
