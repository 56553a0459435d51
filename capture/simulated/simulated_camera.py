"""The simulated camera: renders the scene under the lights the simulated controller has lit.

It writes real 14-bit DNG files, with injectable faults (timeouts, truncated files).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ps_lab.capture.camera_devices import FAULT_KINDS, CameraDevice
from ps_lab.errors import CameraError
from ps_lab.io.camera import CameraModel
from ps_lab.io.dng import write_dng
from ps_lab.render import PointLights, render_scene
from ps_lab.render.lens import distort_image

__all__ = ["SimulatedCamera"]

log = logging.getLogger("ps_lab.capture.camera_devices")


class LightStateLike(Protocol):
    """What the simulated camera needs from the simulated controller's state."""

    lit: frozenset[int]
    level: int


RenderFunction = Callable[[Any, np.ndarray, np.ndarray], np.ndarray]


def _default_render(
    scene: Any,
    light_directions: np.ndarray,
    light_intensities: np.ndarray,
    *,
    point_lights: PointLights | None = None,
) -> np.ndarray:
    if len(light_directions) == 0:  # the dark frame: no light, no intensities to pass
        return render_scene(scene, np.zeros((0, 3)))
    return render_scene(scene, light_directions, light_intensities, point_lights=point_lights)


def _parse_faults(faults: Iterable[Mapping[str, Any]]) -> dict[int, str]:
    by_count: dict[int, str] = {}
    for fault in faults:
        kind = fault.get("kind")
        at = fault.get("at")
        if kind not in FAULT_KINDS:
            raise CameraError(f"unknown camera fault kind {kind!r}; expected one of {FAULT_KINDS}")
        if isinstance(at, bool) or not isinstance(at, int) or at < 1:
            raise CameraError(
                f"camera fault {kind!r} needs 'at' = a capture count >= 1, got {at!r}"
            )
        extra = set(fault) - {"kind", "at"}
        if extra:
            raise CameraError(f"camera fault {kind!r}: unknown key(s) {sorted(extra)}")
        by_count[at] = kind
    return by_count


