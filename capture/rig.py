"""Rig files: the light controller, camera, calibration target and (simulated) scene of a rig.

A rig file is TOML data, never code. :func:`load_rig` reads it with :mod:`tomllib` into frozen
dataclasses and validates every key: an unknown key or a value of the wrong type raises
:class:`~ps_lab.errors.RigError` naming the file, the table and the key. Command-line flags
override the file through :func:`apply_overrides`.

This module is the schema and its parser only: :mod:`ps_lab.capture.connect` turns a :class:`Rig`
into live drivers.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ps_lab.capture._rig_lens import LensConfig, lens_camera, parse_lens
from ps_lab.capture._rig_table import _kind, _Table, light_intensities, unit_vectors
from ps_lab.capture.faults import CAMERA_FAULT_KINDS, PTPIP_FAULT_KINDS, Fault
from ps_lab.capture.faults import FAULT_KINDS as CONTROLLER_FAULT_KINDS
from ps_lab.errors import RigError
from ps_lab.geometry import Circle
from ps_lab.io.files import json_safe

log = logging.getLogger(__name__)

CONTROLLER_DRIVERS = ("serial", "simulated", "firmware")
CAMERA_DRIVERS = ("simulated", "gphoto2", "folder")
#: File types a frame may have; RAW types are verified with ``load_raw``, the others with OpenCV.
# A rig file's objects are grey card-like (0.8) unless they say otherwise; the renderer's own
# default albedo is 1.
RIG_ALBEDO = (0.8, 0.8, 0.8)
#: ``[[scene.objects]] kind``: the kinds the renderer draws (``ps_lab.render.scene.OBJECT_KINDS``).
OBJECT_KINDS = ("sphere", "relief", "chrome", "matte")
FILE_TYPES = ("dng", "cr2", "cr3", "nef", "arw", "tif", "tiff", "png")

#: Settings that cannot change what a frame contains: where a device is plugged in (a re-plugged
#: USB adapter gets a new name), how long to wait and how often to retry, which faults a simulator
#: injects, and where the rig file lives. A resumed run ignores them when it compares rig
#: snapshots; every other setting must be unchanged.
OPERATIONAL_KEYS = (
    ("controller", "port"),
    ("controller", "timeout_s"),
    ("camera", "port"),
    ("camera", "timeout_s"),
    ("camera", "retries"),
    ("faults",),
    ("source",),
    ("description",),
)


# --------------------------------------------------------------------------------------------
# Schema
# --------------------------------------------------------------------------------------------


LED_INTENSITY_MODELS = ("equal", "origin")


@dataclass(frozen=True)
class ControllerConfig:
    """``[controller]``: the light controller."""

    driver: str
    lights: int
    port: str | None = None
    level: int = 255
    watchdog_ms: int = 10000
    timeout_s: float = 1.0
    baudrate: int = 115200
    settle_ms: int = 0
    directions: tuple[tuple[float, float, float], ...] | None = None
    #: ``driver = "firmware"``: the wiring (Arduino pin of light 1, 2, ...) and the sketch's ELF
    #: (default: rigs/firmware/ps_lab_lights, built with arduino-mk).
    pins: tuple[int, ...] | None = None
    elf: str | None = None
    # LED emission: radiance ∝ cos^anisotropy of the angle to the LED's axis (aimed at the scene
    # centre); 0 = isotropic. Used by the near-light model (calibration and reconstruction).
    anisotropy: float = 0.0


@dataclass(frozen=True)
class CameraConfig:
    """``[camera]``: the camera and its fixed (manual) settings."""

    driver: str
    exposure_s: float
    file_type: str = "dng"
    timeout_s: float = 30.0
    retries: int = 1
    iso: int | None = None
    aperture: float | None = None
    port: str | None = None
    folder: str | None = None
    prompt: bool = False
    light_state_file: str | None = None
    pattern: str = "*"
    settings: tuple[tuple[str, str | int | float], ...] = ()
    black_level: int = 512
    white_level: int = 16383
    gain: float = 200_000.0
    read_noise_dn: float = 2.0
    shot_noise: bool = True
    dn_per_electron: float = 0.5
    seed: int = 0

    def sensor(self) -> dict[str, Any]:
        """The simulated sensor's settings (:data:`SENSOR_SETTINGS`), as keyword arguments."""
        return {key: getattr(self, key) for key in SENSOR_SETTINGS}


