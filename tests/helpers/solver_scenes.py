"""Rendered scenes the solver tests share: lights in the upper hemisphere, masked observations."""

from __future__ import annotations

from ps_lab.render import random_light_directions, relief_surface, render, sphere_surface


def lights_upper(n, rng, max_zenith_deg=60.0):
    return random_light_directions(n, rng, max_zenith_deg=max_zenith_deg)


def scene(kind, shape, lights, rng, *, specular=0.0):
    """Observations (n, P) of the masked pixels, true normals (P, 3), albedo (P,)."""
    surface = sphere_surface(shape) if kind == "sphere" else relief_surface(shape, seed=3)
    images = render(surface, lights, specular=specular, rng=rng)
    albedo = surface.albedo if surface.albedo.ndim == 2 else surface.albedo.mean(axis=-1)
    return images[:, surface.mask], surface.normals[surface.mask], albedo[surface.mask]


def corrupt(y, rng, low, where=None):
    """Sparse gross outliers (speculars, hot pixels): a copy of ``y`` (n, P) with each
    observation (of those in ``where``, a bool (n, P)) raised with probability 0.1 by a uniform
    draw in [low, 1). Returns the copy and the (n, P) bool mask of the raised observations.
    """
    hit = rng.random(y.shape) < 0.1
    if where is not None:
        hit &= where
    raised = y.copy()
    raised[hit] += rng.uniform(low, 1.0, hit.sum())
    return raised, hit
