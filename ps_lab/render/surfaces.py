"""Height-field objects of the synthetic world: spheres and reliefs with ground-truth normals."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Surface:
    """A height-field object seen by the orthographic camera.

    Attributes
    ----------
    normals : ndarray of shape (H, W, 3)
        Unit normals inside ``mask`` (camera frame), zeros outside.
    mask : ndarray of shape (H, W), bool
        Pixels covered by the object.
    height : ndarray of shape (H, W)
        Surface height z in pixel units (used for ray-marched cast shadows), 0 outside.
    albedo : ndarray of shape (H, W) or (H, W, 3)
        Lambertian albedo (grey or per channel).
    """

    normals: np.ndarray
    mask: np.ndarray
    height: np.ndarray
    albedo: np.ndarray


def _pixel_grid(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    h, w = shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    return cols, rows


def _albedo_array(albedo: object, shape: tuple[int, int], mask: np.ndarray) -> np.ndarray:
    a = np.asarray(albedo, dtype=np.float64)
    h, w = shape
    if a.ndim == 0:
        out = np.full((h, w), float(a))
    elif a.shape == (3,):
        out = np.broadcast_to(a, (h, w, 3)).copy()
    elif a.shape in ((h, w), (h, w, 3)):
        out = a.copy()
    else:
        raise ValueError(f"albedo must be a scalar, (3,), {(h, w)} or {(h, w, 3)}; got {a.shape}")
    out[~mask] = 0.0
    return out


def _default_disc(
    shape: tuple[int, int], center: tuple[float, float] | None, radius: float | None
) -> tuple[tuple[float, float], float]:
    """Centre (default: image centre) and radius (default: 0.45 of the shorter side) of an object."""
    h, w = shape
    if center is None:
        center = ((w - 1) / 2.0, (h - 1) / 2.0)
    if radius is None:
        radius = 0.45 * min(h, w)
    if radius <= 0:
        raise ValueError(f"radius must be positive, got {radius}")
    return center, radius


def sphere_surface(
    shape: tuple[int, int],
    center: tuple[float, float] | None = None,
    radius: float | None = None,
    albedo: object = 1.0,
) -> Surface:
    """Build a sphere seen orthographically.

    Parameters
    ----------
    shape : (H, W)
        Image size.
    center : (x, y), optional
        Sphere centre in pixels (column, row); default the image centre.
    radius : float, optional
        Radius in pixels; default ``0.45 * min(H, W)``.
    albedo : float, (3,), (H, W) or (H, W, 3)
        Lambertian albedo.

    Returns
    -------
    Surface
        Height ``z = sqrt(r^2 - dx^2 - dy^2)`` and normals ``(dx, dy, z) / r``, ``dy`` pointing up.
    """
    center, radius = _default_disc(shape, center, radius)
    cols, rows = _pixel_grid(shape)
    dx = cols - center[0]
    dy = -(rows - center[1])
    d2 = dx * dx + dy * dy
    mask = d2 < radius * radius
    z = np.where(mask, np.sqrt(np.clip(radius * radius - d2, 0.0, None)), 0.0)
    normals = np.stack([dx, dy, z], axis=-1) / radius
    normals[~mask] = 0.0
    # Renormalise against rounding so normals are unit to machine precision.
    norm = np.linalg.norm(normals, axis=-1, keepdims=True)
    normals = np.divide(normals, norm, out=np.zeros_like(normals), where=norm > 0)
    return Surface(normals=normals, mask=mask, height=z, albedo=_albedo_array(albedo, shape, mask))


def _smooth_noise(shape: tuple[int, int], rng: np.random.Generator, scale: float) -> np.ndarray:
    """Smooth random field in [0, 1] with features of about ``scale`` pixels."""
    field = rng.standard_normal(shape)
    sigma = max(scale, 0.5)
    field = cv2.GaussianBlur(
        field, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT
    )
    lo, hi = field.min(), field.max()
    return (field - lo) / (hi - lo) if hi > lo else np.zeros(shape)


def relief_surface(
    shape: tuple[int, int],
    *,
    seed: int = 0,
    albedo: object = None,
    center: tuple[float, float] | None = None,
    radius: float | None = None,
) -> Surface:
    """Build a height-field object: a rounded dome carrying smooth bumps and ridges.

    The bumps are steep enough (slopes up to about 60-70 degrees) to cast visible shadows onto the
    dome under oblique light. The normals are the analytic normals of the very height field returned
    in ``height``, so shading and ray-marched shadows agree.

    Parameters
    ----------
    shape : (H, W)
        Image size.
    seed : int
        Seed of the bump layout and of the default albedo pattern.
    albedo : float, (3,), (H, W) or (H, W, 3), optional
        Lambertian albedo; default a smooth seeded pattern in [0.55, 1].
    center : (x, y), optional
        Centre of the object's bounding circle; default the image centre.
    radius : float, optional
        Radius of the bounding circle; default ``0.45 * min(H, W)``.

    Returns
    -------
    Surface
    """
    center, radius = _default_disc(shape, center, radius)
    rng = np.random.default_rng(seed)
    cols, rows = _pixel_grid(shape)
    # Work in units of the radius: u right, v up.
    u = (cols - center[0]) / radius
    v = -(rows - center[1]) / radius
    rho2 = u * u + v * v
    mask = rho2 < 1.0

    # Dome: an ellipsoid cap of height `dome` (in radius units) -> vertical tangent at the rim.
    dome = 0.35
    root = np.sqrt(np.clip(1.0 - rho2, 1e-12, None))
    height = dome * root
    gu = -dome * u / root
    gv = -dome * v / root

    # Bumps (isotropic) and ridges (elongated) of Gaussian profile, placed well inside the rim.
    n_bumps = 5
    n_ridges = 2
    for k in range(n_bumps + n_ridges):
        for _attempt in range(50):
            c = rng.uniform(-0.65, 0.65, size=2)
            if c @ c < 0.6**2:
                break
        amp = rng.uniform(0.18, 0.28)
        if k < n_bumps:
            s_major = s_minor = rng.uniform(0.07, 0.11)
        else:
            s_major = rng.uniform(0.25, 0.35)
            s_minor = rng.uniform(0.06, 0.09)
        theta = rng.uniform(0.0, np.pi)
        ct, st = np.cos(theta), np.sin(theta)
        du, dv = u - c[0], v - c[1]
        a = ct * du + st * dv  # along the ridge
        b = -st * du + ct * dv  # across
        g = amp * np.exp(-0.5 * ((a / s_major) ** 2 + (b / s_minor) ** 2))
        da = -a / s_major**2 * g
        db = -b / s_minor**2 * g
        height = height + g
        gu = gu + ct * da - st * db
        gv = gv + st * da + ct * db

    # Back to pixel units: height scales with the radius, gradients are dimensionless.
    height = np.where(mask, height * radius, 0.0)
    normals = np.stack([-gu, -gv, np.ones_like(gu)], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    normals[~mask] = 0.0
    if albedo is None:
        albedo = 0.55 + 0.45 * _smooth_noise(shape, rng, 0.12 * radius)
    return Surface(
        normals=normals, mask=mask, height=height, albedo=_albedo_array(albedo, shape, mask)
    )


