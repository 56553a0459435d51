"""Shading of the synthetic world: Lambert + Cook-Torrance, cast shadows, chrome spheres.

The camera looks down ``-z`` (orthographic, one pixel = one length unit); lights are directional.
Vectors live in the camera frame: x right, y up (``y = -(row offset)``), z toward the camera, and
light directions point from the surface toward the light (the DiLiGenT convention). Pixel ``(x, y)``
is (column, row) with the origin at the centre of the top-left pixel. See ``docs/renderer.md``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from ps_lab.render.surfaces import Surface

_VIEW = np.array([0.0, 0.0, 1.0])
# Offset (pixel units of height) that a shadow ray must clear, so a surface does not shadow itself
# through the linear interpolation of its own curved height field.
_SHADOW_BIAS = 0.5
# Height margin (pixels) of the fast shadow sweep, which interpolates between neighbouring rays;
# rays within it are marched exactly.
_SHADOW_SLACK = 1.0
# Standard deviation (pixels) of the Gaussian lens blur applied to chrome highlights.
_HIGHLIGHT_PSF_SIGMA = 0.6
# Schlick's reflectance at normal incidence (a dielectric); the Fresnel term is divided by it so
# that ``specular`` sets the lobe's scale independently of the material.
_FRESNEL_F0 = 0.04


class _HeightSampler:
    """Exact bilinear samples of a height field at float64 positions (column x, row y).

    A sample whose four neighbouring pixels are not all on the object is ``-inf`` (it blocks
    nothing): interpolating across the silhouette would smear the object's rim height into empty
    space and shadow the rim itself.
    """

    def __init__(self, height: np.ndarray, mask: np.ndarray) -> None:
        self.rows, self.cols = height.shape
        self.flat = np.ascontiguousarray(height, dtype=np.float64).ravel()
        cell = np.zeros(height.shape, dtype=bool)  # cell (r, c) spans pixels r..r+1, c..c+1
        cell[:-1, :-1] = mask[:-1, :-1] & mask[:-1, 1:] & mask[1:, :-1] & mask[1:, 1:]
        self.cell_on_object = cell.ravel()

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x0 = np.floor(x)
        y0 = np.floor(y)
        fx = x - x0
        fy = y - y0
        # Cells outside the array are off the object; clip only to index safely.
        index = np.clip(y0, 0, self.rows - 1).astype(np.intp) * self.cols
        index += np.clip(x0, 0, self.cols - 1).astype(np.intp)
        on_object = self.cell_on_object[index]
        on_object &= (x0 >= 0) & (y0 >= 0) & (x0 < self.cols - 1) & (y0 < self.rows - 1)
        index = np.where(on_object, index, 0)
        flat, w = self.flat, self.cols
        h00, h01 = flat[index], flat[index + 1]
        h10, h11 = flat[index + w], flat[index + w + 1]
        value = h00 + fx * (h01 - h00) + fy * ((h10 - h00) + fx * (h11 - h10 - h01 + h00))
        return np.where(on_object, value, -np.inf)


def _terrain_ahead(
    height: np.ndarray, step: tuple[float, float], rise: float
) -> tuple[np.ndarray, np.ndarray]:
    """Highest ``G = h - rise u`` ahead of every pixel along the light, from one sweep.

    Returns ``ahead`` and the offset ``rise * u``, both (H, W): pixel ``p`` may be shadowed only
    if ``ahead[p] > h(p) + bias - rise u(p)`` (up to the interpolation margin ``_SHADOW_SLACK``).

    Along a ray ``q = p + t d`` the test ``h(q) > h(p) + bias + t rise`` reads
    ``G(q) > G(p) + bias`` with ``G = h - rise u`` and ``u`` the coordinate along ``d``. The height
    field is resampled on a grid rotated so that ``d`` runs along its rows; a reverse running
    maximum of ``G`` along each row gives, for every pixel at once, the highest ``G`` ahead (from
    2 pixels on). Rotating that back interpolates between neighbouring rows, so comparisons keep a
    margin (``_SHADOW_SLACK``); the caller marches the candidates exactly.
    """
    step_x, step_y = step
    h, w = height.shape
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    half = int(np.ceil(0.5 * np.hypot(h, w))) + 2
    size = 2 * half + 1
    # Rotated grid (column u', row v'): original x = cx + (u'-half) dx - (v'-half) dy, etc.
    to_original = np.array(
        [
            [step_x, -step_y, cx - half * step_x + half * step_y],
            [step_y, step_x, cy - half * step_y - half * step_x],
        ]
    )
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    rotated = cv2.warpAffine(
        height.astype(np.float32),
        to_original,
        (size, size),
        flags=flags,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    ).astype(np.float64)
    along = np.arange(size, dtype=np.float64)
    g_rot = rotated - rise * along[None, :]
    ahead = np.maximum.accumulate(g_rot[:, ::-1], axis=1)[:, ::-1]
    ahead = np.concatenate([ahead[:, 2:], np.full((size, 2), -1e9)], axis=1)
    # Back to the original grid: u' = (x - cx) dx + (y - cy) dy + half, v' = -(x - cx) dy + ...
    to_rotated = np.array(
        [
            [step_x, step_y, half - cx * step_x - cy * step_y],
            [-step_y, step_x, half + cx * step_y - cy * step_x],
        ]
    )
    ahead_here = cv2.warpAffine(
        ahead.astype(np.float32),
        to_rotated,
        (w, h),
        flags=flags,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=-1e9,
    )
    cols = np.arange(w, dtype=np.float64)[None, :]
    rows = np.arange(h, dtype=np.float64)[:, None]
    u_here = (cols - cx) * step_x + (rows - cy) * step_y + half
    return ahead_here, rise * u_here


def _cast_shadow(
    height: np.ndarray, mask: np.ndarray, lit: np.ndarray, light: np.ndarray
) -> np.ndarray:
    """Ray-march the height field from every lit pixel toward a directional light.

    Parameters
    ----------
    height : ndarray of shape (H, W)
        Height field in pixel units (0 off the object).
    mask : ndarray of shape (H, W), bool
        The object.
    lit : ndarray of shape (H, W), bool
        Pixels to test (those facing the light).
    light : ndarray of shape (3,)
        Unit direction toward the light.

    Returns
    -------
    ndarray of shape (H, W), bool
        True where some sample along the ray lies above the ray (plus a small bias).

    Notes
    -----
    The ray advances one pixel per step along the light's image-plane direction and rises by
    ``l_z / |l_xy|`` per step; a sample is the bilinear interpolation of the four surrounding
    pixels (none of them off the object), and a ray stops once it is above the highest point or
    leaves the array. Marching every pixel would cost ``O(H W)`` per step, so a running-maximum
    sweep (:func:`_terrain_ahead`) first discards the rays that clearly clear the terrain, only
    the remaining ones are marched (vectorised over pixels), and each stops as soon as the sweep
    says the terrain ahead of it stays below it.
    """
    shadow = np.zeros(height.shape, dtype=bool)
    horizontal = float(np.hypot(light[0], light[1]))
    if horizontal < 1e-9 or not lit.any():
        return shadow  # light along the camera axis: nothing can block it
    rise = light[2] / horizontal  # height gained per pixel travelled
    step_x = light[0] / horizontal
    step_y = -light[1] / horizontal  # y up -> rows down
    h, w = height.shape
    ray0 = height + _SHADOW_BIAS
    sample = _HeightSampler(height, mask)
    ahead, rise_u = _terrain_ahead(height, (step_x, step_y), rise)
    g_start = ray0 - rise_u  # the ray from p is blocked at q iff G(q) > g_start[p]
    candidate = lit & (ahead > g_start - _SHADOW_SLACK)
    # The sweep skips the first two pixels of each ray: check those for every other lit pixel,
    # first with cv2.remap (fast, bilinear weights quantised to 1/32 pixel), then exactly.
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float32)
    src = height.astype(np.float32)
    for t in (1, 2):
        quick = cv2.remap(
            src,
            cols + np.float32(t * step_x),
            rows + np.float32(t * step_y),
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0.0,
        )
        ys, xs = np.nonzero(lit & ~candidate & (quick > ray0 + t * rise - _SHADOW_SLACK))
        shadow[ys, xs] |= sample(xs + t * step_x, ys + t * step_y) > ray0[ys, xs] + t * rise
    ys, xs = np.nonzero(candidate)
    # Steps worth taking: until the ray is above the highest point or has left the array.
    z0 = ray0[ys, xs]
    g0 = g_start[ys, xs]
    last = (float(height.max()) - z0) / max(rise, 1e-12)
    if step_x:
        last = np.minimum(last, np.where(step_x > 0, (w - 1 - xs) / step_x, xs / -step_x))
    if step_y:
        last = np.minimum(last, np.where(step_y > 0, (h - 1 - ys) / step_y, ys / -step_y))
    t = 1
    keep = last >= t
    ys, xs, z0, g0, last = ys[keep], xs[keep], z0[keep], g0[keep], last[keep]
    while ys.size:
        x, y = xs + t * step_x, ys + t * step_y
        blocked = sample(x, y) > z0 + t * rise
        shadow[ys[blocked], xs[blocked]] = True
        # Once the sweep says nothing ahead of the ray's position rises to it (2 pixels on),
        # four more exact steps finish the ray (the sweep is read at the nearest pixel).
        clear = (
            ahead[np.rint(y).astype(np.intp), np.rint(x).astype(np.intp)] < g0 - 3 * _SHADOW_SLACK
        )
        last = np.where(clear, np.minimum(last, t + 4), last)
        t += 1
        keep = ~blocked & (last >= t)
        ys, xs, z0, g0, last = ys[keep], xs[keep], z0[keep], g0[keep], last[keep]
    return shadow


def _normalise_lights(light_directions: np.ndarray) -> np.ndarray:
    lights = np.asarray(light_directions, dtype=np.float64)
    if lights.ndim == 1:
        lights = lights[None, :]
    if lights.ndim != 2 or lights.shape[1] != 3:
        raise ValueError(f"light_directions must have shape (n, 3), got {lights.shape}")
    norm = np.linalg.norm(lights, axis=1, keepdims=True)
    if np.any(~np.isfinite(norm)) or np.any(norm <= 0):
        raise ValueError("light directions must be finite and non-zero")
    return lights / norm


def _cook_torrance(
    normals: np.ndarray, light: np.ndarray, n_dot_l: np.ndarray, roughness: float
) -> np.ndarray:
    """Cook-Torrance specular radiance per unit strength and irradiance, (P,) for (P, 3) normals.

    ``D F G / (4 (n.v))`` times the Fresnel normalisation ``1 / F0`` (see ``docs/renderer.md``); the
    ``n.l`` of the rendering equation cancels that of the BRDF denominator. ``light`` is one unit
    vector (3,) or one per pixel (P, 3) (a light at a finite distance).
    """
    half = np.asarray(light, dtype=np.float64) + _VIEW
    length = np.linalg.norm(half, axis=-1, keepdims=True)
    if half.ndim == 1 and float(length[0]) < 1e-9:
        # light straight from behind: no visible point can reflect it
        return np.zeros(normals.shape[0])
    half = half / np.maximum(length, 1e-9)
    n_dot_h = np.clip(np.sum(normals * half, axis=-1), 1e-6, 1.0)
    n_dot_v = np.clip(normals[:, 2], 1e-6, 1.0)
    v_dot_h = np.maximum(half[..., 2], 1e-6)
    m2 = roughness * roughness
    cos2 = n_dot_h * n_dot_h
    tan2 = (1.0 - cos2) / cos2
    beckmann = np.exp(-tan2 / m2) / (np.pi * m2 * cos2 * cos2)
    fresnel = (_FRESNEL_F0 + (1.0 - _FRESNEL_F0) * (1.0 - v_dot_h) ** 5) / _FRESNEL_F0
    geometry = np.minimum(
        1.0, np.minimum(2.0 * n_dot_h * n_dot_v / v_dot_h, 2.0 * n_dot_h * n_dot_l / v_dot_h)
    )
    return beckmann * fresnel * geometry / (4.0 * n_dot_v)


def render(
    surface: Surface,
    light_directions: np.ndarray,
    light_intensities: np.ndarray | None = None,
    *,
    cast_shadows: bool = True,
    specular: float = 0.0,
    roughness: float = 0.3,
    noise_sigma: float = 0.0,
    noise_fraction: float = 0.0,
    rng: np.random.Generator | None = None,
    progress: Callable[[int], None] | None = None,
) -> np.ndarray:
    """Render one image per light.

    Parameters
    ----------
    surface : Surface
        The object.
    light_directions : ndarray of shape (n, 3)
        Directions toward the lights (normalised here).
    light_intensities : ndarray of shape (n,), (n, 1) or (n, 3), optional
        Light intensities (grey or per channel); default all ones.
    cast_shadows : bool
        Ray-march the height field toward each light and darken occluded points.
    specular : float
        Strength of the Cook-Torrance lobe (about the peak radiance at normal incidence for
        ``roughness = 0.3``); 0 gives a purely Lambertian object.
    roughness : float
        Beckmann RMS slope ``m`` of the specular lobe.
    noise_sigma : float
        Standard deviation of the additive Gaussian noise.
    noise_fraction : float
        Share of the object's observations (light x pixel) that receive noise (the paper's noise
        density).
    rng : numpy.random.Generator, optional
        Noise source; default ``numpy.random.default_rng(0)``.
    progress : callable, optional
        Called with 1 after each light is shaded.

    Returns
    -------
    ndarray of shape (n, H, W), or (n, H, W, 3) when albedo or intensities are per channel
        Linear radiance, zeros outside the mask, not clipped (noise can make values negative).
    """
    lights = _normalise_lights(light_directions)
    n = lights.shape[0]
    if roughness <= 0:
        raise ValueError(f"roughness must be positive, got {roughness}")
    if specular < 0:
        raise ValueError(f"specular must be >= 0, got {specular}")
    if not 0.0 <= noise_fraction <= 1.0:
        raise ValueError(f"noise_fraction must be in [0, 1], got {noise_fraction}")
    if light_intensities is None:
        intensities = np.ones((n, 1))
    else:
        intensities = np.asarray(light_intensities, dtype=np.float64).reshape(n, -1)
        if intensities.shape[1] not in (1, 3):
            raise ValueError(
                f"light_intensities must be (n,), (n, 1) or (n, 3); got {intensities.shape}"
            )
    albedo = np.asarray(surface.albedo, dtype=np.float64)
    colour = albedo.ndim == 3 or intensities.shape[1] == 3
    h, w = surface.mask.shape
    # Work in the object's bounding box (shadows fall within the object).
    rows = np.flatnonzero(surface.mask.any(axis=1))
    cols = np.flatnonzero(surface.mask.any(axis=0))
    if rows.size == 0:
        rows = cols = np.array([0])
    box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    mask = surface.mask[box]
    normals = surface.normals[box][mask]  # (P, 3)
    albedo_p = albedo[box][mask].reshape(normals.shape[0], -1)  # (P, 1) or (P, 3)
    height = np.asarray(surface.height, dtype=np.float64)[box]
    cast_shadows = cast_shadows and normals.shape[0] > 0

    shading = np.zeros((n, normals.shape[0]))  # Lambertian cosine, 0 in attached/cast shadow
    spec = np.zeros((n, normals.shape[0]))
    for i, light in enumerate(lights):
        n_dot_l = normals @ light
        lit = n_dot_l > 0
        if cast_shadows:
            lit_map = np.zeros(mask.shape, dtype=bool)
            lit_map[mask] = lit
            lit &= ~_cast_shadow(height, mask, lit_map, light)[mask]
        shading[i] = np.where(lit, n_dot_l, 0.0)
        if specular > 0:
            spec[i] = np.where(
                lit, specular * _cook_torrance(normals, light, n_dot_l, roughness), 0.0
            )
        if progress is not None:
            progress(1)

    # (n, P, C) radiance: albedo-weighted diffuse plus (white) specular, times the light intensity.
    radiance = (shading[:, :, None] * albedo_p[None] + spec[:, :, None]) * intensities[:, None, :]
    if noise_fraction > 0 and noise_sigma > 0:
        rng = np.random.default_rng(0) if rng is None else rng
        total = n * normals.shape[0]
        count = int(round(noise_fraction * total))
        chosen = rng.choice(total, size=count, replace=False)
        noise = rng.normal(0.0, noise_sigma, size=(count, radiance.shape[2]))
        flat = radiance.reshape(total, radiance.shape[2])
        flat[chosen] += noise
    out = np.zeros((n, h, w, radiance.shape[2]))
    out[:, box[0], box[1]][:, mask] = radiance
    return out if colour else out[..., 0]


def _subpixel_offsets(supersample: int) -> np.ndarray:
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    return (np.arange(s) + 0.5) / s - 0.5


@functools.lru_cache(maxsize=8)
def _chrome_coverage(
    shape: tuple[int, int], center: tuple[float, float], radius: float, supersample: int
) -> tuple[tuple[slice, slice], np.ndarray] | None:
    """Anti-aliased outline of a sphere: its bounding box and each pixel's covered share.

    Returns the box (row slice, column slice) and the (bh, bw) share of each pixel inside the
    sphere, from an ``s x s`` sub-pixel grid; None if the box is empty. Cached: the simulated camera
    renders the same sphere for every frame; callers must not modify the returned array.
    """
    h, w = shape
    if radius <= 0:
        raise ValueError(f"radius must be positive, got {radius}")
    offsets = _subpixel_offsets(supersample)
    x0 = max(int(np.floor(center[0] - radius)) - 1, 0)
    x1 = min(int(np.ceil(center[0] + radius)) + 2, w)
    y0 = max(int(np.floor(center[1] - radius)) - 1, 0)
    y1 = min(int(np.ceil(center[1] + radius)) + 2, h)
    if x0 >= x1 or y0 >= y1:
        return None
    xs = ((np.arange(x0, x1)[:, None] + offsets[None, :]).ravel() - center[0]) / radius
    ys = ((np.arange(y0, y1)[:, None] + offsets[None, :]).ravel() - center[1]) / radius
    inside = ys[:, None] ** 2 + xs[None, :] ** 2 < 1.0
    s = offsets.size
    coverage = inside.reshape(y1 - y0, s, x1 - x0, s).mean(axis=(1, 3))
    coverage.flags.writeable = False
    return (slice(y0, y1), slice(x0, x1)), coverage


def render_chrome_sphere(
    shape: tuple[int, int],
    center: tuple[float, float],
    radius: float,
    light_directions: np.ndarray,
    *,
    light_angular_radius_deg: float = 1.5,
    light_radiance: float = 50.0,
    ambient: float = 0.02,
    supersample: int = 4,
) -> np.ndarray:
    """Render a mirror sphere under small disc-shaped lights.

    A sub-pixel sample on the sphere reflects the view vector ``v = (0, 0, 1)`` into
    ``r = 2 (n.v) n - v``; it sees ``light_radiance`` where ``r`` falls inside a light's disc of
    angular radius ``light_angular_radius_deg`` (with a narrow linear ramp at the disc's edge) and
    ``ambient`` everywhere on the sphere. Each pixel averages an ``s x s`` grid of sub-pixel samples
    for the outline and a finer grid for the highlight (one sub-sample spans at most a quarter of
    the disc radius), so both are anti-aliased and the highlight centroid moves smoothly with the
    light.
    The background is 0.

    Parameters
    ----------
    shape : (H, W)
        Image size.
    center : (x, y)
        Sphere centre in pixels.
    radius : float
        Sphere radius in pixels.
    light_directions : ndarray of shape (n, 3)
        Directions toward the lights.
    light_angular_radius_deg : float
        Angular radius of each light's disc, degrees.
    light_radiance : float
        Radiance seen in a light's disc.
    ambient : float
        Radiance reflected everywhere else on the sphere.
    supersample : int
        Sub-pixel grid size ``s``.

    Returns
    -------
    ndarray of shape (n, H, W)
    """
    lights = _normalise_lights(light_directions)
    if light_angular_radius_deg <= 0:
        raise ValueError(
            f"light_angular_radius_deg must be positive, got {light_angular_radius_deg}"
        )
    out = np.zeros((lights.shape[0], shape[0], shape[1]))
    geometry = _chrome_coverage(
        (int(shape[0]), int(shape[1])),
        (float(center[0]), float(center[1])),
        float(radius),
        int(supersample),
    )
    if geometry is None:
        return out
    box, coverage = geometry
    out[:, box[0], box[1]] = ambient * coverage
    disc = np.deg2rad(light_angular_radius_deg)
    for i, light in enumerate(lights):
        highlight = _chrome_highlight(shape, center, radius, light, disc, supersample)
        if highlight is not None:
            (rows, cols), values = highlight
            out[i, rows, cols] += light_radiance * values
    return out


def _chrome_highlight(
    shape: tuple[int, int],
    center: tuple[float, float],
    radius: float,
    light: np.ndarray,
    disc: float,
    supersample: int,
) -> tuple[tuple[slice, slice], np.ndarray] | None:
    """Share of each pixel whose reflected view vector falls inside the light's disc.

    The highlight is small (a fraction of a pixel on a small sphere), so it gets its own sub-pixel
    grid, fine enough that one sub-sample spans at most a quarter of the disc's angular radius; the
    disc edge is a linear ramp one sub-sample wide, so the highlight moves smoothly with the light.
    The lens's point spread function (a Gaussian of ``_HIGHLIGHT_PSF_SIGMA`` pixels) is applied on
    that grid before pixel integration: without it a sub-pixel highlight would land in one or two
    pixels and its centroid would snap to pixel centres, as it would on a real sensor with no blur.
    Returns the pixel box and its (bh, bw) values, or None when the highlight is off the sphere.
    """
    half = light + _VIEW
    half = half / np.linalg.norm(half)
    if half[2] <= 1e-6:
        return None
    grid = _highlight_grid(shape, center, radius, half, disc, supersample)
    if grid is None:
        return None
    dx, dy, nz = grid.normals
    # Reflected view vector r = 2 (n.v) n - v, v = (0, 0, 1).
    cos_angle = 2.0 * nz * (dx * light[0] + dy * light[1] + nz * light[2]) - light[2]
    return grid.box, grid.pixel_share(np.arccos(np.clip(cos_angle, -1.0, 1.0)), disc)


@dataclass(frozen=True)
class _HighlightGrid:
    """The fine sub-pixel grid around a mirror point (see :func:`_chrome_highlight`)."""

    box: tuple[slice, slice]
    fine: int
    ramp: float
    inside: np.ndarray
    normals: tuple[np.ndarray, np.ndarray, np.ndarray]  # sphere normal (dx, dy, nz) per sample

    def pixel_share(self, angle: np.ndarray, disc: float) -> np.ndarray:
        """Each pixel's share of samples within ``disc`` (linear ramp, lens blur), (bh, bw)."""
        weight = np.where(self.inside, np.clip((disc - angle) / self.ramp + 0.5, 0.0, 1.0), 0.0)
        sigma = _HIGHLIGHT_PSF_SIGMA * self.fine
        weight = cv2.GaussianBlur(
            weight, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_CONSTANT
        )
        rows, cols = self.box
        shape = (rows.stop - rows.start, self.fine, cols.stop - cols.start, self.fine)
        return weight.reshape(shape).mean(axis=(1, 3))


def _highlight_grid(
    shape: tuple[int, int],
    center: tuple[float, float],
    radius: float,
    mirror_normal: np.ndarray,
    disc: float,
    supersample: int,
) -> _HighlightGrid | None:
    """Sub-pixel grid over the highlight of a disc of angular radius ``disc`` (None: off image)."""
    h, w = shape
    # The mirror point and the reflected vector's angular change per pixel there: a normal turns by
    # 1/radius per pixel (1/(radius nz) radially), the reflection by twice that.
    px = center[0] + radius * mirror_normal[0]
    py = center[1] - radius * mirror_normal[1]
    per_pixel = 2.0 / (radius * mirror_normal[2])
    fine = int(np.clip(np.ceil(4.0 * per_pixel / disc), supersample, 32))
    # Inside the disc the normal stays within half the disc (plus the ramp) of the bisector; the
    # orthographic projection moves the sphere point by at most radius times that angle.
    reach = radius * (0.5 * disc + per_pixel / fine) + 2.0 + 3.0 * _HIGHLIGHT_PSF_SIGMA
    x0, x1 = max(int(np.floor(px - reach)), 0), min(int(np.ceil(px + reach)) + 1, w)
    y0, y1 = max(int(np.floor(py - reach)), 0), min(int(np.ceil(py + reach)) + 1, h)
    if x0 >= x1 or y0 >= y1:
        return None
    offsets = _subpixel_offsets(fine)
    xs = (np.arange(x0, x1)[:, None] + offsets[None, :]).ravel()  # (bw * fine,)
    ys = (np.arange(y0, y1)[:, None] + offsets[None, :]).ravel()
    dx, dy = np.broadcast_arrays(
        (xs[None, :] - center[0]) / radius, -(ys[:, None] - center[1]) / radius
    )
    d2 = dx * dx + dy * dy
    nz = np.sqrt(np.clip(1.0 - d2, 0.0, None))
    return _HighlightGrid(
        (slice(y0, y1), slice(x0, x1)), fine, per_pixel / fine, d2 < 1.0, (dx, dy, nz)
    )
