"""Analytic depth maps (orthographic or perspective) and their exact normals: integration tests.

Depth is the distance along the viewing axis, away from the camera; normals are in the camera frame
(x right, y up, z toward the camera), the row index growing downward.
"""

from __future__ import annotations

import numpy as np


def normals_from_depth(depth, d_col, d_row, focal_length=None, principal_point=None):
    """Exact normals (x right, y up, z toward the camera) of a depth map with known gradient.

    Parameters
    ----------
    depth, d_col, d_row : ndarray of shape (H, W)
        Depth (away from the camera) and its derivatives along columns and rows.
    focal_length : float, optional
        Perspective camera focal length in pixels; default orthographic.
    principal_point : (x, y), optional
        Default the image centre.

    Returns
    -------
    ndarray of shape (H, W, 3)
        Unit normals facing the camera.
    """
    if focal_length is None:
        n = np.stack([d_col, -d_row, np.ones_like(depth)], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)
    h, w = depth.shape
    cx, cy = principal_point if principal_point is not None else ((w - 1) / 2, (h - 1) / 2)
    u = np.arange(w)[None, :] - cx + np.zeros((h, 1))
    v = np.arange(h)[:, None] - cy + np.zeros((1, w))
    f = focal_length
    ray = np.stack([u, -v, -f * np.ones_like(u)], axis=-1) / f  # P = depth * ray
    p_col = d_col[..., None] * ray + depth[..., None] * np.array([1.0 / f, 0, 0])
    p_row = d_row[..., None] * ray + depth[..., None] * np.array([0, -1.0 / f, 0])
    n = np.cross(p_col, p_row)
    facing = np.sum(n * ray, axis=-1) < 0
    n = np.where(facing[..., None], n, -n)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def sphere_cap(shape, radius, max_slope_deg=60.0, offset=0.0):
    """A sphere seen from above, cut where its slope reaches ``max_slope_deg``.

    Returns depth (NaN outside), d_col, d_row, mask.
    """
    h, w = shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    du = cols - (w - 1) / 2
    dv = rows - (h - 1) / 2
    r2 = du**2 + dv**2
    mask = r2 < (radius * np.sin(np.radians(max_slope_deg))) ** 2
    z = np.sqrt(np.clip(radius**2 - r2, 1e-12, None))
    depth = offset - z
    return np.where(mask, depth, np.nan), du / z, dv / z, mask


def bumps(shape, seed=0, count=6, amplitude=0.12, offset=0.0):
    """Gaussian bumps and dents on a tilted plane, over a disc with a hole plus a separate blob.

    ``amplitude`` is the bump height as a share of the shorter side. Returns depth (NaN outside),
    d_col, d_row, mask (two 4-connected components).
    """
    h, w = shape
    s = min(h, w)
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    depth = 0.05 * cols - 0.03 * rows + offset
    d_col = np.full(shape, 0.05)
    d_row = np.full(shape, -0.03)
    for _ in range(count):
        cu, cv = rng.uniform(0.2, 0.8, 2) * (w, h)
        sigma = rng.uniform(0.05, 0.1) * s
        amp = rng.choice([-1, 1]) * rng.uniform(0.5, 1.0) * amplitude * s
        g = amp * np.exp(-((cols - cu) ** 2 + (rows - cv) ** 2) / (2 * sigma**2))
        depth += g
        d_col += -g * (cols - cu) / sigma**2
        d_row += -g * (rows - cv) / sigma**2
    cu, cv = 0.42 * w, 0.5 * h
    rr = np.hypot(cols - cu, rows - cv)
    mask = (rr < 0.38 * s) & (np.hypot(cols - cu - 0.1 * s, rows - cv) > 0.08 * s)
    mask |= np.hypot(cols - 0.9 * w, rows - 0.15 * h) < 0.07 * s
    return np.where(mask, depth, np.nan), d_col, d_row, mask


def _taper(rows, h):
    """``b(row) = sin^2`` from 0 to 1 and back over the middle 70 % of the rows; and db/drow."""
    y = np.clip((rows - 0.15 * h) / (0.7 * h), 0, 1)
    b = np.sin(np.pi * y) ** 2
    db = 2 * np.sin(np.pi * y) * np.cos(np.pi * y) * np.pi / (0.7 * h) * ((y > 0) & (y < 1))
    return b, db


def ledge(shape, height=None, offset=0.0):
    """A ramp that rises toward a cliff above a flat floor (an occluding edge with a step).

    Left of the edge column the surface rises quadratically (toward the camera) to the cliff's lip;
    right of it lies the flat floor. The lip height ``height * b(row)`` tapers to zero at the top
    and bottom of the ramp's extent, so paths around the cliff determine its height from the
    normals. Returns depth, d_col, d_row, mask, edge column (the step lies between columns
    ``edge - 1`` and ``edge``) and the rows where the step exceeds one pixel.
    """
    h, w = shape
    height = 0.15 * w if height is None else height
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    edge = w // 2 + 8
    start = w // 6
    x = np.clip((cols - start) / (edge - start), 0, None)
    q = np.where(cols < edge, x * x, 0.0)
    dq = np.where(cols < edge, 2 * x / (edge - start), 0.0) * (cols >= start)
    b, db = _taper(rows, h)
    depth = offset - height * b * q
    d_col = -height * b * dq
    d_row = -height * db * q
    mask = np.ones(shape, dtype=bool)
    step_rows = np.flatnonzero(height * b[:, 0] > 1.0)
    return depth, d_col, d_row, mask, edge, step_rows


def occluding_step(shape, height=None, max_slope_deg=80.0, offset=0.0):
    """A wave-shaped ledge: a quarter-cylinder that steepens to an occluding edge above a floor.

    Left of the edge column the surface rises (toward the camera) along a quarter circle until its
    slope reaches ``max_slope_deg`` at the last pixel before the edge; right of it lies the flat
    floor, so the depth steps there (an occluding edge, as at a limb). The rise is scaled by
    ``b(row)``, which tapers to zero at the top and bottom of the wave, so paths around the ends
    determine the step from the normals. Returns depth, d_col, d_row, mask, edge column (the step
    lies between columns ``edge - 1`` and ``edge``) and the rows where the step exceeds one pixel.
    """
    h, w = shape
    height = 0.2 * w if height is None else height
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    edge = w // 2 + 8
    start = w // 6
    # Quarter circle z = H (1 - sqrt(1 - x^2)), x in [0, x_max], slope H x / sqrt(1 - x^2) / L.
    length = edge - 1 - start
    t = np.tan(np.radians(max_slope_deg))
    # Slope at the last pixel (x = x_max) for the largest b (= 1): H x / (L sqrt(1 - x^2)) = t.
    x_max = 1.0 / np.sqrt(1.0 + (height / (t * length)) ** 2)
    x = np.clip((cols - start) / length, 0, None) * x_max
    on = (cols >= start) & (cols < edge)
    root = np.sqrt(np.clip(1 - x**2, 1e-12, None))
    q = np.where(cols < edge, np.where(on, 1 - root, 0.0), 0.0)
    dq = np.where(on, x / root * x_max / length, 0.0)
    b, db = _taper(rows, h)
    depth = offset - height * b * q
    d_col = -height * b * dq
    d_row = -height * db * q
    mask = np.ones(shape, dtype=bool)
    step_rows = np.flatnonzero(height * b[:, 0] * q[0].max() > 1.0)
    return depth, d_col, d_row, mask, edge, step_rows
