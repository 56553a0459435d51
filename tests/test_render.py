"""Renderer: geometry, shading, shadows, specular, noise, chrome highlights, scene composition."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from ps_lab.render import (
    Scene,
    SceneObject,
    Surface,
    random_light_directions,
    relief_surface,
    render,
    render_chrome_sphere,
    render_scene,
    scene_ground_truth,
    sphere_surface,
)

SHAPE = (72, 80)


def _lambert(surface: Surface, lights: np.ndarray) -> np.ndarray:
    """Reference: albedo * max(n.l, 0), one light at a time with plain loops over lights."""
    out = []
    for light in lights:
        light = light / np.linalg.norm(light)
        cosine = np.maximum(surface.normals @ light, 0.0)
        out.append(surface.albedo * cosine * surface.mask)
    return np.array(out)


def _centroid(image: np.ndarray) -> tuple[float, float]:
    rows, cols = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    total = image.sum()
    return float((image * cols).sum() / total), float((image * rows).sum() / total)


def test_random_light_directions_are_unit_and_inside_the_cap(rng):
    lights = random_light_directions(500, rng, max_zenith_deg=50.0)
    assert lights.shape == (500, 3)
    np.testing.assert_allclose(np.linalg.norm(lights, axis=1), 1.0, atol=1e-12)
    assert lights[:, 2].min() >= np.cos(np.deg2rad(50.0)) - 1e-12
    # Spread over all azimuths, not a degenerate set.
    assert np.ptp(np.arctan2(lights[:, 1], lights[:, 0])) > 5.0


@pytest.mark.parametrize(
    "make", [lambda: sphere_surface(SHAPE), lambda: relief_surface(SHAPE, seed=3)]
)
def test_normals_unit_inside_mask_zero_outside(make):
    surface = make()
    assert surface.mask.any() and not surface.mask.all()
    np.testing.assert_allclose(
        np.linalg.norm(surface.normals[surface.mask], axis=-1), 1.0, atol=1e-12
    )
    assert np.all(surface.normals[~surface.mask] == 0.0)
    assert np.all(surface.height[~surface.mask] == 0.0)
    assert np.all(surface.normals[surface.mask][:, 2] > 0.0)


def test_sphere_geometry_defaults_and_y_up():
    surface = sphere_surface(SHAPE)
    h, w = SHAPE
    radius = 0.45 * min(h, w)
    assert abs(surface.mask.sum() - np.pi * radius**2) < 2 * np.pi * radius
    cy, cx = (h - 1) / 2, (w - 1) / 2
    top = (int(round(cy - 0.8 * radius)), int(round(cx)))  # above the centre in the image
    right = (int(round(cy)), int(round(cx + 0.8 * radius)))
    assert surface.normals[top][1] > 0.7  # y up = toward smaller row numbers
    assert surface.normals[right][0] > 0.7
    np.testing.assert_allclose(surface.height.max(), radius, rtol=0.02)


def test_relief_normals_are_those_of_its_height_field():
    surface = relief_surface((120, 120), seed=5)
    # Central differences of the height in the interior (away from the steep rim).
    dz_dx = np.gradient(surface.height, axis=1)
    dz_dy_up = -np.gradient(surface.height, axis=0)
    numeric = np.stack([-dz_dx, -dz_dy_up, np.ones_like(dz_dx)], axis=-1)
    numeric /= np.linalg.norm(numeric, axis=-1, keepdims=True)
    rows, cols = np.mgrid[0:120, 0:120]
    interior = surface.mask & (np.hypot(cols - 59.5, rows - 59.5) < 0.75 * 0.45 * 120)
    cosine = np.sum(numeric[interior] * surface.normals[interior], axis=-1)
    assert np.median(np.degrees(np.arccos(np.clip(cosine, -1, 1)))) < 1.0
    # Deterministic in the seed, different across seeds.
    again = relief_surface((120, 120), seed=5)
    np.testing.assert_array_equal(again.height, surface.height)
    assert not np.array_equal(relief_surface((120, 120), seed=6).height, surface.height)


def test_lambertian_image_equals_albedo_n_dot_l(rng):
    albedo = rng.uniform(0.3, 1.0, size=SHAPE)
    surface = sphere_surface(SHAPE, albedo=albedo)
    lights = random_light_directions(6, rng)
    images = render(surface, lights, cast_shadows=False)
    assert images.shape == (6, *SHAPE)
    np.testing.assert_allclose(images, _lambert(surface, lights), atol=1e-12)
    # A sphere is convex: ray-marched shadows change nothing.
    np.testing.assert_allclose(render(surface, lights, cast_shadows=True), images, atol=1e-12)


def test_light_intensities_scale_and_colour_channels(rng):
    surface = relief_surface(SHAPE, seed=1)
    lights = random_light_directions(4, rng)
    grey = render(surface, lights)
    scaled = render(surface, lights, np.array([1.0, 2.0, 0.5, 3.0]))
    np.testing.assert_allclose(scaled, grey * np.array([1.0, 2.0, 0.5, 3.0])[:, None, None])
    rgb = np.array([[1.0, 0.5, 0.25]] * 4)
    colour = render(surface, lights, rgb)
    assert colour.shape == (4, *SHAPE, 3)
    np.testing.assert_allclose(colour, grey[..., None] * rgb[:, None, None, :])
    colour_albedo = sphere_surface(SHAPE, albedo=(0.2, 0.4, 0.8))
    assert render(colour_albedo, lights).shape == (4, *SHAPE, 3)


def test_light_from_the_camera_casts_no_shadow():
    surface = relief_surface((96, 96), seed=2)
    light = np.array([[0.0, 0.0, 1.0]])
    with_shadows = render(surface, light, cast_shadows=True)
    np.testing.assert_array_equal(with_shadows, render(surface, light, cast_shadows=False))
    assert np.all(with_shadows[0][surface.mask] > 0)


def _blocked_by_oracle(surface: Surface, row: int, col: int, light: np.ndarray) -> bool:
    """Slow reference: quarter-pixel steps, scipy bilinear heights strictly inside the object."""
    horizontal = np.hypot(light[0], light[1])
    rise = light[2] / horizontal
    t = np.arange(0.25, 400.0, 0.25)
    rows = row - t * light[1] / horizontal
    cols = col + t * light[0] / horizontal
    heights = map_coordinates(surface.height, [rows, cols], order=1, cval=0.0)
    on_object = map_coordinates(surface.mask.astype(float), [rows, cols], order=1, cval=0.0) > 0.999
    ray = surface.height[row, col] + t * rise
    return bool(np.any(on_object & (heights > ray + 0.5)))


def test_oblique_light_casts_shadows_where_attached_test_says_lit():
    surface = relief_surface((128, 128), seed=0)
    zenith = np.deg2rad(60.0)
    light = np.array([np.sin(zenith), 0.0, np.cos(zenith)])
    image = render(surface, light[None])[0]
    facing = surface.mask & (surface.normals @ light > 0.05)
    cast = facing & (image == 0.0)
    assert cast.sum() > 0.02 * facing.sum()
    # Shadow pixels lie behind something tall (checked with an independent, slower march)...
    rows, cols = np.nonzero(cast)
    pick = np.random.default_rng(0).choice(rows.size, size=min(25, rows.size), replace=False)
    blocked = [_blocked_by_oracle(surface, rows[i], cols[i], light) for i in pick]
    assert np.mean(blocked) > 0.9
    # Elsewhere on the lit side the image is plain Lambertian shading.
    np.testing.assert_allclose(
        image[facing & ~cast], (surface.normals @ light * surface.albedo)[facing & ~cast]
    )


def _ray_excess(surface: Surface, row: int, col: int, light: np.ndarray) -> float:
    """Slow reference: how far the terrain rises above the ray (quarter-pixel steps, t >= 1)."""
    horizontal = np.hypot(light[0], light[1])
    t = np.arange(1.0, 400.0, 0.25)
    rows = row - t * light[1] / horizontal
    cols = col + t * light[0] / horizontal
    heights = map_coordinates(surface.height, [rows, cols], order=1, cval=0.0)
    on_object = map_coordinates(surface.mask.astype(float), [rows, cols], order=1, cval=0.0) > 0.999
    ray = surface.height[row, col] + 0.5 + t * light[2] / horizontal
    return float(np.max(np.where(on_object, heights - ray, -np.inf)))


@pytest.mark.parametrize("seed", [0, 1])
def test_cast_shadows_agree_with_a_brute_force_march(seed):
    # The fast path (sweep + partial march) must find every clearly blocked ray and no clear one.
    rng = np.random.default_rng(seed)
    surface = relief_surface((100, 120), seed=seed)
    lights = random_light_directions(4, rng, max_zenith_deg=70.0)
    images = render(surface, lights)
    blocked_seen = 0
    for light, image in zip(lights, images, strict=True):
        facing = surface.mask & (surface.normals @ light > 0)
        rows, cols = np.nonzero(facing)
        pick = rng.choice(rows.size, size=150, replace=False)
        excess = np.array([_ray_excess(surface, rows[i], cols[i], light) for i in pick])
        shadowed = image[rows[pick], cols[pick]] == 0.0
        assert np.all(shadowed[excess > 0.3])
        assert not np.any(shadowed[excess < -0.3])
        blocked_seen += int(np.sum(excess > 0.3))
    assert blocked_seen > 10


def test_specular_adds_positive_energy_near_the_mirror_direction():
    surface = sphere_surface((101, 101))
    light = np.array([0.3, 0.2, 0.9])
    light /= np.linalg.norm(light)
    diffuse = render(surface, light[None])[0]
    shiny = render(surface, light[None], specular=0.8, roughness=0.15)[0]
    extra = shiny - diffuse
    assert extra.min() >= 0.0
    assert extra.max() > 0.3
    assert np.all(extra[~surface.mask] == 0.0) and np.all(extra[diffuse == 0] == 0.0)
    half = (light + [0, 0, 1]) / np.linalg.norm(light + [0, 0, 1])
    radius = 0.45 * 101
    expected = (50 + radius * half[0], 50 - radius * half[1])
    peak_row, peak_col = np.unravel_index(np.argmax(extra), extra.shape)
    assert np.hypot(peak_col - expected[0], peak_row - expected[1]) <= 1.5
    # Rougher surfaces spread the lobe: lower peak, wider footprint.
    rough = render(surface, light[None], specular=0.8, roughness=0.5)[0] - diffuse
    assert rough.max() < extra.max()
    assert (rough > 0.05 * rough.max()).sum() > (extra > 0.05 * extra.max()).sum()


def test_lights_from_behind_leave_the_object_dark():
    surface = relief_surface((48, 48), seed=1)
    lights = np.array([[0.0, 0.0, -1.0], [0.3, 0.1, -0.9]])
    images = render(surface, lights, specular=0.5)
    assert images.shape == (2, 48, 48)
    assert np.all(images[0] == 0.0)
    # A light behind the object can reach only the steep normals that face it, with finite values.
    facing = surface.normals @ (lights[1] / np.linalg.norm(lights[1])) > 0
    assert np.all(np.isfinite(images[1])) and np.all(images[1] >= 0.0)
    assert np.all(images[1][~facing] == 0.0)


@pytest.mark.parametrize("fraction", [0.1, 0.4])
def test_noise_share_matches_noise_fraction(rng, fraction):
    surface = sphere_surface((64, 64))
    lights = random_light_directions(10, rng)
    clean = render(surface, lights)
    noisy = render(surface, lights, noise_sigma=0.05, noise_fraction=fraction, rng=rng)
    changed = noisy != clean
    assert not changed[:, ~surface.mask].any()
    observations = lights.shape[0] * surface.mask.sum()
    assert abs(changed.sum() / observations - fraction) < 1e-3
    assert abs(np.std((noisy - clean)[changed]) - 0.05) < 0.005
    # Seeded: the same generator state gives the same noise.
    again = render(
        surface, lights, noise_sigma=0.05, noise_fraction=fraction, rng=np.random.default_rng(7)
    )
    twice = render(
        surface, lights, noise_sigma=0.05, noise_fraction=fraction, rng=np.random.default_rng(7)
    )
    np.testing.assert_array_equal(again, twice)


def test_chrome_highlight_at_centre_for_a_light_from_the_camera():
    center, radius = (40.3, 37.6), 25.4
    image = render_chrome_sphere(
        (80, 84), center, radius, np.array([[0.0, 0.0, 1.0]]), ambient=0.0
    )[0]
    cx, cy = _centroid(image)
    assert abs(cx - center[0]) < 0.02 and abs(cy - center[1]) < 0.02


def test_chrome_highlight_where_the_normal_bisects_view_and_light(rng):
    center, radius = (61.7, 58.2), 44.6
    lights = random_light_directions(8, rng, max_zenith_deg=60.0)
    images = render_chrome_sphere((120, 128), center, radius, lights, ambient=0.0)
    for light, image in zip(lights, images, strict=True):
        half = (light + [0, 0, 1]) / np.linalg.norm(light + [0, 0, 1])
        cx, cy = _centroid(image)
        assert (
            np.hypot(cx - (center[0] + radius * half[0]), cy - (center[1] - radius * half[1]))
            < 0.02
        )


def test_chrome_outline_is_antialiased_and_ambient():
    center, radius = (30.25, 29.6), 20.3
    image = render_chrome_sphere(
        (60, 60),
        center,
        radius,
        np.array([[0.0, 0.0, 1.0]]),
        light_radiance=0.0,
        ambient=1.0,
        supersample=8,
    )[0]
    assert abs(image.sum() - np.pi * radius**2) < 0.01 * np.pi * radius**2
    partial = (image > 0.02) & (image < 0.98)
    assert partial.sum() > 20  # grey edge pixels, not a binary disc
    assert image[0, 0] == 0.0 and image[30, 30] == 1.0


def _scene() -> Scene:
    return Scene(
        width=160,
        height=112,
        objects=(
            SceneObject("relief", (50.0, 56.0), 44.0, (0.9, 0.7, 0.5), specular=0.3, seed=4),
            SceneObject("chrome", (126.3, 30.2), 22.5, (1.0, 1.0, 1.0)),
            SceneObject("matte", (126.0, 84.0), 22.0, (0.8, 0.8, 0.8)),
        ),
        background=0.01,
    )


def test_render_scene_dark_frame_and_additivity(rng):
    scene = _scene()
    lights = random_light_directions(3, rng)
    intensities = np.array([[1.0, 1.0, 1.0], [0.5, 1.0, 2.0], [1.2, 0.9, 1.0]])
    dark = render_scene(scene, np.zeros((0, 3)))
    assert dark.shape == (112, 160, 3)
    # The simulated camera passes its (empty) intensities along with the (empty) directions.
    np.testing.assert_array_equal(render_scene(scene, np.zeros((0, 3)), np.zeros((0, 3))), dark)
    truth = scene_ground_truth(scene)
    assert np.all(dark[0, 0] == 0.01)
    assert np.all(dark[truth["mask"]] == 0.0)
    single = [
        render_scene(scene, lights[i : i + 1], intensities[i : i + 1]) - dark for i in range(3)
    ]
    both = render_scene(scene, lights[:2], intensities[:2]) - dark
    np.testing.assert_allclose(both, single[0] + single[1], atol=1e-12)
    assert single[1][truth["mask"]].max() > 0
    # Per-channel intensities and albedo: the relief's channel ratio is (0.5*0.9, 1*0.7, 2*0.5).
    pixels = truth["mask"] & (single[1][..., 1] > 0.05)
    ratio = single[1][pixels] / single[1][pixels][:, 1:2]
    np.testing.assert_allclose(np.median(ratio, axis=0), [0.45 / 0.7, 1.0, 1.0 / 0.7], rtol=0.05)


def test_scene_ground_truth_matches_objects():
    scene = _scene()
    truth = scene_ground_truth(scene)
    assert truth["chrome"] == [(126.3, 30.2, 22.5)]
    assert truth["matte"] == [(126.0, 84.0, 22.0)]
    relief = relief_surface((112, 160), seed=4, center=(50.0, 56.0), radius=44.0)
    np.testing.assert_array_equal(truth["mask"], relief.mask)
    np.testing.assert_allclose(truth["normals"], relief.normals)
    # The chrome sphere in a frame shows a highlight where the mirror sends the light.
    light = np.array([[0.0, 0.0, 1.0]])
    frame = render_scene(scene, light) - render_scene(scene, np.zeros((0, 3)))
    box = frame[8:53, 104:149, 0]
    cx, cy = _centroid(np.where(box > 0.05, box, 0.0))  # above the 0.02 ambient
    assert abs(cx + 104 - 126.3) < 0.1 and abs(cy + 8 - 30.2) < 0.1
