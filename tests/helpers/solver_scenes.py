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
