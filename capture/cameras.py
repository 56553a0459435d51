"""Cameras behind one base class: a simulated sensor that writes DNG, and a watched folder.

Every camera is used the same way::

    with camera:
        frame = camera.capture(run / "frames" / "0001-L01-r0.dng", frame_index=1)

:meth:`Camera.capture` is a template method: it validates the target, logs, times the shot,
calls the driver's ``_do_capture`` hook and checks that a non-empty file arrived. Drivers raise
:class:`~ps_lab.errors.CameraError` with a one-line reason on any failure or timeout.

The gphoto2 driver lives in :mod:`ps_lab.capture.gphoto2_camera` so that this module never
needs python-gphoto2.
"""

from __future__ import annotations

import fnmatch
import logging
import math
import os
import shutil
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol

import numpy as np

from ps_lab.capture.dng import write_dng
from ps_lab.capture.raw import RAW_SUFFIXES, read_exposure
from ps_lab.errors import CameraError, PsLabError

__all__ = [
    "FAULT_KINDS",
    "Camera",
    "CapturedFrame",
    "FolderCamera",
    "SimulatedCamera",
]

log = logging.getLogger(__name__)

FAULT_KINDS = ("timeout", "truncated")


@dataclass(frozen=True)
class CapturedFrame:
    """One frame that arrived on disk.

    Attributes
    ----------
    path : Path
        The frame file.
    exposure_s : float
        Exposure time in seconds (as set, or as read from the file).
    started, finished : float
        Epoch seconds around the capture (trigger to file on disk).

    """

    path: Path
    exposure_s: float
    started: float
    finished: float


class Camera(ABC):
    """Abstract camera: :meth:`capture` validates and times, ``_do_capture`` shoots.

    Parameters
    ----------
    timeout_s : float
        How long a capture may take before :class:`CameraError`.

    """

    #: Short driver name used in log lines and in :attr:`settings`.
    driver = "camera"

    def __init__(self, *, timeout_s: float = 30.0) -> None:
        if not timeout_s > 0:
            raise CameraError(f"camera timeout must be positive, got {timeout_s}")
        self.timeout_s = float(timeout_s)
        self.captures = 0  # capture attempts so far (failed ones included)
        self._closed = False

    # -- public API -----------------------------------------------------------------------
    def capture(
        self,
        path: str | os.PathLike[str],
        *,
        frame_index: int | None = None,
        label: str | None = None,
    ) -> CapturedFrame:
        """Shoot one frame into ``path``.

        Parameters
        ----------
        path : path-like
            Target file; its folder must exist. An existing file is replaced.
        frame_index : int, optional
            Index of the frame in the capture plan (a simulated camera seeds its noise with
            it, so a re-shot frame is identical). Defaults to the number of earlier captures.
        label : str, optional
            What the frame is, for log lines and operator prompts (e.g. ``"light 3"``).

        Returns
        -------
        CapturedFrame

        Raises
        ------
        CameraError
            When the camera is closed, the target folder is missing, the capture fails or times
            out, or no non-empty file arrived.

        """
        if self._closed:
            raise CameraError(f"{self.driver} camera is closed")
        path = Path(path)
        if not path.parent.is_dir():
            raise CameraError(f"cannot capture to {path}: folder {path.parent} does not exist")
        if path.is_dir():
            raise CameraError(f"cannot capture to {path}: it is a folder")
        index = self.captures if frame_index is None else int(frame_index)
        if index < 0:
            raise CameraError(f"frame index must be >= 0, got {index}")
        self.captures += 1
        label = label or f"frame {index}"
        log.info("%s camera: capturing %s -> %s", self.driver, label, path)
        started = time.time()
        try:
            exposure = self._do_capture(path, index, label)
        except PsLabError:
            raise
        except OSError as exc:
            raise CameraError(f"capture of {label} to {path} failed: {exc}") from exc
        finished = time.time()
        if not path.is_file():
            raise CameraError(f"{self.driver} camera produced no file at {path}")
        if path.stat().st_size == 0:
            raise CameraError(f"{self.driver} camera produced an empty file at {path}")
        if exposure is None:
            exposure = self._fallback_exposure(path)
        log.debug("%s camera: %s done in %.3f s", self.driver, label, finished - started)
        return CapturedFrame(
            path=path, exposure_s=float(exposure), started=started, finished=finished
        )

    @property
    def settings(self) -> dict[str, Any]:
        """JSON-serialisable description of the settings that shape the frames."""
        return {"driver": self.driver, "timeout_s": self.timeout_s}

    def close(self) -> None:
        """Release the camera; further captures raise :class:`CameraError`. Idempotent."""
        if not self._closed:
            self._closed = True
            self._do_close()

    def __enter__(self) -> Camera:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- driver hooks ---------------------------------------------------------------------
    @abstractmethod
    def _do_capture(self, path: Path, frame_index: int, label: str) -> float | None:
        """Write the frame to ``path``; return its exposure in seconds if the driver knows it."""

    def _do_close(self) -> None:  # noqa: B027 - optional hook, most drivers hold nothing
        """Release driver resources."""

    def _fallback_exposure(self, path: Path) -> float:
        exposure = read_exposure(path) if path.suffix.lower() in RAW_SUFFIXES else None
        if exposure is None:
            log.warning(
                "%s camera: exposure of %s unknown; assuming 1 s (frames are then not rescaled)",
                self.driver,
                path.name,
            )
            return 1.0
        return exposure


