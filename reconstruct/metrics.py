"""Error metrics: angular errors of normals, depth errors up to offsets (shared by ps-lab)."""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

__all__ = ["angular_errors_deg", "depth_error", "error_summary"]


def angular_errors_deg(normals: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Angle in degrees between two sets of normals.

    Parameters
    ----------
    normals : ndarray of shape (..., 3)
        Estimated normals; need not be unit length (they are normalised here).
    reference : ndarray of shape (..., 3)
        Ground-truth normals, same shape (or broadcastable).

    Returns
    -------
    ndarray of shape (...,)
        ``arccos`` of the clipped dot product of the unit vectors, in degrees. A zero vector on
        either side (an unsolvable pixel) gives 90 degrees, never NaN.
    """
    a = np.asarray(normals, dtype=np.float64)
    b = np.asarray(reference, dtype=np.float64)
    if a.shape[-1] != 3 or b.shape[-1] != 3:
        raise ValueError(f"normals need a last axis of 3, got {a.shape} and {b.shape}")
    na = np.linalg.norm(a, axis=-1)
    nb = np.linalg.norm(b, axis=-1)
    dot = np.einsum("...k,...k->...", a, b)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.where((na > 0) & (nb > 0), dot / np.maximum(na * nb, np.finfo(float).tiny), 0.0)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def error_summary(errors_deg: np.ndarray) -> dict:
    """Mean, median, 90th percentile and maximum of angular errors.

    Parameters
    ----------
    errors_deg : ndarray of any shape
        Angular errors in degrees (NaN entries are ignored).

    Returns
    -------
    dict
        ``{"mean", "median", "p90", "max"}`` as Python floats (NaN when there are no errors).
    """
    e = np.asarray(errors_deg, dtype=np.float64).ravel()
    e = e[np.isfinite(e)]
    if e.size == 0:
        nan = float("nan")
        return {"mean": nan, "median": nan, "p90": nan, "max": nan}
    return {
        "mean": float(e.mean()),
        "median": float(np.median(e)),
        "p90": float(np.percentile(e, 90)),
        "max": float(e.max()),
    }


def depth_error(depth: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """RMS difference between two depth maps, each 4-connected component up to its offset.

    Integrated depth is known only up to one offset per component
    (:mod:`ps_lab.reconstruct.integrate`), so each component of the pixels where both are finite is compared after removing its mean
    difference.

    Parameters
    ----------
    depth, truth : ndarray of shape (H, W)
        Depth maps in the same unit, NaN where there is none.

    Returns
    -------
    dict
        ``rmse`` (same unit), ``range`` (of ``truth`` over the compared pixels), ``relative``
        (``rmse / range``) and ``pixels``.
    """
    both = np.isfinite(depth) & np.isfinite(truth)
    labels, count = ndi.label(both)
    difference = (np.asarray(depth, np.float64) - truth)[both]
    component = labels[both]
    offsets = ndi.mean(difference, component, np.arange(1, count + 1))
    residual = difference - np.concatenate([[0.0], np.atleast_1d(offsets)])[component]
    rmse = float(np.sqrt(np.mean(residual**2))) if residual.size else float("nan")
    spread = float(np.ptp(truth[both])) if residual.size else float("nan")
    return {
        "rmse": rmse,
        "range": spread,
        "relative": rmse / spread if spread > 0 else float("nan"),
        "pixels": int(both.sum()),
    }