class SimulatedCamera(CameraDevice):
    """A simulated RAW camera looking at a rendered scene, lit by the simulated controller.

    Each capture asks ``light_state()`` which lights are lit and at which PWM level, renders
    the scene under exactly those lights, and simulates the sensor (all in DN):

    ``mean = radiance * exposure_s * gain``; with shot noise, ``Poisson(mean / dn_per_electron)
    * dn_per_electron``; plus ``N(0, read_noise_dn^2)``; plus ``black_level``; rounded and
    clipped to ``[0, white_level]``.

    The scene's (H, W) grid becomes a (2H, 2W) RGGB mosaic in which each 2x2 block samples the
    same scene pixel (its R, G, G, B), so :func:`~ps_lab.io.raw.load_raw` (half-size)
    returns the scene grid. Noise is drawn independently for each of the four photosites from
    ``numpy.random.default_rng([seed, frame_index])``: a re-shot frame is byte-identical.

    Parameters
    ----------
    scene : Scene
        What :func:`ps_lab.render.render_scene` renders.
    light_directions : ndarray of shape (N, 3)
        True direction of each light (light i is row i - 1).
    light_intensities : ndarray of shape (N, 3) or (N,), optional
        True RGB intensity of each light at level 255; ones by default.
    light_state : callable
        Returns an object with ``lit`` (frozenset of 1-based light numbers) and ``level``
        (0..255, scales every lit light's intensity by ``level / 255``).
    exposure_s : float
        Exposure time written into each DNG.
    black_level, white_level : int
        Sensor offset and saturation level in DN (14-bit by default).
    gain : float
        DN per unit radiance per second of exposure.
    read_noise_dn : float
        Standard deviation of the Gaussian read noise in DN.
    shot_noise : bool
        Add photon shot noise (Poisson in electrons).
    dn_per_electron : float
        Conversion gain for the shot noise.
    seed : int
        Noise seed of the whole run; frame ``k`` uses ``[seed, k]``.
    faults : iterable of mappings
        ``{"kind": "timeout" | "truncated", "at": n}``: the n-th capture call (1-based) times
        out after ``timeout_s`` or writes a truncated DNG.
    timeout_s : float
        Capture timeout (how long an injected timeout waits before failing).
    render : callable, optional
        ``render(scene, directions (k, 3), intensities (k, 3)) -> (H, W, 3)``; defaults to
        :func:`ps_lab.render.render_scene` (tests inject a stand-in).
    point_lights : PointLights, optional
        The N lights as LEDs at a finite distance (row i - 1 is light i); the renderer then
        receives ``point_lights=`` the lit ones.
    lens : CameraModel, optional
        The lens's distortion, applied to every rendered frame (rig file ``[lens] distortion``):
        the scene's ground truth stays in undistorted pixels.

    """

    driver = "simulated"

    def __init__(
        self,
        scene: Any,
        light_directions: np.ndarray,
        light_intensities: np.ndarray | None,
        light_state: Callable[[], LightStateLike],
        *,
        exposure_s: float,
        black_level: int = 512,
        white_level: int = 16383,
        gain: float = 200_000.0,
        read_noise_dn: float = 2.0,
        shot_noise: bool = True,
        dn_per_electron: float = 0.5,
        seed: int = 0,
        faults: Iterable[Mapping[str, Any]] = (),
        timeout_s: float = 10.0,
        render: RenderFunction | None = None,
        point_lights: PointLights | None = None,
        lens: CameraModel | None = None,
    ) -> None:
        super().__init__(timeout_s=timeout_s)
        directions = np.asarray(light_directions, dtype=np.float64)
        if directions.ndim != 2 or directions.shape[1] != 3 or directions.shape[0] < 1:
            raise CameraError(f"light_directions must have shape (N, 3), got {directions.shape}")
        n = directions.shape[0]
        if light_intensities is None:
            intensities = np.ones((n, 3))
        else:
            intensities = np.asarray(light_intensities, dtype=np.float64)
            if intensities.ndim == 1:
                intensities = np.repeat(intensities[:, None], 3, axis=1)
            if intensities.shape != (n, 3):
                raise CameraError(
                    f"light_intensities must have shape ({n}, 3) or ({n},), got {intensities.shape}"
                )
        if not (math.isfinite(exposure_s) and exposure_s > 0):
            raise CameraError(f"exposure_s must be positive, got {exposure_s}")
        if not 0 <= black_level < white_level <= 65535:
            raise CameraError(
                f"need 0 <= black_level < white_level <= 65535, got {black_level}, {white_level}"
            )
        if not gain > 0 or read_noise_dn < 0 or not dn_per_electron > 0:
            raise CameraError("gain and dn_per_electron must be positive, read_noise_dn >= 0")
        self.scene = scene
        self.light_directions = directions
        self.light_intensities = intensities
        self.point_lights = point_lights
        self.light_state = light_state
        self.exposure_s = float(exposure_s)
        self.black_level = int(black_level)
        self.white_level = int(white_level)
        self.gain = float(gain)
        self.read_noise_dn = float(read_noise_dn)
        self.shot_noise = bool(shot_noise)
        self.dn_per_electron = float(dn_per_electron)
        self.seed = int(seed)
        self.faults = _parse_faults(faults)
        self._render = render or _default_render
        self.lens = lens

    @property
    def settings(self) -> dict[str, Any]:  # noqa: D102 - documented on the base class
        return {
            **super().settings,
            "exposure_s": self.exposure_s,
            "black_level": self.black_level,
            "white_level": self.white_level,
            "gain": self.gain,
            "read_noise_dn": self.read_noise_dn,
            "shot_noise": self.shot_noise,
            "dn_per_electron": self.dn_per_electron,
            "seed": self.seed,
        }

    @property
    def linear_scale(self) -> float:
        """Loaded value per unit radiance: ``exposure_s * gain / (white_level - black_level)``.

        ``load_raw`` of a noise-free, unclipped frame equals ``radiance * linear_scale`` up to
        the rounding to whole DN.
        """
        return self.exposure_s * self.gain / (self.white_level - self.black_level)

    def radiance(self, lit: Iterable[int], level: int = 255) -> np.ndarray:
        """Render the scene under lights ``lit`` (1-based) at PWM ``level``: (H, W, 3) float64."""
        indices = sorted({int(i) for i in lit})
        n = self.light_directions.shape[0]
        bad = [i for i in indices if not 1 <= i <= n]
        if bad:
            raise CameraError(f"simulated controller reports light(s) {bad} lit; the rig has {n}")
        if not 0 <= int(level) <= 255:
            raise CameraError(f"simulated controller reports level {level}, expected 0..255")
        zero_based = np.array([i - 1 for i in indices], dtype=np.intp)
        directions = self.light_directions[zero_based].reshape(-1, 3)
        intensities = self.light_intensities[zero_based].reshape(-1, 3) * (int(level) / 255.0)
        if self.point_lights is None:
            radiance = self._render(self.scene, directions, intensities)
        else:
            lit_leds = self.point_lights.select(zero_based)
            radiance = self._render(self.scene, directions, intensities, point_lights=lit_leds)
        radiance = np.asarray(radiance, dtype=np.float64)
        if radiance.ndim == 2:
            radiance = np.repeat(radiance[..., None], 3, axis=2)
        if radiance.ndim != 3 or radiance.shape[2] != 3:
            raise CameraError(f"renderer returned shape {radiance.shape}, expected (H, W, 3)")
        if self.lens is not None:
            radiance = distort_image(radiance, self.lens).astype(np.float64)
        return radiance

    def sensor_mosaic(self, radiance: np.ndarray, frame_index: int) -> np.ndarray:
        """Simulate the sensor on a rendered (H, W, 3) radiance image: (2H, 2W) uint16 RGGB.

        Deterministic for a given ``frame_index`` (noise from ``default_rng([seed, frame_index])``).
        """
        height, width, _ = radiance.shape
        mean = np.empty((2 * height, 2 * width), dtype=np.float64)
        mean[0::2, 0::2] = radiance[..., 0]
        mean[0::2, 1::2] = radiance[..., 1]
        mean[1::2, 0::2] = radiance[..., 1]
        mean[1::2, 1::2] = radiance[..., 2]
        mean *= self.exposure_s * self.gain
        np.maximum(mean, 0.0, out=mean)
        rng = np.random.default_rng([self.seed, int(frame_index)])
        if self.shot_noise:
            # Cap the Poisson mean far above the white level: the value clips anyway.
            cap = 4.0 * self.white_level / self.dn_per_electron
            electrons = rng.poisson(np.minimum(mean / self.dn_per_electron, cap))
            signal = electrons * self.dn_per_electron
        else:
            signal = mean
        if self.read_noise_dn > 0:
            signal = signal + rng.normal(0.0, self.read_noise_dn, size=signal.shape)
        raw = np.rint(signal + self.black_level)
        return np.clip(raw, 0, self.white_level).astype(np.uint16)

    def _do_capture(self, path: Path, frame_index: int, label: str) -> float | None:
        fault = self.faults.get(self.captures)
        if fault == "timeout":
            log.warning("simulated camera: injected timeout on capture %d", self.captures)
            time.sleep(self.timeout_s)
            raise CameraError(
                f"simulated camera timed out after {self.timeout_s:g} s capturing {label} "
                f"(injected fault at capture {self.captures})"
            )
        state = self.light_state()
        radiance = self.radiance(state.lit, state.level)
        mosaic = self.sensor_mosaic(radiance, frame_index)
        write_dng(
            path,
            mosaic,
            black_level=self.black_level,
            white_level=self.white_level,
            cfa="RGGB",
            exposure_s=self.exposure_s,
            make="ps-lab",
            model="simulated camera",
        )
        if fault == "truncated":
            log.warning("simulated camera: injected truncated file on capture %d", self.captures)
            size = path.stat().st_size
            with open(path, "r+b") as handle:
                handle.truncate(max(1, size // 2))
        return self.exposure_s


