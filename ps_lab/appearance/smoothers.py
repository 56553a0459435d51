"""Interpolating appearance models as weights over the training lights (pure functions).

The ``rbf``, ``bln`` and ``gp`` models of :mod:`ps_lab.appearance.models` predict a pixel under a
light ``l`` as a weighted sum of its training observations: ``I(l) = w(l)ᵀ y`` with weights
``w(l)`` (n,) that depend only on the ``n`` training lights ``L_i`` and the model's parameters
(the same for every pixel). This module computes ``w(l)``:

- ``rbf``: RelightLab's normalised Gaussian weights
  ``w_i(l) = exp(−|l − L_i|²/σ²) / Σ_j exp(−|l − L_j|²/σ²)``;
- ``bln`` (bilinear, RelightLab's ``-b bilinear``): an ``r × r`` grid of nodes over the light
  plane ``(l_x, l_y) ∈ [−1, 1]²`` (node ``(i, j)`` at ``x = −1 + 2i/(r−1)``, ``y = −1 + 2j/(r−1)``,
  ``z = sqrt(max(1 − x² − y², 0))``), each node the ``rbf`` interpolation (σ) of the training
  lights; a light takes the bilinear interpolation of the four nodes around ``(l_x, l_y)``;
- ``gp`` (Gaussian-process / kernel-ridge regression over the light directions with a PTM mean):
  the Gaussian kernel ``k(a, b) = exp(−|a − b|²/σ²)``, ridge ``λ``, and the six PTM terms
  ``p(l)`` as an unpenalised mean; ``w(l)ᵀ = [k(l, L), p(l)] · G`` with ``G`` the first ``n``
  columns of the inverse of ``[[K + λI, P], [Pᵀ, 0]]`` (:func:`gp_solve`; stored in the file so
  that a reader needs no linear algebra).
"""

from __future__ import annotations

import numpy as np

__all__ = ["bln_weights", "gp_solve", "gp_weights", "gaussian_weights", "grid_nodes"]


def _unit(directions: np.ndarray) -> np.ndarray:
    d = np.asarray(directions, dtype=np.float64)
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    return d / np.where(norm > 0, norm, 1.0)


def _ptm(d: np.ndarray) -> np.ndarray:
    x, y = d[..., 0], d[..., 1]
    return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=-1)


def _sq_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sum((a[..., None, :] - b) ** 2, axis=-1)


def gaussian_weights(directions: np.ndarray, lights: np.ndarray, sigma: float) -> np.ndarray:
    """Normalised Gaussian weights (the ``rbf`` model).

    Parameters
    ----------
    directions : ndarray of shape (..., 3)
    lights : ndarray of shape (n, 3)
    sigma : float

    Returns
    -------
    ndarray of shape (..., n), float64, rows summing to 1

    """
    logw = -_sq_dist(_unit(directions), np.asarray(lights, np.float64)) / (sigma * sigma)
    logw -= logw.max(axis=-1, keepdims=True)
    w = np.exp(logw)
    return w / w.sum(axis=-1, keepdims=True)


def grid_nodes(resolution: int) -> np.ndarray:
    """The ``bln`` grid's nodes, row-major (y then x): ndarray of shape (r·r, 3)."""
    g = np.linspace(-1.0, 1.0, resolution)
    x, y = np.meshgrid(g, g)
    x, y = x.ravel(), y.ravel()
    return np.stack([x, y, np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, 1.0))], axis=-1)


def bln_weights(
    directions: np.ndarray, lights: np.ndarray, sigma: float, resolution: int
) -> np.ndarray:
    """Bilinear interpolation of a grid of ``rbf`` nodes over the light plane (``bln``).

    Parameters
    ----------
    directions : ndarray of shape (..., 3)
    lights : ndarray of shape (n, 3)
    sigma : float
    resolution : int
        Nodes per side (≥ 2).

    Returns
    -------
    ndarray of shape (..., n), float64, rows summing to 1

    """
    d = _unit(directions)
    r = int(resolution)
    nodes = gaussian_weights(grid_nodes(r), lights, sigma)  # (r·r, n)
    g = np.clip((d[..., :2] + 1.0) / 2.0 * (r - 1), 0.0, r - 1 - 1e-9)
    i0 = np.floor(g).astype(np.int64)
    t = g - i0
    out = np.zeros((*d.shape[:-1], nodes.shape[1]))
    for dy in (0, 1):
        for dx in (0, 1):
            wx = t[..., 0] if dx else 1.0 - t[..., 0]
            wy = t[..., 1] if dy else 1.0 - t[..., 1]
            out += (wx * wy)[..., None] * nodes[(i0[..., 1] + dy) * r + i0[..., 0] + dx]
    return out


def gp_solve(lights: np.ndarray, sigma: float, ridge: float) -> np.ndarray:
    """The ``gp`` model's matrix ``G`` (n + 6, n) from its training lights.

    Parameters
    ----------
    lights : ndarray of shape (n, 3)
    sigma, ridge : float

    Returns
    -------
    ndarray of shape (n + 6, n), float64

    """
    lights = _unit(lights)
    n = len(lights)
    kernel = np.exp(-_sq_dist(lights, lights) / (sigma * sigma))
    mean = _ptm(lights)
    m = mean.shape[1]
    system = np.block([[kernel + ridge * np.eye(n), mean], [mean.T, np.zeros((m, m))]])
    return np.linalg.pinv(system)[:, :n]


def gp_weights(
    directions: np.ndarray, lights: np.ndarray, sigma: float, solve: np.ndarray
) -> np.ndarray:
    """The ``gp`` model's weights ``[k(l, L), p(l)] · G``.

    Parameters
    ----------
    directions : ndarray of shape (..., 3)
    lights : ndarray of shape (n, 3)
    sigma : float
    solve : ndarray of shape (n + 6, n)
        :func:`gp_solve`.

    Returns
    -------
    ndarray of shape (..., n), float64

    """
    d = _unit(directions)
    k = np.exp(-_sq_dist(d, np.asarray(lights, np.float64)) / (sigma * sigma))
    return np.concatenate([k, _ptm(d)], axis=-1) @ np.asarray(solve, np.float64)
