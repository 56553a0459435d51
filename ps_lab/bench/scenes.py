"""The rendered scenes of the paper experiments: surfaces, light sets, speculars tuned to a share.

See :mod:`ps_lab.bench.paper` for the model; this module prepares each scene once (surface,
light sets, clean and corrupted renderings) for every table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ps_lab import render as _render

__all__ = ["light_set_rng", "roughness_for_specular_share", "specular_share"]


@dataclass(frozen=True)
class LightSet:
    light_directions: np.ndarray  # (N, 3)
    observations: np.ndarray  # (N, P) speculars, shadows, no noise
    specular_share: float
    shadow_share: float


@dataclass(frozen=True)
class PreparedScene:
    name: str
    surface: _render.Surface
    normals: np.ndarray  # (P, 3) ground truth
    scale: float  # largest Lambertian radiance (max albedo under a unit light)
    roughness: float
    max_specular_ratio: float
    light_sets: tuple[LightSet, ...]


def make_surface(name: str, size: int, seed: int) -> _render.Surface:
    if name == "sphere":
        return _render.sphere_surface((size, size))
    if name == "relief":
        return _render.relief_surface((size, size), seed=seed)
    raise ValueError(f"unknown scene {name!r} (sphere or relief)")


def masked_observations(images: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(n, H, W[, C]) rendered images -> (n, P) observations of the masked pixels (grey)."""
    images = np.asarray(images, dtype=np.float64)
    if images.ndim == 4:
        images = images.mean(axis=-1)
    observations = np.ascontiguousarray(images[:, mask])
    # Shared by every table: nothing may change them in place.
    observations.flags.writeable = False
    return observations


def albedo_scale(surface: _render.Surface) -> float:
    albedo = np.asarray(surface.albedo, dtype=np.float64)
    if albedo.ndim == 3:
        albedo = albedo.mean(axis=-1)
    albedo = np.broadcast_to(albedo, surface.mask.shape)
    return float(albedo[surface.mask].max())


def light_set_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of light set ``index``: fixed by the run's seed, independent of the rest."""
    return np.random.default_rng([seed, index])


def specular_share(
    surface: _render.Surface,
    light_directions: np.ndarray,
    *,
    strength: float,
    roughness: float,
    threshold: float,
) -> float:
    """Share of observations whose Cook-Torrance part exceeds ``threshold``.

    Parameters
    ----------
    surface : Surface
        The rendered object.
    light_directions : ndarray of shape (n, 3)
        The lights.
    strength, roughness : float
        The renderer's ``specular`` and ``roughness``.
    threshold : float
        Radiance above which an observation counts as specular-corrupted.

    Returns
    -------
    float
        Share over all ``n x P`` observations of the object (shadowed ones included).
    """
    diffuse = masked_observations(_render.render(surface, light_directions), surface.mask)
    full = masked_observations(
        _render.render(surface, light_directions, specular=strength, roughness=roughness),
        surface.mask,
    )
    return float(np.mean(full - diffuse > threshold))


def roughness_for_specular_share(
    surface: _render.Surface,
    light_directions: np.ndarray,
    *,
    strength: float,
    share: float,
    threshold: float,
    bounds: tuple[float, float] = (0.03, 0.5),
    steps: int = 14,
) -> float:
    """Roughness of the Cook-Torrance lobe that corrupts ``share`` of the observations.

    A narrower lobe (smaller roughness) is brighter but hits fewer observations; within
    ``bounds`` the share above ``threshold`` grows with the roughness, so bisection (on the
    logarithm of the roughness) finds it.

    Parameters
    ----------
    surface : Surface
        The rendered object.
    light_directions : ndarray of shape (n, 3)
        The lights the share is measured with.
    strength : float
        The renderer's ``specular`` (kept fixed).
    share : float
        Wanted share of observations with a specular part above ``threshold``.
    threshold : float
        Radiance above which an observation counts as specular-corrupted.
    bounds : (float, float)
        Search interval of the roughness.
    steps : int
        Bisection steps.

    Returns
    -------
    float
        The roughness.
    """
    if not 0.0 < share < 1.0:
        raise ValueError(f"share must lie in (0, 1), got {share}")

    diffuse = masked_observations(_render.render(surface, light_directions), surface.mask)

    def measured(roughness: float) -> float:
        full = _render.render(surface, light_directions, specular=strength, roughness=roughness)
        return float(np.mean(masked_observations(full, surface.mask) - diffuse > threshold))

    lo, hi = math.log(bounds[0]), math.log(bounds[1])
    if measured(math.exp(hi)) < share:
        raise ValueError(
            f"the specular lobe cannot corrupt {share:.0%} of observations above {threshold:g} "
            f"with strength {strength:g}; raise the strength"
        )
    if measured(math.exp(lo)) > share:
        return math.exp(lo)
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        if measured(math.exp(mid)) < share:
            lo = mid
        else:
            hi = mid
    return math.exp(0.5 * (lo + hi))
