"""Light directions from highlight positions on a mirror sphere.

Frame (DiLiGenT, camera frame): x right, y up, z toward the camera. Image rows run down, so a
pixel ``(x, y)`` of a sphere with circle ``(cx, cy, r)`` has, orthographically, the normal

    n = ((x − cx) / r,  −(y − cy) / r,  sqrt(1 − nx² − ny²))

and with the view vector v = (0, 0, 1) (surface toward camera) the mirror law gives the direction
from the surface toward the light

    l = 2 (n · v) n − v = (2 nz nx,  2 nz ny,  2 nz² − 1).

With a focal length (in pixels: focal length / pixel pitch) the camera is a pinhole at the origin
looking down −z: the sphere centre lies on the ray through the circle centre at the distance where
its angular radius is ``atan(r / f)``; the highlight pixel's ray hits the sphere at P, n = P − C
(unit sphere) and v = −(ray direction), then the same mirror law applies.
"""

from __future__ import annotations

import numpy as np

from ps_lab.calibration._circle import Circle


def light_directions_from_highlights(
    highlights: np.ndarray,
    circle: Circle,
    *,
    focal_length_px: float | None = None,
    principal_point: tuple[float, float] | None = None,
) -> np.ndarray:
    """Mirror-reflect the view vector at each highlight.

    Parameters
    ----------
    highlights : ndarray of shape (n, 2)
        Highlight positions ``(x, y)`` in pixels.
    circle : Circle
        The chrome sphere's outline.
    focal_length_px : float, optional
        Focal length divided by the pixel pitch (of the loaded image). None: orthographic.
    principal_point : (float, float), optional
        ``(x, y)`` of the optical axis in pixels; required with ``focal_length_px``.

    Returns
    -------
    ndarray of shape (n, 3)
        Unit light directions (surface toward light), camera frame x right, y up, z toward camera.

    """
    hl = np.asarray(highlights, dtype=np.float64).reshape(-1, 2)
    cx, cy, r = circle
    if focal_length_px is None:
        nx = (hl[:, 0] - cx) / r
        ny = -(hl[:, 1] - cy) / r
        # A highlight measured just outside the outline is put on it (grazing normal).
        rho = np.hypot(nx, ny)
        shrink = np.where(rho > 1.0, 1.0 / np.maximum(rho, 1.0), 1.0)
        nx, ny = nx * shrink, ny * shrink
        nz = np.sqrt(np.clip(1.0 - nx * nx - ny * ny, 0.0, 1.0))
        normals = np.column_stack([nx, ny, nz])
        view = np.broadcast_to([0.0, 0.0, 1.0], normals.shape)
    else:
        if principal_point is None:
            raise ValueError("principal_point is required with focal_length_px")
        f = float(focal_length_px)
        px, py = principal_point

        def ray(x: np.ndarray, y: np.ndarray) -> np.ndarray:
            d = np.column_stack([x - px, -(y - py), np.full(np.shape(x), -f)])
            return d / np.linalg.norm(d, axis=1, keepdims=True)

        # Unit sphere at distance D on the ray through the circle centre (angular radius atan(r/f)).
        # Written with the perpendicular offset of the centre from each ray, which stays accurate
        # for long focal lengths (no difference of two ~D-sized numbers).
        distance = 1.0 / np.sin(np.arctan(r / f))
        c_hat = ray(np.array([cx]), np.array([cy]))[0]
        d = ray(hl[:, 0], hl[:, 1])
        along = d @ c_hat
        perp = distance * (c_hat[None, :] - along[:, None] * d)  # centre minus its foot on the ray
        s = np.sqrt(np.clip(1.0 - np.sum(perp * perp, axis=1), 0.0, None))
        normals = -perp - s[:, None] * d
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        view = -d
    ndotv = np.sum(normals * view, axis=1, keepdims=True)
    lights = 2.0 * ndotv * normals - view
    return lights / np.linalg.norm(lights, axis=1, keepdims=True)


def highlights_from_light_directions(light_directions: np.ndarray, circle: Circle) -> np.ndarray:
    """Inverse of the orthographic mirror law: where each light's highlight appears.

    Parameters
    ----------
    light_directions : ndarray of shape (n, 3)
        Unit directions toward the lights.
    circle : Circle
        The sphere's outline.

    Returns
    -------
    ndarray of shape (n, 2)
        ``(x, y)`` pixel positions of the mirror points (the half-vector of l and v).

    """
    lights = np.asarray(light_directions, dtype=np.float64).reshape(-1, 3)
    lights = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    half = lights + np.array([0.0, 0.0, 1.0])
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    cx, cy, r = circle
    return np.column_stack([cx + r * half[:, 0], cy - r * half[:, 1]])
