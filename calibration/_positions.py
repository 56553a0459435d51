"""LED positions from the highlights of two or more chrome spheres (orthographic camera).

Positions are in the scene frame of :mod:`ps_lab.geometry` (pixel units; x right, y up, z toward
the camera; origin at the image centre in the spheres' plane, the plane through the chrome spheres'
centres). With the view direction v = (0, 0, 1), the highlight at pixel (x, y) of a sphere with
circle (cx, cy, r) lies at the surface point S = C + r n, with

    n = ((x - cx) / r, -(y - cy) / r, sqrt(1 - nx² - ny²)),   C = (cx, cy, 0) in the scene frame,

and the light lies on the reflected ray S + t (2 (n·v) n - v), t > 0. Each light's position is the
least-squares intersection of its rays from all spheres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ps_lab.calibration._circle import Circle
from ps_lab.geometry import Camera, scene_points

_VIEW = np.array([0.0, 0.0, 1.0])
# Rays of one light closer than this to parallel cannot place it: it is too far for the baseline
# between the spheres (position error ~ direction error / angle between the rays).
MIN_RAY_ANGLE_DEG = 1.0


@dataclass(frozen=True)
class Triangulation:
    """LED positions from the rays of several chrome spheres (see :func:`triangulate_lights`).

    Attributes
    ----------
    origins, directions : ndarray of shape (s, n, 3)
        Each sphere's highlight points and unit reflected rays (scene frame).
    positions : ndarray of shape (n, 3)
        Least-squares intersections; NaN rows for lights whose rays are nearly parallel.
    miss : ndarray of shape (n,)
        RMS distance (pixels) of each position from its rays (NaN where not triangulated).
    spread_deg : ndarray of shape (n,)
        Largest angle between two of a light's rays.
    light_directions : ndarray of shape (n, 3)
        Unit directions from the scene origin toward each position; for lights too far to
        triangulate, the mean of their rays' directions.
    """

    origins: np.ndarray
    directions: np.ndarray
    positions: np.ndarray
    miss: np.ndarray
    spread_deg: np.ndarray
    light_directions: np.ndarray

    @property
    def too_far(self) -> np.ndarray:
        """(n,) bool: lights with no position (directional fall-back)."""
        return ~np.all(np.isfinite(self.positions), axis=1)


def reflected_rays(
    highlights: np.ndarray, circle: Circle, shape: tuple[int, int], camera: Camera | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Rays from a chrome sphere's highlight points toward the lights.

    Parameters
    ----------
    highlights : ndarray of shape (n, 2)
        Highlight ``(x, y)`` pixels.
    circle : Circle
        The sphere's outline; its centre lies in the spheres' plane.
    shape : (H, W)
        Image size (the frame's origin is the image centre).
    camera : Camera, optional
        Perspective (:class:`ps_lab.geometry.Camera`): the sphere's centre is where its circle
        centre's ray meets the spheres' plane, its radius the circle's (the magnification is 1
        there, to first order in the sphere's angular size), and each highlight is where its
        pixel's ray meets the sphere (the closest approach for a ray just past the limb); the
        view vector is that ray's, reversed.

    Returns
    -------
    origins : ndarray of shape (n, 3)
        The sphere surface points (scene frame).
    directions : ndarray of shape (n, 3)
        Unit mirror reflections of the view vector, ``2 (n.v) n - v``.
    """
    hl = np.asarray(highlights, dtype=np.float64).reshape(-1, 2)
    if camera is not None:
        return _perspective_rays(hl, circle, shape, camera)
    cx, cy, r = circle
    nx = (hl[:, 0] - cx) / r
    ny = -(hl[:, 1] - cy) / r
    # A highlight measured just outside the outline is put on it (grazing normal).
    shrink = 1.0 / np.maximum(np.hypot(nx, ny), 1.0)
    nx, ny = nx * shrink, ny * shrink
    nz = np.sqrt(np.clip(1.0 - nx * nx - ny * ny, 0.0, 1.0))
    normals = np.column_stack([nx, ny, nz])
    centre = scene_points(shape, [cy], [cx], 0.0)[0]
    directions = 2.0 * nz[:, None] * normals - _VIEW[None, :]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return centre[None, :] + r * normals, directions


def _perspective_rays(hl, circle, shape, camera):
    """:func:`reflected_rays` through a perspective camera."""
    cx, cy, r = circle
    centre = scene_points(shape, [cy], [cx], 0.0)[0]
    eye = camera.centre(shape)
    through = scene_points(shape, hl[:, 1], hl[:, 0], np.zeros(len(hl)))  # on the plane
    d = through - eye[None, :]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    offset = eye - centre
    b = d @ offset
    c = float(offset @ offset) - r * r
    t = -b - np.sqrt(np.clip(b * b - c, 0.0, None))
    surface = eye[None, :] + t[:, None] * d
    normals = surface - centre[None, :]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    view = -d
    directions = 2.0 * np.einsum("nk,nk->n", normals, view)[:, None] * normals - view
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return centre[None, :] + r * normals, directions