#: The simulated sensor's ``[camera]`` keys, in the order a run's manifest records them.
SENSOR_SETTINGS = (
    "black_level", "white_level", "gain", "read_noise_dn", "shot_noise", "dn_per_electron", "seed"
)


@dataclass(frozen=True)
class CalibrationConfig:
    """``[calibration]``: nominal position of the calibration targets."""

    chrome_sphere: Circle | None = None
    matte_sphere: Circle | None = None
    # Every chrome sphere (``chrome_sphere`` is the first): two or more give LED positions.
    chrome_spheres: tuple[Circle, ...] = ()
    # Where the object's outline lies (near lights): "table" (on the table the chrome spheres
    # rest on: their radius below their centres), a height in pixels above the spheres' centre
    # plane, or None (found from the shading by `ps-lab reconstruct`).
    object_outline: str | float | None = None
    # LEDs' intensities without a matte target: "equal" (identical LEDs: equal radiant
    # intensity) or "origin" (equal irradiance at the scene origin); a per-LED file is given to
    # `ps-lab calibrate --led-intensities FILE`.
    led_intensities: str = "equal"


@dataclass(frozen=True)
class LightLayoutConfig:
    """``[scene.lights]``: where the simulated lights really are and how bright they are."""

    seed: int = 0
    max_zenith_deg: float = 55.0
    directions: tuple[tuple[float, float, float], ...] | None = None
    intensities: tuple[tuple[float, float, float], ...] | None = None
    intensity_spread: float = 0.0
    color_spread: float = 0.0
    nominal_error_deg: float = 0.0
    # LEDs at a finite distance: on a dome of this radius (pixel units) around the scene origin
    # (image centre, spheres' plane); None = lights at infinity. ``led_radius``: emitting disc.
    dome_radius: float | None = None
    led_radius: float = 15.0


@dataclass(frozen=True)
class SceneObjectConfig:
    """``[[scene.objects]]``: one object of the simulated scene, as the rig file describes it.

    Plain data: the simulator (:mod:`ps_lab.capture.simulated.simulation`) turns it into the
    renderer's ``SceneObject`` (the same fields); ``kind`` is one of :data:`OBJECT_KINDS`,
    ``center`` and ``radius`` in pixels, ``albedo`` per channel, ``specular`` and ``roughness``
    the Cook-Torrance lobe, ``seed`` a relief's layout.
    """

    kind: str
    center: tuple[float, float]
    radius: float
    albedo: tuple[float, float, float] = RIG_ALBEDO
    specular: float = 0.0
    roughness: float = 0.3
    seed: int = 0


@dataclass(frozen=True)
class SceneConfig:
    """``[scene]``: what the simulated camera sees."""

    width: int
    height: int
    objects: tuple[SceneObjectConfig, ...]
    lights: LightLayoutConfig = field(default_factory=LightLayoutConfig)
    background: float = 0.0


@dataclass(frozen=True)
class FaultsConfig:
    """``[faults]``: faults to inject into the simulated controller and camera."""

    controller: tuple[Fault, ...] = ()
    camera: tuple[Fault, ...] = ()
    seed: int = 0


