"""Pixel geometry shared by the rig file, the run format, calibration, the renderer and the solvers.

One :class:`Circle`; the scene frame of near lights (:func:`frame_origin`, :func:`scene_points`)
and the light vectors of LEDs at a finite distance (:func:`near_light_vectors`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Circle(NamedTuple):
    """A circle in loaded-image pixels: x = column, y = row, origin at the top-left pixel centre."""

    x: float
    y: float
    radius: float

    @property
    def center(self) -> tuple[float, float]:
        """``(x, y)``, as rig files write it."""
        return (self.x, self.y)


# --- the scene frame and lights at a finite distance ---------------------------------------------
#
# Scene frame (pixel units): x right, y up, z toward the camera (the camera frame of the light
# directions), with its origin at the image centre ((W - 1) / 2, (H - 1) / 2) lying in the spheres'
# plane, the plane through the chrome spheres' centres (z = 0). The orthographic camera cannot see
# depth, so that plane is the reference every height and light position is measured from.


def frame_origin(shape: tuple[int, int]) -> tuple[float, float]:
    """Pixel ``(x, y)`` (column, row) of the scene frame's origin: the image centre.

    Parameters
    ----------
    shape : (H, W)
        Image size.

    Returns
    -------
    (float, float)
    """
    h, w = shape
    return (w - 1) / 2.0, (h - 1) / 2.0


class Camera(NamedTuple):
    """A perspective camera for near lights: focal length and principal point, in pixels.

    In the scene frame (units: pixels *at the spheres' plane*, where the magnification is 1) the
    camera's centre is ``(cx - ox, oy - cy, f)``, ``f`` above the plane, with ``(ox, oy)`` the
    frame origin (:func:`frame_origin`): pixel (row, col) sees the ray from the centre through the
    plane point ``(col - ox, oy - row, 0)``.
    """

    focal_length: float
    principal_point: tuple[float, float]

    @classmethod
    def from_intrinsics(cls, fx: float, fy: float, cx: float, cy: float) -> Camera:
        """The camera of a calibrated camera matrix (``camera.json``), on undistorted frames.

        The scene frame has square pixels, so one focal length stands for both: the geometric
        mean of ``fx`` and ``fy`` (they differ by the pixels' aspect ratio, ~1e-3 on a sensor
        with square pixels).
        """
        return cls(float(np.sqrt(fx * fy)), (float(cx), float(cy)))

    def centre(self, shape: tuple[int, int]) -> np.ndarray:
        """(3,) the camera's centre in the scene frame."""
        ox, oy = frame_origin(shape)
        cx, cy = self.principal_point
        return np.array([cx - ox, oy - cy, self.focal_length])


def scene_points(
    shape: tuple[int, int],
    rows: np.ndarray,
    cols: np.ndarray,
    heights: np.ndarray,
    camera: Camera | None = None,
) -> np.ndarray:
    """Scene-frame points of pixels at given heights above the spheres' plane.

    Parameters
    ----------
    shape : (H, W)
        Image size.
    rows, cols : ndarray of shape (m,)
        Pixel rows and columns (may be fractional).
    heights : ndarray of shape (m,) or float
        z of each point (pixel units).
    camera : Camera, optional
        Perspective: each point lies on its pixel's ray. Default orthographic.

    Returns
    -------
    ndarray of shape (m, 3)
        Orthographic ``(col - (W-1)/2, (H-1)/2 - row, z)``; perspective
        ``(cx - ox + (col - cx) s, oy - cy + (cy - row) s, z)`` with ``s = (f - z) / f``.
    """
    ox, oy = frame_origin(shape)
    cols = np.asarray(cols, dtype=np.float64)
    rows = np.asarray(rows, dtype=np.float64)
    z = np.broadcast_to(np.asarray(heights, dtype=np.float64), cols.shape)
    if camera is None:
        return np.column_stack([cols - ox, oy - rows, z])
    f = float(camera.focal_length)
    cx, cy = camera.principal_point
    s = (f - z) / f
    return np.column_stack([cx - ox + (cols - cx) * s, oy - cy + (cy - rows) * s, z])


def near_light_vectors(
    points: np.ndarray,
    light_positions: np.ndarray,
    light_directions: np.ndarray,
    light_intensities: np.ndarray | None = None,
    *,
    anisotropy: float | np.ndarray | None = None,
    axes: np.ndarray | None = None,
) -> np.ndarray:
    """Per-point light vectors of LEDs at a finite distance (direction times relative irradiance).

    Light ``j`` at ``P_j`` gives the surface point ``X`` the vector

        L_j(X) = e_j u_j(X) (|P_j - O| / |P_j - X|)^2 (c_j(X) / c_j(O))^mu_j

    with ``u_j(X) = (P_j - X) / |P_j - X|``, ``O`` the scene origin, ``c_j(X)`` the cosine between
    the LED's axis (``axes``, default: it points at ``O``) and the ray from the LED to ``X`` (radiance ∝ cos^mu of
    that angle; ``mu_j = 0``: isotropic), and ``e_j`` the light's intensity *at the origin* — the
    intensity of the directional model, so ``light_intensities.txt`` keeps its meaning. A light
    whose position is NaN (too far to triangulate) is directional: ``L_j = e_j d_j``.

    Parameters
    ----------
    points : ndarray of shape (m, 3)
        Surface points (scene frame, pixel units).
    light_positions : ndarray of shape (n, 3)
        LED positions (scene frame); NaN rows for lights at infinity.
    light_directions : ndarray of shape (n, 3)
        Unit directions toward the lights from the origin (used for the NaN rows).
    light_intensities : ndarray of shape (n,), optional
        Intensity at the origin (default ones).
    anisotropy : float or ndarray of shape (n,), optional
        Exponent ``mu`` of each LED's emission (default 0).
    axes : ndarray of shape (n, 3), optional
        Unit optical axis of each LED (default: from the LED toward the origin).

    Returns
    -------
    ndarray of shape (m, n, 3), float64
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pos = np.asarray(light_positions, dtype=np.float64).reshape(-1, 3)
    n = pos.shape[0]
    e = (
        np.ones(n)
        if light_intensities is None
        else np.asarray(light_intensities, dtype=np.float64).reshape(n)
    )
    far = ~np.all(np.isfinite(pos), axis=1)
    pos = np.where(far[:, None], 1.0, pos)
    d = pos[None, :, :] - pts[:, None, :]  # (m, n, 3)
    dist2 = np.einsum("mnk,mnk->mn", d, d)
    dist = np.sqrt(dist2)
    ref2 = np.einsum("nk,nk->n", pos, pos)
    gain = e[None, :] * ref2[None, :] / (dist2 * dist)
    mu = np.broadcast_to(np.asarray(0.0 if anisotropy is None else anisotropy, float), (n,))
    if np.any(mu != 0):
        ref = np.sqrt(ref2)
        if axes is None:
            # cos of the angle between the axis (-P/|P|) and the ray P -> X: ((X - P) . (-P)) / ...
            cos = np.einsum("mnk,nk->mn", d, pos) / (dist * ref[None, :])
        else:  # (c(X) / c(O)): the ray P -> X against the axis, over the ray P -> O's
            a = np.asarray(axes, dtype=np.float64).reshape(n, 3)
            a = np.where(far[:, None], -pos, a)
            at_origin = np.clip(-np.einsum("nk,nk->n", a, pos) / ref, 1e-6, None)
            cos = -np.einsum("mnk,nk->mn", d, a) / (dist * at_origin[None, :])
        gain = gain * np.clip(cos, 0.0, None) ** mu[None, :]
    out = d * gain[:, :, None]
    if far.any():
        dirs = np.asarray(light_directions, dtype=np.float64).reshape(-1, 3)[far]
        out[:, far] = (e[far, None] * dirs / np.linalg.norm(dirs, axis=1, keepdims=True))[None]
    return out