def ray_sigmas(highlights: np.ndarray, circle: Circle, uncertainty_px: np.ndarray | float = 1.0
               ) -> np.ndarray:
    """Angular standard deviation (radians) of each reflected ray from its highlight's.

    A highlight moved by ``u`` pixels turns the normal by ``u / r`` tangentially and by
    ``u / (r n_z)`` radially (the limb foreshortens), the reflected ray by twice that; the radial
    (larger) one is used. ``uncertainty_px`` is floored at 0.02 px (the sub-pixel sampling limit
    of a centroid), so no ray gets an unbounded weight.

    Parameters
    ----------
    highlights : ndarray of shape (n, 2)
    circle : Circle
    uncertainty_px : float or ndarray of shape (n,)

    Returns
    -------
    ndarray of shape (n,)
    """
    hl = np.asarray(highlights, dtype=np.float64).reshape(-1, 2)
    cx, cy, r = circle
    rho2 = ((hl[:, 0] - cx) ** 2 + (hl[:, 1] - cy) ** 2) / (r * r)
    nz = np.sqrt(np.clip(1.0 - rho2, 0.05, 1.0))
    u = np.maximum(np.broadcast_to(np.asarray(uncertainty_px, float), (len(hl),)), 0.02)
    return 2.0 * u / (r * nz)


def triangulate_lights(
    origins: np.ndarray,
    directions: np.ndarray,
    *,
    min_angle_deg: float | np.ndarray = MIN_RAY_ANGLE_DEG,
    sigmas: np.ndarray | None = None,
) -> Triangulation:
    """Least-squares intersection of each light's rays.

    The point minimising the weighted sum of squared distances to rays ``o_k + t d_k`` solves
    ``(sum_k w_k (I - d_k d_k^T)) P = sum_k w_k (I - d_k d_k^T) o_k``. With ``sigmas`` (each
    ray's angular standard deviation) the weights are ``w_k = 1 / (t_k sigma_k)^2``, ``t_k`` the
    distance from the ray's origin to the point: a ray's angular error moves it by ``t_k
    sigma_k`` at the light, so this is the maximum-likelihood point (two passes: the first,
    unweighted, gives the distances). A sphere near an LED sees it under a larger angle between
    the rays of other spheres but with no better angular precision; the far sphere's ray is the
    less certain one at the light.

    Parameters
    ----------
    origins, directions : ndarray of shape (s, n, 3)
        Ray origins and unit directions from s >= 2 spheres for n lights.
    min_angle_deg : float or ndarray of shape (n,)
        A light whose rays all lie within this angle of each other is too far to place: its
        position is NaN and its direction the mean of its rays.
    sigmas : ndarray of shape (s, n), optional
        Angular standard deviation of each ray (radians; :func:`ray_sigmas`). None: equal
        weights.

    Returns
    -------
    Triangulation
    """
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if o.ndim != 3 or o.shape[0] < 2 or o.shape != d.shape or o.shape[2] != 3:
        raise ValueError(f"need rays of shape (s >= 2, n, 3), got {o.shape} and {d.shape}")
    n = o.shape[1]
    projector = np.eye(3) - d[..., :, None] * d[..., None, :]  # (s, n, 3, 3)
    cosines = np.clip(np.einsum("snk,tnk->nst", d, d), -1.0, 1.0)
    spread = np.degrees(np.arccos(cosines.min(axis=(1, 2))))
    ok = spread >= min_angle_deg
    positions = np.full((n, 3), np.nan)
    weights = np.ones(o.shape[:2])
    for _ in range(1 if sigmas is None else 2):
        system = np.einsum("sn,snij->nij", weights, projector)
        target = np.einsum("sn,snij,snj->ni", weights, projector, o)
        if ok.any():
            positions[ok] = np.linalg.solve(system[ok], target[ok][..., None])[..., 0]
        if sigmas is not None:
            reach = np.linalg.norm(np.where(ok[None, :, None], positions[None] - o, 1.0), axis=2)
            weights = 1.0 / (reach * np.asarray(sigmas, np.float64)) ** 2
            weights /= weights.mean(axis=0, keepdims=True)
    offset = positions[None] - o
    along = np.einsum("snk,snk->sn", offset, d)
    perp = offset - along[..., None] * d
    miss = np.sqrt(np.mean(np.einsum("snk,snk->sn", perp, perp), axis=0))
    light_directions = d.mean(axis=0)
    light_directions[ok] = positions[ok]
    light_directions /= np.linalg.norm(light_directions, axis=1, keepdims=True)
    return Triangulation(o, d, positions, miss, spread, light_directions)
