"""Light directions of the synthetic world: random sets within a cone, and perturbed copies.

Directions are unit vectors in the camera frame (x right, y up, z toward the camera), pointing from
the surface toward the light (see ``docs/renderer.md``).
"""

from __future__ import annotations

import numpy as np


def random_light_directions(
    n: int, rng: np.random.Generator, *, max_zenith_deg: float = 60.0
) -> np.ndarray:
    """Draw light directions uniformly over the spherical cap around the viewing direction.

    Parameters
    ----------
    n : int
        Number of lights.
    rng : numpy.random.Generator
        Source of randomness.
    max_zenith_deg : float
        Largest angle between a light and the camera axis (+z), in degrees.

    Returns
    -------
    ndarray of shape (n, 3)
        Unit vectors with ``z >= cos(max_zenith_deg) > 0``.
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    if not 0.0 < max_zenith_deg < 90.0:
        raise ValueError(f"max_zenith_deg must be in (0, 90), got {max_zenith_deg}")
    cos_max = np.cos(np.deg2rad(max_zenith_deg))
    # Uniform on the cap: z uniform in [cos_max, 1], azimuth uniform.
    z = rng.uniform(cos_max, 1.0, size=n)
    phi = rng.uniform(0.0, 2.0 * np.pi, size=n)
    s = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


def perturb_light_directions(
    light_directions: np.ndarray, angle_deg: float, rng: np.random.Generator
) -> np.ndarray:
    """Turn every light by exactly ``angle_deg`` about a random axis perpendicular to it.

    Parameters
    ----------
    light_directions : ndarray of shape (n, 3)
        Unit light directions.
    angle_deg : float
        Angle between each light and its perturbed copy.
    rng : numpy.random.Generator
        Source of the random directions of the turn.

    Returns
    -------
    ndarray of shape (n, 3)
        Unit vectors at ``angle_deg`` from the input, in uniformly random directions.
    """
    lights = np.asarray(light_directions, dtype=np.float64)
    lights = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    tangent = rng.standard_normal(lights.shape)
    tangent -= np.sum(tangent * lights, axis=1, keepdims=True) * lights
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    a = np.radians(angle_deg)
    return np.cos(a) * lights + np.sin(a) * tangent