@dataclass(frozen=True)
class Rig:
    """A validated rig file."""

    name: str
    controller: ControllerConfig
    camera: CameraConfig
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    scene: SceneConfig | None = None
    faults: FaultsConfig = field(default_factory=FaultsConfig)
    description: str = ""
    source: Path | None = field(default=None, compare=False)
    lens: LensConfig | None = None  # [lens]: capture/_rig_lens.py

    @property
    def n_lights(self) -> int:
        """Number of lights, numbered 1..N."""
        return self.controller.lights

    @property
    def simulated_camera(self) -> bool:
        """Whether the camera is the simulated one (the run then gets ground truth)."""
        return self.camera.driver == "simulated"

    def snapshot(self) -> dict[str, Any]:
        """Return the rig as a JSON-ready dict (what a capture run's manifest stores)."""
        snap = json_safe(dataclasses.asdict(self))
        snap.pop("source", None)
        if snap.get("lens") is None:  # absent, as in runs captured before [lens]
            snap.pop("lens", None)
        for key in ("pins", "elf"):  # firmware-only keys: absent elsewhere, as in older runs
            if snap["controller"].get(key) is None:
                snap["controller"].pop(key, None)
        snap["source"] = str(self.source) if self.source is not None else None
        cal: dict[str, Any] = {}
        for key in ("chrome_sphere", "matte_sphere"):
            circle = getattr(self.calibration, key)
            if circle is not None:
                cal[key] = {"center": list(circle.center), "radius": circle.radius}
        if len(self.calibration.chrome_spheres) > 1:
            cal["chrome_spheres"] = [
                {"center": list(c.center), "radius": c.radius}
                for c in self.calibration.chrome_spheres
            ]
        # near-light statements, recorded only when set (older runs' snapshots stay equal)
        if self.calibration.object_outline is not None:
            cal["object_outline"] = self.calibration.object_outline
        if self.calibration.led_intensities != "equal":
            cal["led_intensities"] = self.calibration.led_intensities
        snap["calibration"] = cal
        return snap

    def camera_settings(self) -> dict[str, Any]:
        """Return the settings that shape the frames (stored in the manifest)."""
        cam = self.camera
        settings: dict[str, Any] = {
            "driver": cam.driver,
            "exposure_s": cam.exposure_s,
            "iso": cam.iso,
            "aperture": cam.aperture,
            "file_type": cam.file_type,
        }
        if cam.driver == "gphoto2" and cam.settings:
            settings["settings"] = dict(cam.settings)
        if cam.driver == "simulated":
            settings.update(cam.sensor())
        return settings


def comparable_snapshot(snapshot: Mapping[str, Any]) -> dict[str, Any]:
    """Return ``snapshot`` without the :data:`OPERATIONAL_KEYS` a resumed run may change."""
    snap = json_safe(dict(snapshot))
    for path in OPERATIONAL_KEYS:
        *tables, key = path
        node = snap
        for table in tables:
            node = node.get(table) if isinstance(node, dict) else None
        if isinstance(node, dict):
            node.pop(key, None)
    return snap


def snapshot_differences(
    old: Mapping[str, Any], new: Mapping[str, Any], prefix: str = ""
) -> list[str]:
    """List the dotted keys whose values differ between two JSON-like dicts."""
    diffs: list[str] = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key, "<missing>"), new.get(key, "<missing>")
        name = f"{prefix}{key}"
        if isinstance(a, dict) and isinstance(b, dict):
            diffs.extend(snapshot_differences(a, b, name + "."))
        elif a != b:
            diffs.append(name)
    return diffs


# --------------------------------------------------------------------------------------------
# Reading and validation
# --------------------------------------------------------------------------------------------