# ------------------------------------------------------------------------------------------
# Simulated camera
# ------------------------------------------------------------------------------------------


class LightStateLike(Protocol):
    """What the simulated camera needs from the simulated controller's state."""

    lit: frozenset[int]
    level: int


RenderFunction = Callable[[Any, np.ndarray, np.ndarray], np.ndarray]


def _default_render(
    scene: Any, light_directions: np.ndarray, light_intensities: np.ndarray
) -> np.ndarray:
    # Imported here: the renderer is only needed when a rig file selects the simulated camera.
    from ps_lab.capture.render import render_scene

    if len(light_directions) == 0:  # the dark frame: no light, no intensities to pass
        return render_scene(scene, np.zeros((0, 3)))
    return render_scene(scene, light_directions, light_intensities)


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


class SimulatedCamera(Camera):
    """A simulated RAW camera looking at a rendered scene, lit by the simulated controller.

    Each capture asks ``light_state()`` which lights are lit and at which PWM level, renders
    the scene under exactly those lights, and simulates the sensor (all in DN):

    ``mean = radiance * exposure_s * gain``; with shot noise, ``Poisson(mean / dn_per_electron)
    * dn_per_electron``; plus ``N(0, read_noise_dn^2)``; plus ``black_level``; rounded and
    clipped to ``[0, white_level]``.

    The scene's (H, W) grid becomes a (2H, 2W) RGGB mosaic in which each 2x2 block samples the
    same scene pixel (its R, G, G, B), so :func:`~ps_lab.capture.raw.load_raw` (half-size)
    returns the scene grid. Noise is drawn independently for each of the four photosites from
    ``numpy.random.default_rng([seed, frame_index])``: a re-shot frame is byte-identical.

    Parameters
    ----------
    scene : Scene
        What :func:`ps_lab.capture.render.render_scene` renders.
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
        :func:`ps_lab.capture.render.render_scene` (tests inject a stand-in).

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
        radiance = np.asarray(self._render(self.scene, directions, intensities), dtype=np.float64)
        if radiance.ndim == 2:
            radiance = np.repeat(radiance[..., None], 3, axis=2)
        if radiance.ndim != 3 or radiance.shape[2] != 3:
            raise CameraError(f"renderer returned shape {radiance.shape}, expected (H, W, 3)")
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


# ------------------------------------------------------------------------------------------
# Folder camera
# ------------------------------------------------------------------------------------------


class FolderCamera(Camera):
    """A camera seen through a folder: tethering software or a card reader drops files there.

    Each capture (optionally) prompts the operator, then waits for the next new file in
    ``folder`` whose name matches ``pattern`` and whose size is non-zero and unchanged over
    two consecutive polls, and moves (or copies) it to the target path. Files present when the
    camera is created, hidden files (leading ``.``) and files already taken are ignored.

    Parameters
    ----------
    folder : path-like
        The watched folder; must exist.
    timeout_s : float
        How long to wait for a new file.
    pattern : str or sequence of str
        Glob pattern(s) on the file name (case-insensitive), e.g. ``"*.CR2"``.
    prompt : callable, optional
        Called with a message such as ``"press the shutter for light 3"`` before waiting.
    poll_s : float
        Polling interval.
    copy : bool
        Copy instead of move (leaves the original in the watched folder).
    exposure_s : float, optional
        Nominal exposure; used when the file does not state one.

    """

    driver = "folder"

    def __init__(
        self,
        folder: str | os.PathLike[str],
        *,
        timeout_s: float = 120.0,
        pattern: str | Sequence[str] = "*",
        prompt: Callable[[str], Any] | None = None,
        poll_s: float = 0.2,
        copy: bool = False,
        exposure_s: float | None = None,
    ) -> None:
        super().__init__(timeout_s=timeout_s)
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise CameraError(f"watched folder {self.folder} does not exist")
        self.patterns = (pattern,) if isinstance(pattern, str) else tuple(pattern)
        self.prompt = prompt
        self.poll_s = float(poll_s)
        self.copy = bool(copy)
        self.exposure_s = exposure_s
        self._seen: set[str] = set(self._candidates())

    @property
    def settings(self) -> dict[str, Any]:  # noqa: D102 - documented on the base class
        return {
            **super().settings,
            "folder": str(self.folder),
            "pattern": list(self.patterns),
            "exposure_s": self.exposure_s,
        }

    def _candidates(self) -> list[str]:
        try:
            entries = list(os.scandir(self.folder))
        except OSError as exc:
            raise CameraError(f"cannot list watched folder {self.folder}: {exc}") from exc
        names = []
        for entry in entries:
            if entry.name.startswith(".") or not entry.is_file():
                continue
            lowered = entry.name.lower()
            if any(fnmatch.fnmatchcase(lowered, p.lower()) for p in self.patterns):
                names.append(entry.name)
        return names

    def _do_capture(self, path: Path, frame_index: int, label: str) -> float | None:
        if self.prompt is not None:
            self.prompt(f"press the shutter for {label}")
        deadline = time.monotonic() + self.timeout_s
        sizes: dict[str, int] = {}
        while True:
            new = [name for name in self._candidates() if name not in self._seen]
            stable = []
            for name in new:
                try:
                    size = (self.folder / name).stat().st_size
                except FileNotFoundError:
                    continue
                if size > 0 and sizes.get(name) == size:
                    stable.append(name)
                sizes[name] = size
            if stable:
                name = min(stable, key=lambda n: ((self.folder / n).stat().st_mtime_ns, n))
                break
            if time.monotonic() >= deadline:
                raise CameraError(
                    f"no new file matching {', '.join(self.patterns)} appeared in {self.folder} "
                    f"within {self.timeout_s:g} s for {label}"
                )
            time.sleep(self.poll_s)
        self._seen.add(name)
        source = self.folder / name
        log.info("folder camera: %s arrived for %s", source, label)
        if self.copy:
            shutil.copyfile(source, path)
        else:
            shutil.move(source, path)
        if path.parent.resolve() == self.folder.resolve():
            self._seen.add(path.name)
        if path.suffix.lower() in RAW_SUFFIXES:
            exposure = read_exposure(path)
            if exposure is not None:
                return exposure
        return self.exposure_s
