"""A second near-light rig, apart from the rest of the renderer: LEDs, spheres, object, table.

This module shares no geometry with :mod:`ps_lab.render.near_shading` or :mod:`ps_lab.geometry`:
it has its own world frame, its own sphere, shadow and mirror code, and writes a plain image
folder of 16-bit PNGs, so the near-light path can be checked on a scene it was not written against.

World frame (pixel units): the table is the plane ``z = 0``, z points up toward the camera, x to
the image's right, y to the image's top; the world origin lies on the table below the pixel
``origin_px`` (column, row), which is the dome's centre. The camera is orthographic, looking down
``-z``; pixel (row, col) sees the vertical line ``x = col - origin_px[0]``, ``y = origin_px[1] -
row``.

The scene (:class:`TableRig`): 24 LEDs on rings of a dome centred on the table (isotropic and of
equal radiant intensity by default; optionally ``cos^mu`` beams whose axes are aimed at the dome
centre to within a random tilt, and outputs that differ by a random factor); two chrome spheres resting on the table (centres at ``z = r``); the object,
a height field ``z = h(x, y) >= 0`` standing on the table inside a disc (its top below the
spheres' centres); no matte sphere. Shading: Lambert plus a Blinn-Phong lobe, ``1/d^2``
fall-off, cast shadows marched over the height field. The far twin lights the same scene from
the same directions (dome centre to LED) at infinity, with the irradiance the LEDs give the dome
centre. :func:`write_board_frames` renders the flat-field target: a flat matte board on the
table filling the frame, under every LED.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

__all__ = ["TableRig", "chrome_frames", "render_board", "render_table_rig", "write_board_frames",
           "write_table_rig"]


@dataclass(frozen=True)
class TableRig:
    """The rig: image, dome, spheres, object, sensor.

    Attributes
    ----------
    shape : (H, W)
    origin_px : (col, row)
        Pixel above the dome's centre (the world origin on the table).
    dome_radius : float
        LED distance from the dome centre (pixels).
    rings : tuple of (elevation_deg, count, azimuth_offset_deg)
        LED rings of the dome.
    led_radius : float
        Radius of each LED's emitting disc (pixels), seen in the chrome spheres.
    spheres : tuple of (col, row, radius)
        Chrome spheres resting on the table.
    object_center : (col, row)
    object_radius : float
        The object's footprint is a disc of this radius.
    object_top : float
        The object's largest height above the table.
    albedo, specular, shininess : float
    led_radiance : float
        Radiance of an LED's disc (of full scale); ``blur_px``: the lens's Gaussian blur of the
        spheres' images.
    peak : float
        Image value of the brightest object pixel (of 1.0 = 65535).
    full_well : float
        Electrons at full scale (shot noise); ``read_noise`` in units of full scale.
    seed : int
    beam_mu : float
        Each LED's radiance falls off as ``cos^mu`` of the angle from its optical axis (0:
        isotropic, 1: a Lambertian emitter).
    beam_tilt_deg : float
        Each axis points at the dome centre, turned by a random angle up to this.
    output_spread : float
        Each LED's output is ``1 + U(-spread, spread)`` (seeded).
    """

    shape: tuple[int, int] = (360, 480)
    origin_px: tuple[float, float] = (236.0, 184.0)
    dome_radius: float = 540.0
    rings: tuple[tuple[float, int, float], ...] = ((28.0, 8, 0.0), (48.0, 8, 22.5),
                                                   (70.0, 8, 10.0))
    led_radius: float = 10.0
    spheres: tuple[tuple[float, float, float], ...] = ((60.0, 296.0, 40.0),
                                                       (420.0, 62.0, 40.0))
    object_center: tuple[float, float] = (244.0, 176.0)
    object_radius: float = 90.0
    object_top: float = 30.0
    albedo: float = 0.8
    specular: float = 0.05
    shininess: float = 100.0
    led_radiance: float = 8.0
    blur_px: float = 0.8
    peak: float = 0.8
    full_well: float = 30000.0
    read_noise: float = 1.5e-4
    seed: int = 24
    focal_px: float | None = None
    principal_px: tuple[float, float] | None = None
    extra: dict = field(default_factory=dict)
    beam_mu: float = 0.0
    beam_tilt_deg: float = 0.0
    output_spread: float = 0.0

    def camera_centre(self) -> np.ndarray | None:
        """(3,) world position of a perspective camera's centre (None: orthographic).

        Above the principal point, at the height where the spheres' centres are imaged at scale 1.
        """
        if self.focal_px is None:
            return None
        h, w = self.shape
        cx, cy = self.principal_px or ((w - 1) / 2.0, (h - 1) / 2.0)
        return np.array([cx - self.origin_px[0], self.origin_px[1] - cy,
                         self.focal_px + self.spheres[0][2]])

    def rays(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Unit directions (..., 3) of pixels' viewing rays, away from the camera."""
        h, w = self.shape
        cx, cy = self.principal_px or ((w - 1) / 2.0, (h - 1) / 2.0)
        d = np.stack([cols - cx, cy - rows, np.full(np.shape(rows), -float(self.focal_px))],
                     axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def led_positions(self) -> np.ndarray:
        """(24, 3) world positions of the LEDs."""
        out = []
        for elevation, count, offset in self.rings:
            e = np.radians(elevation)
            for k in range(count):
                a = np.radians(offset + 360.0 * k / count)
                out.append([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        return self.dome_radius * np.array(out)

    def led_axes(self) -> np.ndarray:
        """(24, 3) unit optical axes: toward the dome centre, turned by up to ``beam_tilt_deg``."""
        leds = self.led_positions()
        axes = -leds / np.linalg.norm(leds, axis=1, keepdims=True)
        if self.beam_tilt_deg <= 0:
            return axes
        rng = np.random.default_rng(self.seed + 101)
        tilt = np.radians(self.beam_tilt_deg) * np.sqrt(rng.uniform(0, 1, len(axes)))
        turn = rng.uniform(0, 2 * np.pi, len(axes))
        out = []
        for a, t, phi in zip(axes, tilt, turn, strict=True):
            e1 = np.cross(a, [0.0, 0.0, 1.0] if abs(a[2]) < 0.9 else [1.0, 0.0, 0.0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(a, e1)
            out.append(np.cos(t) * a + np.sin(t) * (np.cos(phi) * e1 + np.sin(phi) * e2))
        return np.array(out)

    def led_outputs(self) -> np.ndarray:
        """(24,) relative outputs (radiant intensity on the axis), ``1 +- output_spread``."""
        n = len(self.led_positions())
        if self.output_spread <= 0:
            return np.ones(n)
        rng = np.random.default_rng(self.seed + 202)
        return 1.0 + rng.uniform(-self.output_spread, self.output_spread, n)

    def led_emission(self, j: int, toward: np.ndarray) -> np.ndarray:
        """LED j's radiant intensity toward points (m, 3): output times ``cos^mu``."""
        led = self.led_positions()[j]
        w = np.asarray(toward, float) - led[None, :]
        cos = w @ self.led_axes()[j] / np.linalg.norm(w, axis=1)
        beam = np.clip(cos, 0.0, None) ** self.beam_mu if self.beam_mu else np.ones(len(w))
        return self.led_outputs()[j] * beam

    def pixel_xy(self) -> tuple[np.ndarray, np.ndarray]:
        """World x, y of every pixel centre, each (H, W)."""
        h, w = self.shape
        rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
        return cols - self.origin_px[0], self.origin_px[1] - rows


def _object_height(rig: TableRig, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height above the table: a rounded base with three bumps and a groove, 0 at the outline."""
    ox = rig.object_center[0] - rig.origin_px[0]
    oy = rig.origin_px[1] - rig.object_center[1]
    u, v = (x - ox) / rig.object_radius, (y - oy) / rig.object_radius
    rho2 = u * u + v * v
    inside = np.clip(1.0 - rho2, 0.0, None)
    base = 0.55 * inside ** 1.5
    bumps = (0.30 * np.exp(-((u - 0.30) ** 2 + (v - 0.20) ** 2) / 0.06)
             + 0.22 * np.exp(-((u + 0.35) ** 2 + (v - 0.10) ** 2) / 0.04)
             + 0.18 * np.exp(-((u + 0.05) ** 2 + (v + 0.40) ** 2) / 0.05))
    groove = -0.05 * np.exp(-((u - v * 0.3) ** 2) / 0.02) * inside
    return rig.object_top * (base + bumps * inside ** 2 + groove)


def _object(rig: TableRig) -> tuple[np.ndarray, ...]:
    """Mask (H, W), heights (H, W), unit normals (H, W, 3), world x and y (H, W) of the object.

    x, y: the surface point each pixel sees (perspective: where its ray meets the height field).
    """
    x, y = rig.pixel_xy()
    eye = rig.camera_centre()
    if eye is not None:
        h, w = rig.shape
        rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
        d = rig.rays(rows, cols)
        z = np.zeros(rows.shape)
        for _ in range(60):  # z = h(ray(z)): a contraction (slopes x field of view << 1)
            t = (z - eye[2]) / d[..., 2]
            x, y = eye[0] + t * d[..., 0], eye[1] + t * d[..., 1]
            z = _object_height(rig, x, y)
    ox = rig.object_center[0] - rig.origin_px[0]
    oy = rig.origin_px[1] - rig.object_center[1]
    mask = np.hypot(x - ox, y - oy) < rig.object_radius - 1.0
    eps = 1e-3
    height = _object_height(rig, x, y)
    gx = (_object_height(rig, x + eps, y) - _object_height(rig, x - eps, y)) / (2 * eps)
    gy = (_object_height(rig, x, y + eps) - _object_height(rig, x, y - eps)) / (2 * eps)
    normals = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return mask, height, normals, x, y


def _shadowed(height: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray, rig: TableRig,
              toward: np.ndarray, far: bool) -> np.ndarray:
    """Points (m,) whose path to the light hits the height field.

    The light is a position, or a direction when ``far``; the field is sampled bilinearly in
    half-pixel steps.
    """
    top = float(height.max())
    hit = np.zeros(x.shape, bool)
    d = np.broadcast_to(toward, (x.size, 3)) if far else toward[None, :] - np.column_stack(
        [x, y, z])
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    horiz = np.hypot(d[:, 0], d[:, 1])
    step = 0.5 / np.maximum(horiz, 1e-6)
    t = step * 2.0
    alive = np.ones(x.shape, bool)
    for _ in range(4000):
        px, py, pz = x + t * d[:, 0], y + t * d[:, 1], z + 0.3 + t * d[:, 2]
        alive &= pz <= top
        if not alive.any():
            break
        col = px + rig.origin_px[0]
        row = rig.origin_px[1] - py
        sample = ndimage.map_coordinates(height, [row, col], order=1, mode="constant")
        hit |= alive & (sample > pz)
        alive &= ~hit
        t = t + step
    return hit


def _object_images(rig: TableRig, lights: np.ndarray, far: bool) -> np.ndarray:
    """Radiance of the object (n, H, W); 0 off the object.

    ``lights`` (n, 3): positions, or unit directions when ``far`` (irradiance of an LED at the
    dome centre).
    """
    mask, height, normals, x, y = _object(rig)
    rows, cols = np.nonzero(mask)
    px, py, pz = x[rows, cols], y[rows, cols], height[rows, cols]
    nrm = normals[rows, cols]
    out = np.zeros((lights.shape[0], *rig.shape))
    points = np.column_stack([px, py, pz])
    eye = rig.camera_centre()
    view = np.array([0.0, 0.0, 1.0]) if eye is None else eye[None, :] - points
    view = view / np.linalg.norm(view, axis=-1, keepdims=True)
    grid = _object_height(rig, *rig.pixel_xy())  # world grid, 1 unit apart, for the shadows
    for j, light in enumerate(lights):
        if far:
            u = np.broadcast_to(light / np.linalg.norm(light), points.shape)
            irradiance = np.full(px.size, rig.led_emission(j, np.zeros((1, 3)))[0]
                                 / rig.dome_radius ** 2)
        else:
            d = light[None, :] - points
            dist2 = np.einsum("mk,mk->m", d, d)
            u = d / np.sqrt(dist2)[:, None]
            irradiance = rig.led_emission(j, points) / dist2
        cos = np.einsum("mk,mk->m", nrm, u)
        half = u + view
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        lobe = (rig.shininess + 8.0) / 8.0 * np.clip(np.einsum("mk,mk->m", nrm, half), 0,
                                                     None) ** rig.shininess
        lit = cos > 0
        lit[lit] &= ~_shadowed(grid, px[lit], py[lit], pz[lit], rig,
                               light if not far else light / np.linalg.norm(light), far)
        value = np.where(lit, irradiance * cos * (rig.albedo + rig.specular * lobe), 0.0)
        out[j, rows, cols] = value
    return out


def _mirror_share(rig, light, far, centre, radius, sub_c, sub_r, col0, row0):
    """Share of an LED's disc seen in the mirror at sub-sample pixels (any shape).

    NaN off the sphere.
    """
    eye = rig.camera_centre()
    if eye is None:
        dx, dy = (sub_c - col0) / radius, (row0 - sub_r) / radius
        inside = dx * dx + dy * dy < 1.0
        nz = np.sqrt(np.clip(1.0 - dx * dx - dy * dy, 0.0, 1.0))
        # mirror of the view vector (0, 0, 1) about n
        rx, ry, rz = 2 * nz * dx, 2 * nz * dy, 2 * nz * nz - 1.0
    else:  # each sub-sample's ray meets the sphere; its mirror image about the normal there
        d = rig.rays(*np.broadcast_arrays(sub_r, sub_c))
        offset = eye - centre
        b = d @ offset
        disc2 = b * b - (offset @ offset - radius * radius)
        inside = disc2 > 0
        t = -b - np.sqrt(np.clip(disc2, 0.0, None))
        n = (eye + t[..., None] * d - centre) / radius
        dx, dy, nz = n[..., 0], n[..., 1], n[..., 2]
        dn = np.einsum("...k,...k->...", d, n)
        rx, ry, rz = (d[..., k] - 2 * dn * n[..., k] for k in range(3))
    if far:
        to = light / np.linalg.norm(light)
        disc = np.arctan(rig.led_radius / rig.dome_radius)
        cos = rx * to[0] + ry * to[1] + rz * to[2]
    else:
        tx = light[0] - (centre[0] + radius * dx)
        ty = light[1] - (centre[1] + radius * dy)
        tz = light[2] - (centre[2] + radius * nz)
        length = np.sqrt(tx * tx + ty * ty + tz * tz)
        disc = np.arctan(rig.led_radius / length)
        cos = (rx * tx + ry * ty + rz * tz) / length
    angle = np.arccos(np.clip(cos, -1.0, 1.0))
    # a disc with a soft edge (a diffuser): full inside 0.8 of its radius, ramp to 1.2
    share = np.clip((1.2 * disc - angle) / (0.4 * disc), 0.0, 1.0)
    return np.where(inside, share, np.nan)


def _chrome_images(rig: TableRig, lights: np.ndarray, far: bool, supersample: int = 8
                   ) -> np.ndarray:
    """Mirror spheres (n, H, W): each sub-sample's reflected view ray against the LED's disc.

    Blurred by the lens at the sub-sample grid, then integrated over each pixel (blur before
    sampling: a centroid of pixel values then has no pixel-locking bias).
    """
    out = np.zeros((lights.shape[0], *rig.shape))
    s = supersample
    offsets = (np.arange(s) + 0.5) / s - 0.5
    for col0, row0, radius in rig.spheres:
        r0, r1 = int(np.floor(row0 - radius)) - 4, int(np.ceil(row0 + radius)) + 5
        c0, c1 = int(np.floor(col0 - radius)) - 4, int(np.ceil(col0 + radius)) + 5
        sub_r = (np.arange(r0, r1)[:, None] + offsets[None, :]).reshape(-1, 1)
        sub_c = (np.arange(c0, c1)[:, None] + offsets[None, :]).reshape(1, -1)
        centre = np.array([col0 - rig.origin_px[0], rig.origin_px[1] - row0, radius])
        for j, light in enumerate(lights):
            share = _mirror_share(rig, light, far, centre, radius, sub_c, sub_r, col0, row0)
            value = np.where(np.isfinite(share), rig.led_radiance * np.nan_to_num(share) + 0.01,
                             0.0)
            value = ndimage.gaussian_filter(value, rig.blur_px * s)
            value = value.reshape(r1 - r0, s, c1 - c0, s).mean(axis=(1, 3))
            block = out[j, r0:r1, c0:c1]
            out[j, r0:r1, c0:c1] = np.maximum(block, value)
    return out


def chrome_frames(rig: TableRig) -> np.ndarray:
    """The chrome spheres alone under every LED (n, H, W), float, before noise and clipping."""
    return _chrome_images(rig, rig.led_positions(), False)


def render_table_rig(rig: TableRig, *, far: bool = False) -> dict:
    """Render the rig (float frames in units of full scale, before noise) and its truth.

    Returns
    -------
    dict
        ``frames`` (n, H, W) (object scaled so its brightest pixel is ``rig.peak``; spheres
        saturate), ``mask``, ``normals`` (H, W, 3; camera frame x right, y up, z toward the
        camera), ``height`` (H, W; above the table), ``leds`` (n, 3; world),
        ``directions`` (n, 3; unit, dome centre to LED).
    """
    leds = rig.led_positions()
    directions = leds / np.linalg.norm(leds, axis=1, keepdims=True)
    lights = directions if far else leds
    objects = _object_images(rig, lights, far)
    mask, height, normals, _, _ = _object(rig)
    # the same exposure for both twins: the near rig's brightest object pixel sets it
    scale = rig.peak / float(rig.extra.get("reference_peak") or objects.max())
    frames = objects * scale + _chrome_images(rig, lights, far)
    return {"frames": frames, "raw_peak": float(objects.max()), "mask": mask, "normals": normals,
            "height": height, "leds": leds, "directions": directions}


def write_table_rig(folder: Path, rig: TableRig, *, far: bool = False,
                    reference_peak: float | None = None) -> dict:
    """Write the rig as an image folder; return :func:`render_table_rig`'s dict.

    ``001.png`` ... (16-bit, shot and read noise, clipped), ``mask.png``, ``normal_gt.npy``, and
    the truth under ``truth/`` (LEDs and heights in the world frame).
    """
    if reference_peak is not None:
        rig = replace(rig, extra={"reference_peak": reference_peak})
    scene = render_table_rig(rig, far=far)
    rng = np.random.default_rng(rig.seed + (1 if far else 0))
    folder = Path(folder)
    (folder / "truth").mkdir(parents=True, exist_ok=True)
    for j, frame in enumerate(scene["frames"]):
        electrons = rng.poisson(np.clip(frame, 0.0, 2.0) * rig.full_well) / rig.full_well
        noisy = electrons + rng.normal(0.0, rig.read_noise, frame.shape)
        value = np.clip(np.round(noisy * 65535.0), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(folder / f"{j + 1:03d}.png"), value)
    cv2.imwrite(str(folder / "mask.png"), scene["mask"].astype(np.uint8) * 255)
    np.save(folder / "normal_gt.npy", scene["normals"].astype(np.float32))
    np.savetxt(folder / "truth" / "led_positions_world.txt", scene["leds"])
    np.save(folder / "truth" / "height_world.npy", scene["height"])
    return scene


def render_board(rig: TableRig, height: float = 0.0) -> dict:
    """A flat matte board at ``height`` above the table filling the frame, under every LED.

    The flat-field target: Lambertian (the rig's albedo), no spheres, no object; float frames
    scaled so the brightest pixel is ``rig.peak``.

    Returns
    -------
    dict
        ``frames`` (n, H, W), ``height`` (the board's, above the table), ``leds`` (n, 3; world).
    """
    h, w = rig.shape
    x, y = rig.pixel_xy()
    eye = rig.camera_centre()
    if eye is not None:  # each pixel's ray meets the board's plane
        rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
        d = rig.rays(rows, cols)
        t = (height - eye[2]) / d[..., 2]
        x, y = eye[0] + t * d[..., 0], eye[1] + t * d[..., 1]
    points = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, float(height))])
    leds = rig.led_positions()
    frames = np.zeros((len(leds), h, w))
    for j, led in enumerate(leds):
        d = led[None, :] - points
        dist2 = np.einsum("mk,mk->m", d, d)
        cos = np.clip(d[:, 2] / np.sqrt(dist2), 0.0, None)
        frames[j] = (rig.albedo * rig.led_emission(j, points) * cos / dist2).reshape(h, w)
    frames *= rig.peak / frames.max()
    return {"frames": frames, "height": float(height), "leds": leds}


def write_board_frames(folder: Path, rig: TableRig, height: float = 0.0, *,
                       noise_seed: int | None = None) -> dict:
    """Write :func:`render_board`'s frames as 16-bit PNGs (``001.png`` ...; shot and read noise).

    ``noise_seed`` (default ``rig.seed + 7``) draws the noise; the LEDs stay the rig's.
    """
    board = render_board(rig, height)
    rng = np.random.default_rng(rig.seed + 7 if noise_seed is None else noise_seed)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for j, frame in enumerate(board["frames"]):
        electrons = rng.poisson(np.clip(frame, 0.0, 2.0) * rig.full_well) / rig.full_well
        noisy = electrons + rng.normal(0.0, rig.read_noise, frame.shape)
        value = np.clip(np.round(noisy * 65535.0), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(folder / f"{j + 1:03d}.png"), value)
    return board