def load_rig(path: str | Path) -> Rig:
    """Read and validate a rig file.

    Parameters
    ----------
    path : str or Path
        A TOML rig file.

    Returns
    -------
    Rig

    Raises
    ------
    RigError
        The file is missing, not TOML, or has an unknown key or a value of the wrong type.

    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise RigError(f"rig file {path} does not exist") from None
    except IsADirectoryError:
        raise RigError(f"rig file {path} is a directory") from None
    except OSError as exc:
        raise RigError(f"cannot read rig file {path}: {exc.strerror or exc}") from None
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise RigError(f"rig file {path} is not UTF-8 text") from None
    except tomllib.TOMLDecodeError as exc:
        raise RigError(f"rig file {path} is not valid TOML: {exc}") from None
    return parse_rig(data, origin=str(path), source=path)


def parse_rig(data: Mapping[str, Any], *, origin: str = "<rig>", source: Path | None = None) -> Rig:
    """Validate a rig already parsed from TOML (see :func:`load_rig`)."""
    top = _Table(dict(data), "", origin)
    name = top.str("name", source.stem if source is not None else "rig")
    description = top.str("description", "")
    ctl_table, cam_table = top.table("controller"), top.table("camera")
    for key, table in (("controller", ctl_table), ("camera", cam_table)):
        if table is None:
            raise RigError(f"{origin}: missing table [{key}]")
    controller, camera = _parse_controller(ctl_table), _parse_camera(cam_table)
    lens = parse_lens(top.table("lens"), source, camera.driver == "simulated")
    cal_table = top.table("calibration")
    calibration = _parse_calibration(cal_table) if cal_table is not None else CalibrationConfig()
    scene_table = top.table("scene")
    scene = _parse_scene(scene_table, controller.lights) if scene_table is not None else None
    lens_camera(lens, source, origin, scene)  # the camera calibrated for these frames
    faults_table = top.table("faults")
    faults = _parse_faults(faults_table) if faults_table is not None else FaultsConfig()
    top.done()

    # A gphoto2 camera on ptpip:127.0.0.1 with a [scene] is the PTP/IP camera simulator.
    ptpip_sim = camera.driver == "gphoto2" and scene is not None
    if camera.driver == "simulated" and scene is None:
        raise RigError(f"{origin}: the simulated camera needs a [scene] table")
    if ptpip_sim and local_ptpip_port(camera.port) is None:
        raise RigError(
            f"{origin}: [scene] only applies to a simulated camera, or to a gphoto2 camera on "
            f'port = "ptpip:127.0.0.1[:N]" (the PTP/IP camera simulator); got {camera.port!r}'
        )
    if camera.driver not in ("simulated", "gphoto2") and scene is not None:
        raise RigError(
            f"{origin}: [scene] only applies to a simulated camera "
            f"(camera driver is {camera.driver!r})"
        )
    sensor = sorted(_SENSOR_KEYS & set(cam_table.data))
    if camera.driver == "gphoto2" and scene is None and sensor:
        raise RigError(
            f"{origin}: [camera] {sensor[0]}: applies to a gphoto2 camera only on a [scene] "
            "(the PTP/IP camera simulator)"
        )
    if camera.driver == "simulated" and camera.file_type != "dng":
        raise RigError(f"{origin}: [camera] file_type: the simulated camera writes 'dng' files")
    if (
        (camera.driver == "simulated" or ptpip_sim)
        and controller.driver == "serial"
        and camera.light_state_file is None
    ):
        raise RigError(
            f"{origin}: [camera] light_state_file: required when a simulated camera works with a "
            "serial controller (the state file written by `ps-lab rig serve-sim --state-file`)"
        )
    if faults.controller and controller.driver != "simulated":
        raise RigError(
            f"{origin}: [faults] controller: faults can only be injected into a simulated "
            "controller"
        )
    kinds = PTPIP_FAULT_KINDS if ptpip_sim else CAMERA_FAULT_KINDS
    if faults.camera and camera.driver != "simulated" and not ptpip_sim:
        raise RigError(
            f"{origin}: [faults] camera: faults can only be injected into a simulated camera"
        )
    for fault in faults.camera:
        if fault.kind not in kinds:
            raise RigError(
                f"{origin}: [faults] camera: {fault.kind!r} is not a fault of this camera; "
                f"choose from {', '.join(kinds)}"
            )
    return Rig(
        name=name,
        description=description,
        controller=controller,
        camera=camera,
        calibration=calibration,
        scene=scene,
        faults=faults,
        source=source,
        lens=lens,
    )


def _parse_controller(t: _Table) -> ControllerConfig:
    driver = t.str("driver", required=True, choices=CONTROLLER_DRIVERS)
    lights = t.int("lights", required=True, lo=1, hi=999)
    port = t.str("port", None, required=driver == "serial")
    if driver != "serial" and port is not None:
        raise t.error("port", f"a {driver} controller is served on its own pty; remove the port")
    pins = _pins(t, lights) if driver == "firmware" else None
    elf = t.str("elf", None) if driver == "firmware" else None
    cfg = ControllerConfig(
        driver=driver,
        lights=lights,
        port=port,
        level=t.int("level", 255, lo=0, hi=255),
        watchdog_ms=t.int("watchdog_ms", 10000, lo=0, hi=3_600_000),
        timeout_s=t.float("timeout_s", 1.0, lo=0.01, hi=60.0),
        baudrate=t.int("baudrate", 115200, lo=300),
        settle_ms=t.int("settle_ms", 0, lo=0, hi=60_000),
        directions=unit_vectors(t, "directions", lights),
        pins=pins,
        elf=elf,
        anisotropy=t.float("anisotropy", 0.0, lo=0.0, hi=100.0),
    )
    t.done()
    return cfg


def _pins(t: _Table, lights: int) -> tuple[int, ...] | None:
    pins = t.ints("pins")
    if pins is None:
        return None
    if len(pins) != lights:
        raise t.error("pins", f"{len(pins)} pins for {lights} lights")
    if any(not 2 <= p <= 19 for p in pins) or len(set(pins)) != len(pins):
        raise t.error("pins", "each light needs its own Uno pin 2-19 (0 and 1 are the serial port)")
    return pins


_SENSOR_KEYS = {*SENSOR_SETTINGS, "light_state_file"}
_CAMERA_KEYS = {
    "simulated": _SENSOR_KEYS,
    # and, on a [scene] (the PTP/IP camera simulator), the simulated sensor's keys
    "gphoto2": {"iso", "aperture", "port", "settings"} | _SENSOR_KEYS,
    "folder": {"folder", "prompt", "pattern"},
}


def _parse_camera(t: _Table) -> CameraConfig:
    driver = t.str("driver", required=True, choices=CAMERA_DRIVERS)
    for key in t.data:
        other = {k for d, keys in _CAMERA_KEYS.items() if d != driver for k in keys}
        if key in other - _CAMERA_KEYS[driver]:
            raise t.error(key, f"does not apply to the {driver!r} camera")
    cfg = CameraConfig(
        driver=driver,
        exposure_s=t.float("exposure_s", required=True, lo=1e-6, hi=3600.0),
        file_type=t.str("file_type", "dng", choices=FILE_TYPES),
        timeout_s=t.float("timeout_s", 30.0, lo=0.01, hi=3600.0),
        retries=t.int("retries", 1, lo=0, hi=10),
        iso=t.int("iso", None, lo=1),
        aperture=t.float("aperture", None, lo=0.1),
        port=t.str("port", None),
        folder=t.str("folder", None, required=driver == "folder"),
        prompt=t.bool("prompt", False),
        light_state_file=t.str("light_state_file", None),
        black_level=t.int("black_level", 512, lo=0, hi=65534),
        white_level=t.int("white_level", 16383, lo=1, hi=65535),
        pattern=t.str("pattern", "*"),
        settings=_gphoto2_settings(t),
        gain=t.float("gain", 200_000.0, lo=1e-6),
        read_noise_dn=t.float("read_noise_dn", 2.0, lo=0.0),
        shot_noise=t.bool("shot_noise", True),
        dn_per_electron=t.float("dn_per_electron", 0.5, lo=1e-6),
        seed=t.int("seed", 0, lo=0),
    )
    if cfg.white_level <= cfg.black_level:
        raise t.error("white_level", f"must exceed black_level ({cfg.black_level})")
    t.done()
    return cfg


def _gphoto2_settings(t: _Table) -> tuple[tuple[str, str | int | float], ...]:
    table = t.table("settings")
    if table is None:
        return ()
    out = []
    for key, value in sorted(table.data.items()):
        if isinstance(value, bool) or not isinstance(value, str | int | float):
            raise table.error(key, f"expected a string or a number, got {_kind(value)}")
        table.used.add(key)
        out.append((key, value))
    table.done()
    return tuple(out)


def _parse_circle(t: _Table) -> Circle:
    center = t.vector("center", 2, required=True)
    radius = t.float("radius", required=True, lo=1.0)
    t.done()
    return Circle(center[0], center[1], radius)


def _parse_calibration(t: _Table) -> CalibrationConfig:
    chrome = t.table("chrome_sphere")
    matte = t.table("matte_sphere")
    spheres = tuple(_parse_circle(c) for c in t.tables("chrome_spheres"))
    if chrome is not None and spheres:
        raise t.error("chrome_spheres", "give chrome_sphere or chrome_spheres, not both")
    if chrome is not None:
        spheres = (_parse_circle(chrome),)
    outline = t.data.get("object_outline")
    if isinstance(outline, str):
        outline = t.str("object_outline", choices=("table",))
    elif outline is not None:
        outline = t.float("object_outline", lo=-1e6, hi=1e6)
    t.used.add("object_outline")
    cfg = CalibrationConfig(
        chrome_sphere=spheres[0] if spheres else None,
        matte_sphere=_parse_circle(matte) if matte is not None else None,
        chrome_spheres=spheres,
        object_outline=outline,
        led_intensities=t.str("led_intensities", "equal", choices=LED_INTENSITY_MODELS),
    )
    t.done()
    return cfg


def _parse_scene(t: _Table, n_lights: int) -> SceneConfig:
    width = t.int("width", required=True, lo=8, hi=8192)
    height = t.int("height", required=True, lo=8, hi=8192)
    background = t.float("background", 0.0, lo=0.0)
    objects = []
    for ot in t.tables("objects"):
        obj = SceneObjectConfig(
            kind=ot.str("kind", required=True, choices=OBJECT_KINDS),
            center=ot.vector("center", 2, required=True),
            radius=ot.float("radius", required=True, lo=1.0),
            albedo=ot.vector("albedo", 3, RIG_ALBEDO),
            specular=ot.float("specular", 0.0, lo=0.0),
            roughness=ot.float("roughness", 0.3, lo=0.01, hi=1.0),
            seed=ot.int("seed", 0, lo=0),
        )
        ot.done()
        cx, cy = obj.center
        if (
            cx - obj.radius < -0.5
            or cy - obj.radius < -0.5
            or cx + obj.radius > width - 0.5
            or cy + obj.radius > height - 0.5
        ):
            raise ot.error(
                "center", f"the {obj.kind} object does not fit in the {width}x{height} image"
            )
        objects.append(obj)
    if not objects:
        raise t.error("objects", "a scene needs at least one object")
    lt = t.table("lights")
    if lt is None:
        lights = LightLayoutConfig()
    else:
        lights = LightLayoutConfig(
            seed=lt.int("seed", 0, lo=0),
            max_zenith_deg=lt.float("max_zenith_deg", 55.0, lo=1.0, hi=89.0),
            directions=unit_vectors(lt, "directions", n_lights),
            intensities=light_intensities(lt, n_lights),
            intensity_spread=lt.float("intensity_spread", 0.0, lo=0.0, hi=0.9),
            color_spread=lt.float("color_spread", 0.0, lo=0.0, hi=0.9),
            nominal_error_deg=lt.float("nominal_error_deg", 0.0, lo=0.0, hi=20.0),
            dome_radius=lt.float("dome_radius", None, lo=1.0, hi=1e6),
            led_radius=lt.float("led_radius", 15.0, lo=0.01, hi=1e4),
        )
        if lights.dome_radius is not None and lights.led_radius >= lights.dome_radius:
            raise lt.error("led_radius", f"must be smaller than dome_radius "
                           f"({lights.dome_radius:g})")
        lt.done()
    t.done()
    return SceneConfig(
        width=width, height=height, objects=tuple(objects), lights=lights, background=background
    )


_ALL_CAMERA_FAULTS = tuple(dict.fromkeys(CAMERA_FAULT_KINDS + PTPIP_FAULT_KINDS))


def _parse_faults(t: _Table) -> FaultsConfig:
    def faults(
        key: str, kinds: tuple[str, ...], unit: str, random_allowed: bool
    ) -> tuple[Fault, ...]:
        out = []
        for ft in t.tables(key):
            kind = ft.str("kind", required=True, choices=kinds)
            at = ft.int("at", None, lo=1)
            probability = ft.float("probability", 0.0, lo=0.0, hi=1.0) if random_allowed else 0.0
            if at is None and probability == 0.0:
                hint = " or 'probability'" if random_allowed else ""
                raise ft.error("at", f"missing: give the {unit} number (1 = first){hint}")
            out.append(Fault(kind=kind, at=at, probability=probability))
            ft.done()
        return tuple(out)

    cfg = FaultsConfig(
        controller=faults("controller", CONTROLLER_FAULT_KINDS, "command", True),
        camera=faults("camera", _ALL_CAMERA_FAULTS, "capture", False),
        seed=t.int("seed", 0, lo=0),
    )
    t.done()
    return cfg


# --------------------------------------------------------------------------------------------
# Overrides
# --------------------------------------------------------------------------------------------


def apply_overrides(rig: Rig, *, port: str | None = None, exposure_s: float | None = None) -> Rig:
    """Return ``rig`` with command-line overrides applied (``--port``, ``--exposure``)."""
    controller, camera = rig.controller, rig.camera
    if port is not None:
        if controller.driver != "serial":
            raise RigError(
                "--port applies to a serial controller; "
                f"this rig's controller is {controller.driver!r}"
            )
        controller = dataclasses.replace(controller, port=port)
    if exposure_s is not None:
        if not (math.isfinite(exposure_s) and exposure_s > 0):
            raise RigError(f"--exposure must be a positive number of seconds, got {exposure_s}")
        camera = dataclasses.replace(camera, exposure_s=float(exposure_s))
    return dataclasses.replace(rig, controller=controller, camera=camera)


_LOCAL_PTPIP = re.compile(r"^ptpip:(?:127\.0\.0\.1|localhost)(?::(\d+))?(?::(\d+))?$")


def local_ptpip_port(port: str | None) -> int | None:
    """The TCP port of ``ptpip:127.0.0.1[:N[:N]]`` (15740 without one), else None."""
    match = _LOCAL_PTPIP.match(port or "")
    if match is None:
        return None
    return int(match.group(1)) if match.group(1) else 15740


def parse_light_selection(text: str, n_lights: int) -> tuple[int, ...]:
    """Parse ``"1-24"`` or ``"1,3,5-9"`` into sorted unique 1-based light numbers.

    Raises
    ------
    RigError
        Bad syntax, an empty selection, or a light outside ``1..n_lights``.

    """
    chosen: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        if not part:
            raise RigError(f"--lights {text!r}: empty item")
        try:
            if "-" in part:
                first_s, last_s = part.split("-", 1)
                first, last = int(first_s), int(last_s)
            else:
                first = last = int(part)
        except ValueError:
            raise RigError(
                f"--lights {text!r}: {part!r} is not a number or a range like 1-24"
            ) from None
        if first > last:
            raise RigError(f"--lights {text!r}: range {part!r} runs backwards")
        if first < 1 or last > n_lights:
            raise RigError(f"--lights {text!r}: the rig has lights 1-{n_lights}")
        chosen.update(range(first, last + 1))
    return tuple(sorted(chosen))
