"""LEDs at a finite distance: shading with fall-off and anisotropy, cast shadows, chrome highlights.

Positions live in the scene frame of :mod:`ps_lab.geometry` (pixel units; x right, y up, z toward
the camera; origin at the image centre in the spheres' plane, the plane through the chrome spheres'
centres). A surface's ``height`` plus ``z_offset`` is its z in that frame; the chrome spheres'
centres lie in the plane (z = 0). A light's intensity is its intensity *at the origin*, as in
:func:`ps_lab.geometry.near_light_vectors`. See ``docs/renderer.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ps_lab.geometry import frame_origin, near_light_vectors, scene_points
from ps_lab.render.light_sets import random_light_directions
from ps_lab.render.shading import (
    _SHADOW_BIAS,
    _VIEW,
    _chrome_coverage,
    _cook_torrance,
    _highlight_grid,
)
from ps_lab.render.surfaces import Surface

__all__ = [
    "PointLights",
    "dome_light_positions",
    "mirror_normal",
    "render_chrome_near",
    "render_near",
]


def dome_light_positions(
    n: int, radius: float, rng: np.random.Generator, *, max_zenith_deg: float = 55.0
) -> np.ndarray:
    """LED positions on a dome of ``radius`` around the scene origin, uniform over the cap.

    Returns
    -------
    ndarray of shape (n, 3)
        Scene-frame positions (pixel units).
    """
    return radius * random_light_directions(n, rng, max_zenith_deg=max_zenith_deg)


@njit(cache=True, nogil=True)
def _march_point_lights(height, mask, lit, light_cols, light_rows, light_z, bias, top, shadow):
    """``shadow[i, r, c]``: a bilinear height sample lies above the ray from (r, c) to light i.

    The ray advances one pixel per step in the image toward the light's foot point and rises
    linearly to the light's height; samples with an off-object neighbour block nothing (as in the
    directional march of :func:`ps_lab.render.shading._cast_shadow`).
    """
    h, w = height.shape
    for i in range(light_cols.shape[0]):
        for r in range(h):
            for c in range(w):
                if not lit[i, r, c]:
                    continue
                dc = light_cols[i] - c
                dr = light_rows[i] - r
                length = np.sqrt(dc * dc + dr * dr)
                if length < 1e-9:
                    continue
                z0 = height[r, c] + bias
                rise = (light_z[i] - height[r, c]) / length
                t = 1.0
                while t < length:
                    ray = z0 + t * rise
                    if ray > top:
                        break
                    x = c + t * dc / length
                    y = r + t * dr / length
                    x0 = int(np.floor(x))
                    y0 = int(np.floor(y))
                    if x0 < 0 or y0 < 0 or x0 >= w - 1 or y0 >= h - 1:
                        break
                    on_object = mask[y0, x0] and mask[y0, x0 + 1]
                    if on_object and mask[y0 + 1, x0] and mask[y0 + 1, x0 + 1]:
                        fx = x - x0
                        fy = y - y0
                        h00 = height[y0, x0]
                        h01 = height[y0, x0 + 1]
                        h10 = height[y0 + 1, x0]
                        h11 = height[y0 + 1, x0 + 1]
                        value = h00 + fx * (h01 - h00)
                        value += fy * ((h10 - h00) + fx * (h11 - h10 - h01 + h00))
                        if value > ray:
                            shadow[i, r, c] = True
                            break
                    t += 1.0


def render_near(
    surface: Surface,
    light_positions: np.ndarray,
    light_intensities: np.ndarray | None = None,
    *,
    z_offset: float = 0.0,
    anisotropy: float | np.ndarray | None = None,
    axes: np.ndarray | None = None,
    cast_shadows: bool = True,
    specular: float = 0.0,
    roughness: float = 0.3,
) -> np.ndarray:
    """Render one image per LED at a finite distance.

    Each lit point ``X`` receives ``L_j(X)`` of :func:`ps_lab.geometry.near_light_vectors`
    (direction toward the LED, ``1/d²`` fall-off, ``cos^mu`` emission), and reflects
    ``|L_j| (albedo max(n.u_j, 0) + specular D F G / (4 n.v) / F0)`` as :func:`ps_lab.render.render`
    does for a directional light ``u_j``; cast shadows are marched toward the LED itself.

    Parameters
    ----------
    surface : Surface
        The object; ``surface.height + z_offset`` is each pixel's z in the scene frame.
    light_positions : ndarray of shape (n, 3)
        LED positions (scene frame, pixel units).
    light_intensities : ndarray of shape (n,), (n, 1) or (n, 3), optional
        Intensity of each LED at the scene origin (grey or per channel); default ones.
    z_offset : float
        Height of the surface's ``height = 0`` above the spheres' plane.
    anisotropy : float or ndarray of shape (n,), optional
        Exponent ``mu`` of the LEDs' ``cos^mu`` emission about their axes.
    axes : ndarray of shape (n, 3), optional
        Each LED's unit optical axis (default: pointing at the origin).
    cast_shadows, specular, roughness
        As for :func:`ps_lab.render.render`.

    Returns
    -------
    ndarray of shape (n, H, W), or (n, H, W, 3) when albedo or intensities are per channel
    """
    pos = np.asarray(light_positions, dtype=np.float64).reshape(-1, 3)
    n = pos.shape[0]
    if not np.all(np.isfinite(pos)):
        raise ValueError("light_positions must be finite")
    intensities = (
        np.ones((n, 1))
        if light_intensities is None
        else np.asarray(light_intensities, dtype=np.float64).reshape(n, -1)
    )
    albedo = np.asarray(surface.albedo, dtype=np.float64)
    colour = albedo.ndim == 3 or intensities.shape[1] == 3
    h, w = surface.mask.shape
    rows, cols = np.nonzero(surface.mask)
    normals = surface.normals[rows, cols]
    albedo_p = albedo[rows, cols].reshape(rows.size, -1)
    points = scene_points((h, w), rows, cols, surface.height[rows, cols] + z_offset)
    vectors = near_light_vectors(points, pos, pos, anisotropy=anisotropy, axes=axes)  # (m, n, 3)
    irradiance = np.linalg.norm(vectors, axis=2)
    unit = vectors / np.maximum(irradiance, 1e-300)[:, :, None]
    n_dot_l = np.einsum("mk,mnk->mn", normals, unit)
    lit = n_dot_l > 0
    if cast_shadows and rows.size:
        ox, oy = frame_origin((h, w))
        lit_map = np.zeros((n, h, w), dtype=bool)
        lit_map[:, rows, cols] = lit.T
        shadow = np.zeros((n, h, w), dtype=bool)
        height = np.where(surface.mask, surface.height, 0.0).astype(np.float64)
        _march_point_lights(
            height, surface.mask, lit_map, pos[:, 0] + ox, oy - pos[:, 1], pos[:, 2] - z_offset,
            _SHADOW_BIAS, float(height.max()), shadow,
        )
        lit &= ~shadow[:, rows, cols].T
    shading = np.where(lit, n_dot_l, 0.0)  # (m, n)
    radiance = shading[:, :, None] * albedo_p[:, None, :]
    if specular > 0:
        lobe = np.stack(
            [_cook_torrance(normals, unit[:, j], n_dot_l[:, j], roughness) for j in range(n)],
            axis=1,
        )
        radiance = radiance + (specular * np.where(lit, lobe, 0.0))[:, :, None]
    radiance = radiance * irradiance[:, :, None] * intensities[None, :, :]
    out = np.zeros((n, h, w, radiance.shape[2]))
    out[:, rows, cols] = radiance.transpose(1, 0, 2)
    return out if colour else out[..., 0]


def mirror_normal(
    sphere_center: np.ndarray, radius: float, light_position: np.ndarray, *, iterations: int = 60
) -> np.ndarray:
    """Unit normal of the chrome-sphere point that reflects the view ray toward a point light.

    Fixed point of ``n = bisector(v, (P - C - r n)/|P - C - r n|)`` (a contraction with ratio
    about ``r / |P - C|``), started from the direction of the light seen from the centre.

    Parameters
    ----------
    sphere_center : ndarray of shape (3,)
        Scene-frame centre.
    radius : float
        Sphere radius (pixels).
    light_position : ndarray of shape (3,)
        Scene-frame LED position.
    iterations : int
        At most this many fixed-point steps.

    Returns
    -------
    ndarray of shape (3,)
    """
    c = np.asarray(sphere_center, dtype=np.float64)
    p = np.asarray(light_position, dtype=np.float64)
    normal = np.zeros(3)
    toward = (p - c) / np.linalg.norm(p - c)
    for _ in range(iterations):
        new = toward + _VIEW
        new = new / np.linalg.norm(new)
        if np.max(np.abs(new - normal)) < 1e-15:
            break
        normal = new
        toward = p - (c + radius * normal)
        toward = toward / np.linalg.norm(toward)
    return normal


def render_chrome_near(
    shape: tuple[int, int],
    center: tuple[float, float],
    radius: float,
    light_positions: np.ndarray,
    *,
    light_radius: float = 15.0,
    light_radiance: float = 50.0,
    ambient: float = 0.02,
    supersample: int = 4,
) -> np.ndarray:
    """A mirror sphere (centre in the spheres' plane) under small disc LEDs at a finite distance.

    As :func:`ps_lab.render.render_chrome_sphere`, with each sub-sample's reflected view ray
    compared with the direction from *its own* surface point to the LED, whose disc of radius
    ``light_radius`` (pixel units) subtends ``atan(light_radius / distance)``.

    Parameters
    ----------
    shape : (H, W)
        Image size.
    center : (x, y)
        Circle centre in pixels (column, row).
    radius : float
        Sphere radius in pixels.
    light_positions : ndarray of shape (n, 3)
        Scene-frame LED positions.
    light_radius, light_radiance, ambient, supersample
        LED disc radius (pixel units), its radiance, the sphere's ambient level, outline grid.

    Returns
    -------
    ndarray of shape (n, H, W)
    """
    h, w = shape
    pos = np.asarray(light_positions, dtype=np.float64).reshape(-1, 3)
    out = np.zeros((pos.shape[0], h, w))
    geometry = _chrome_coverage(
        (int(h), int(w)), (float(center[0]), float(center[1])), float(radius), int(supersample)
    )
    if geometry is None:
        return out
    box, coverage = geometry
    out[:, box[0], box[1]] = ambient * coverage
    centre3 = scene_points((h, w), [center[1]], [center[0]], 0.0)[0]
    for i, p in enumerate(pos):
        normal = mirror_normal(centre3, radius, p)
        if normal[2] <= 1e-6:
            continue
        disc = float(np.arctan(light_radius / np.linalg.norm(p - (centre3 + radius * normal))))
        grid = _highlight_grid(shape, center, radius, normal, disc, supersample)
        if grid is None:
            continue
        dx, dy, nz = grid.normals
        # reflected view ray r = 2 nz n - v against the unit vector from the sample to the LED
        sx = p[0] - (centre3[0] + radius * dx)
        sy = p[1] - (centre3[1] + radius * dy)
        sz = p[2] - (centre3[2] + radius * nz)
        length = np.sqrt(sx * sx + sy * sy + sz * sz)
        cos_angle = (2 * nz * (dx * sx + dy * sy + nz * sz) - sz) / length
        values = grid.pixel_share(np.arccos(np.clip(cos_angle, -1.0, 1.0)), disc)
        out[i, grid.box[0], grid.box[1]] += light_radiance * values
    return out


@dataclass(frozen=True)
class PointLights:
    """LEDs at a finite distance for :func:`ps_lab.render.render_scene`.

    Attributes
    ----------
    positions : ndarray of shape (k, 3)
        Scene-frame positions (pixel units) of the lit LEDs.
    anisotropy : float or ndarray of shape (k,)
        Exponent ``mu`` of their ``cos^mu`` emission.
    radius : float
        Radius of each LED's emitting disc (pixel units), seen in the chrome spheres.
    axes : ndarray of shape (k, 3) or None
        Each LED's optical axis (None: aimed at the scene origin).
    """

    positions: np.ndarray
    anisotropy: float | np.ndarray = 0.0
    radius: float = 15.0
    axes: np.ndarray | None = None

    def select(self, rows: np.ndarray) -> PointLights:
        """The LEDs ``rows`` (0-based) only."""
        mu = self.anisotropy
        return PointLights(
            np.asarray(self.positions, dtype=np.float64)[rows].reshape(-1, 3),
            mu if np.ndim(mu) == 0 else np.asarray(mu, dtype=np.float64)[rows].reshape(-1),
            self.radius,
            None if self.axes is None else np.asarray(self.axes, np.float64)[rows].reshape(-1, 3),
        )
