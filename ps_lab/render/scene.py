"""Scenes of the simulated rig: objects placed in one frame, rendered under the lit lights."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ps_lab.render.near_shading import PointLights, render_chrome_near, render_near
from ps_lab.render.shading import _chrome_coverage, render, render_chrome_sphere
from ps_lab.render.surfaces import Surface, relief_surface, sphere_surface


@dataclass(frozen=True)
class SceneObject:
    """One object of a simulated rig scene.

    Attributes
    ----------
    kind : str
        ``'sphere'`` (Lambertian + specular sphere), ``'relief'`` (height-field object, placed in
        its bounding circle), ``'chrome'`` (mirror sphere) or ``'matte'`` (Lambertian sphere).
    center : (x, y)
        Centre in pixels.
    radius : float
        Radius (of the bounding circle for ``'relief'``) in pixels.
    albedo : (r, g, b)
        Per-channel albedo (the mirror's reflectance for ``'chrome'``).
    specular, roughness : float
        Cook-Torrance lobe of ``'sphere'`` and ``'relief'`` objects.
    seed : int
        Layout seed of a ``'relief'`` object.
    """

    kind: str
    center: tuple[float, float]
    radius: float
    albedo: tuple[float, float, float] = (1.0, 1.0, 1.0)
    specular: float = 0.0
    roughness: float = 0.3
    seed: int = 0


@dataclass(frozen=True)
class Scene:
    """Objects on a constant background, seen by an orthographic ``height x width`` camera.

    ``background`` is a light-independent level (stray light, sensor offset) present in every frame
    outside the objects, including the dark frame.
    """

    width: int
    height: int
    objects: tuple[SceneObject, ...]
    background: float = 0.0


OBJECT_KINDS = ("sphere", "relief", "chrome", "matte")


def _build_surfaces(scene: Scene) -> tuple[tuple[Surface | None, np.ndarray], ...]:
    """Per object: its surface (None for chrome) and its (H, W) coverage."""
    shape = (scene.height, scene.width)
    surfaces: list[Surface | None] = []
    for obj in scene.objects:
        if obj.kind not in OBJECT_KINDS:
            raise ValueError(
                f"unknown scene object kind {obj.kind!r}; expected one of {OBJECT_KINDS}"
            )
        albedo = np.asarray(obj.albedo, dtype=np.float64)
        if obj.kind in ("sphere", "matte"):
            surfaces.append(sphere_surface(shape, obj.center, obj.radius, albedo=albedo))
        elif obj.kind == "relief":
            base = relief_surface(shape, seed=obj.seed, center=obj.center, radius=obj.radius)
            colour = base.albedo[..., None] * albedo
            surfaces.append(
                Surface(normals=base.normals, mask=base.mask, height=base.height, albedo=colour)
            )
        else:
            surfaces.append(None)
    return tuple(
        (surface, _object_alpha(scene, obj, surface))
        for obj, surface in zip(scene.objects, surfaces, strict=True)
    )


_cached_surfaces = functools.lru_cache(maxsize=2)(_build_surfaces)


def _scene_surfaces(scene: Scene) -> tuple[tuple[Surface | None, np.ndarray], ...]:
    # The simulated camera renders the same scene once per frame: build its surfaces once.
    try:
        return _cached_surfaces(scene)
    except TypeError:  # unhashable fields (lists): build without the cache
        return _build_surfaces(scene)


def _object_alpha(scene: Scene, obj: SceneObject, surface: Surface | None) -> np.ndarray:
    """(H, W) share of each pixel covered by the object (anti-aliased for the chrome sphere)."""
    if surface is not None:
        return surface.mask.astype(np.float64)
    alpha = np.zeros((scene.height, scene.width))
    geometry = _chrome_coverage(
        (scene.height, scene.width),
        (float(obj.center[0]), float(obj.center[1])),
        float(obj.radius),
        4,
    )
    if geometry is not None:
        box, coverage = geometry
        alpha[box] = coverage
    return alpha


def render_scene(
    scene: Scene,
    light_directions: np.ndarray,
    light_intensities: np.ndarray | None = None,
    *,
    point_lights: PointLights | None = None,
) -> np.ndarray:
    """Render the frame seen with the given lights lit together.

    Parameters
    ----------
    scene : Scene
        The objects and background.
    light_directions : ndarray of shape (k, 3)
        The lit lights; ``k = 0`` gives the dark frame.
    light_intensities : ndarray of shape (k, 3), optional
        Per-channel intensities; default ones (at the scene origin for point lights).
    point_lights : PointLights, optional
        The same k lights as LEDs at a finite distance (fall-off, anisotropy, parallax): then
        ``light_directions`` is not used for shading. Objects' heights are measured from the
        spheres' plane (the relief's outline and the spheres' centres lie in it).

    Returns
    -------
    ndarray of shape (H, W, 3)
        ``background`` outside the objects plus the sum over lit lights of each object's radiance.
        Later objects cover earlier ones (the chrome sphere's outline is anti-aliased); cast shadows
        are computed within each object. Frames add up:
        ``frame(A and B) - dark = (frame(A) - dark) + (frame(B) - dark)``.
    """
    h, w = scene.height, scene.width
    lights = np.asarray(light_directions, dtype=np.float64).reshape(-1, 3)
    k = lights.shape[0]
    if light_intensities is None:
        intensities = np.ones((k, 3))
    else:
        intensities = np.broadcast_to(
            np.asarray(light_intensities, dtype=np.float64).reshape(k, -1 if k else 3), (k, 3)
        )
    frame = np.full((h, w, 3), float(scene.background))
    for obj, (surface, alpha) in zip(scene.objects, _scene_surfaces(scene), strict=True):
        # "Over" compositing: linear in the object's radiance, so frames add up light by light.
        frame *= 1.0 - alpha[..., None]
        if k == 0:
            continue
        if obj.kind == "chrome":
            if point_lights is None:
                grey = render_chrome_sphere((h, w), obj.center, obj.radius, lights)  # (k, H, W)
            else:
                grey = render_chrome_near(
                    (h, w), obj.center, obj.radius, point_lights.positions,
                    light_radius=point_lights.radius,
                )
            frame += np.einsum("khw,kc->hwc", grey, intensities) * np.asarray(obj.albedo)
        else:
            spec = obj.specular if obj.kind != "matte" else 0.0
            # A sphere is convex: only a relief can shadow itself.
            shading = {
                "cast_shadows": obj.kind == "relief",
                "specular": spec,
                "roughness": obj.roughness,
            }
            if point_lights is None:
                images = render(surface, lights, intensities, **shading)
            else:
                images = render_near(
                    surface, point_lights.positions, intensities,
                    anisotropy=point_lights.anisotropy, axes=point_lights.axes,
                    **shading,
                )
            frame += images.sum(axis=0)
    return frame


def scene_ground_truth(scene: Scene) -> dict:
    """Ground truth of a scene.

    Returns
    -------
    dict
        ``normals`` (H, W, 3) of the sphere/relief objects (zeros elsewhere), ``mask`` (H, W) bool
        of those objects, ``depth`` (H, W): their depth along the viewing axis away from the
        camera (``-height``, in pixels; NaN elsewhere), ``chrome`` and ``matte``: lists of
        ``(cx, cy, r)`` circles.
    """
    h, w = scene.height, scene.width
    normals = np.zeros((h, w, 3))
    depth = np.full((h, w), np.nan)
    mask = np.zeros((h, w), dtype=bool)
    chrome: list[tuple[float, float, float]] = []
    matte: list[tuple[float, float, float]] = []
    for obj, (surface, alpha) in zip(scene.objects, _scene_surfaces(scene), strict=True):
        obj_mask = alpha > 0.5
        # A later object hides what is behind it.
        normals[obj_mask] = 0.0
        depth[obj_mask] = np.nan
        mask &= ~obj_mask
        if obj.kind in ("sphere", "relief"):
            normals[obj_mask] = surface.normals[obj_mask]
            depth[obj_mask] = -surface.height[obj_mask]
            mask |= obj_mask
        elif obj.kind == "chrome":
            chrome.append((float(obj.center[0]), float(obj.center[1]), float(obj.radius)))
        else:
            matte.append((float(obj.center[0]), float(obj.center[1]), float(obj.radius)))
    return {"normals": normals, "mask": mask, "depth": depth, "chrome": chrome, "matte": matte}
