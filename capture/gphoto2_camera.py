"""A tethered camera driven through libgphoto2 (python-gphoto2, optional extra ``ps-lab[gphoto2]``).

The driver opens the camera (auto-detected, or on a given port such as ``usb:001,004``),
writes the rig file's settings into the camera's configuration tree (capture target, shutter
speed, ISO, aperture, image format = RAW, ...), and for each frame triggers the shutter, waits
for libgphoto2's ``GP_EVENT_FILE_ADDED`` events until the RAW file appears (a JPEG sibling of
RAW+JPEG modes is ignored and, when possible, deleted from the camera), downloads it to the
target path and deletes it from the camera's RAM or card unless ``keep_on_camera``.

``gphoto2`` is imported when the camera is opened, never at module import, so ps-lab works
without it; tests inject a double of the API through ``gp_module``.
"""

from __future__ import annotations

import logging
import math
import os
import re
import time
from collections.abc import Mapping
from pathlib import Path
from types import ModuleType
from typing import Any

from ps_lab.capture.camera_devices import CameraDevice
from ps_lab.errors import CameraError
from ps_lab.io.raw import RAW_SUFFIXES

__all__ = ["CAMERA_RAW_SUFFIXES", "Gphoto2Camera", "parse_shutter_speed"]

log = logging.getLogger(__name__)

#: File name suffixes treated as the RAW file of a capture (others, e.g. JPEG, are ignored).
CAMERA_RAW_SUFFIXES = (
    *RAW_SUFFIXES,
    ".crw",
    ".nrw",
    ".orf",
    ".rw2",
    ".raf",
    ".pef",
    ".srw",
    ".3fr",
)

#: Settings applied when the rig file does not name them, if the camera has them.
DEFAULT_SETTINGS: dict[str, Any] = {"capturetarget": "Internal RAM", "imageformat": "RAW"}

#: Other widget names cameras use for a setting (Nikon: ``f-number``, ``imagequality``).
SETTING_ALIASES: dict[str, tuple[str, ...]] = {
    "aperture": ("f-number", "fnumber"),
    "imageformat": ("imagequality",),
    "iso": ("isospeed",),
}

#: Settings whose choices are numbers: a value may match a choice numerically.
_NUMERIC = {"shutterspeed", "aperture", "f-number", "fnumber", "iso", "isospeed"}

#: Seconds between triggers while the camera answers busy (PTP DeviceBusy, GP_ERROR_CAMERA_BUSY).
BUSY_RETRY_S = 0.25

#: libgphoto2's model name of a generic PTP/IP camera (``gphoto2 --list-cameras``).
PTPIP_MODEL = "PTP/IP Camera"

# ps-lab is installed from its clone (not from a package index).
_INSTALL_HINT = (
    "python-gphoto2 is not installed: in the ps-lab clone, run "
    ".venv/bin/pip install -e '.[gphoto2]'"
)


def _import_gphoto2() -> ModuleType:
    # Imported here, on first use: python-gphoto2 is an optional extra (ps-lab[gphoto2]) that
    # needs libgphoto2; without it every other camera still works.
    try:
        import gphoto2  # type: ignore[import-not-found]
    except ImportError:
        raise CameraError(_INSTALL_HINT) from None
    return gphoto2


def _keeping_fd0(call: Any) -> None:
    """Run ``call()`` and put back whatever file descriptor 0 was if the call closed it.

    libgphoto2's PTP/IP driver (2.5.34, the python-gphoto2 wheel's) closes descriptor 0 when it
    disconnects, besides its two sockets: on a reconnect in the middle of a capture, 0 is then
    the process's standard input or, once that is gone, whatever was opened next (the light
    controller's serial port, say).
    """
    try:
        before = os.fstat(0)
        saved = os.dup(0)
    except OSError:  # nothing at 0 now: nothing to lose
        call()
        return
    try:
        call()
    finally:
        try:
            after = os.fstat(0)
            same = (after.st_dev, after.st_ino) == (before.st_dev, before.st_ino)
        except OSError:
            same = False
        if not same:
            os.dup2(saved, 0, inheritable=True)
        os.close(saved)


def parse_shutter_speed(value: object) -> float | None:
    """Exposure time in seconds from a gphoto2 shutter-speed string, or None (e.g. ``bulb``).

    Accepts ``"1/125"``, ``"0.5"``, ``"2"``, ``"30s"``, ``"1/20s"``, ``'2"'`` and numbers.
    """
    if isinstance(value, int | float) and not isinstance(value, bool):
        return float(value) if math.isfinite(value) and value > 0 else None
    text = str(value).strip().lower().rstrip('s"').strip()
    match = re.fullmatch(r"(\d+(?:\.\d+)?)(?:\s*/\s*(\d+(?:\.\d+)?))?", text)
    if not match:
        return None
    seconds = float(match.group(1)) / (float(match.group(2)) if match.group(2) else 1.0)
    return seconds if seconds > 0 else None


def _number(name: str, value: object) -> float | None:
    if name == "shutterspeed":
        return parse_shutter_speed(value)
    match = re.search(r"\d+(?:\.\d+)?", str(value))
    return float(match.group()) if match else None


def _match_choice(name: str, value: object, choices: list[str]) -> str | None:
    """Find the camera's choice for ``value``: exact, else case-insensitive, else numeric (1 %)."""
    text = str(value)
    for same in (lambda c: c == text, lambda c: c.lower() == text.lower()):
        found = next((c for c in choices if same(c)), None)
        if found is not None:
            return found
    if name in ("imageformat", "imagequality") and text.lower() == "raw":
        # "RAW" means the RAW-only choice: Canon "RAW", Nikon "NEF (Raw)"; never RAW + JPEG.
        raw_only = [
            c
            for c in choices
            if ("raw" in c.lower() or "nef" in c.lower())
            and not any(t in c.lower() for t in ("+", "jpeg", "jpg", "fine", "normal", "basic"))
        ]
        return raw_only[0] if raw_only else None
    if name in _NUMERIC:
        target = _number(name, value)
        if target is None:
            return None
        for choice in choices:
            number = _number(name, choice)
            if number is not None and abs(number - target) <= 0.01 * target:
                return choice
    return None


class Gphoto2Camera(CameraDevice):
    """A USB-tethered camera through libgphoto2.

    Parameters
    ----------
    port : str, optional
        gphoto2 port such as ``"usb:001,004"``; auto-detected (first camera) when omitted.
    settings : mapping
        Configuration widget name -> value, applied in order, e.g.
        ``{"capturetarget": "Internal RAM", "imageformat": "RAW", "shutterspeed": "1/20",
        "iso": "100", "aperture": "8"}``. Names and values are the camera's own (see
        ``gphoto2 --list-config`` / ``--get-config NAME``); values of choice widgets must match
        a choice (case-insensitively). ``capturetarget`` defaults to ``"Internal RAM"`` where
        the camera offers it.
    timeout_s : float
        How long to wait for the RAW file after triggering.
    keep_on_camera : bool
        Leave captured files on the camera instead of deleting them after download.
    exposure_s, iso, aperture : float, optional
        Shortcuts for the ``shutterspeed``, ``iso`` and ``aperture`` settings (numbers are
        matched to the camera's choices numerically, e.g. 0.05 -> ``"1/20"``, 8 -> ``"f/8"``).
    gp_module : module, optional
        The ``gphoto2`` module (tests pass a double); imported lazily by default.

    """

    driver = "gphoto2"

    def __init__(
        self,
        port: str | None = None,
        *,
        settings: Mapping[str, Any] | None = None,
        timeout_s: float = 30.0,
        keep_on_camera: bool = False,
        exposure_s: float | None = None,
        iso: int | None = None,
        aperture: float | None = None,
        gp_module: Any = None,
    ) -> None:
        super().__init__(timeout_s=timeout_s)
        self.port = port
        self.camera_settings = dict(settings or {})
        # Rig-file conveniences; an explicit entry in ``settings`` wins.
        for name, value in (("shutterspeed", exposure_s), ("iso", iso), ("aperture", aperture)):
            if value is not None:
                self.camera_settings.setdefault(name, value)
        self.keep_on_camera = bool(keep_on_camera)
        self._gp = gp_module if gp_module is not None else _import_gphoto2()
        self._camera: Any = None
        self._stale: tuple[str, str] | None = None
        self.model: str | None = None
        self._connect()

    # -- connection -----------------------------------------------------------------------
    def _gp_error(self, exc: Exception, doing: str) -> CameraError:
        gp = self._gp
        code = getattr(exc, "code", None)
        if code == getattr(gp, "GP_ERROR_MODEL_NOT_FOUND", -105):
            return CameraError(
                f"no camera found by gphoto2 while {doing} (is it on and connected?)"
            )
        if code in (
            getattr(gp, "GP_ERROR_IO_USB_CLAIM", -53),
            getattr(gp, "GP_ERROR_IO_LOCK", -60),
        ):
            return CameraError(
                f"camera is busy while {doing}: another program holds it "
                "(close photo importers, or `gio mount -u` it)"
            )
        return CameraError(f"gphoto2 error while {doing}: {exc}")

    def _open(self) -> None:
        gp = self._gp
        error_type = getattr(gp, "GPhoto2Error", Exception)
        port = self.port
        try:
            if port is None:
                detected = list(gp.Camera.autodetect())
                if not detected:
                    raise CameraError(
                        "no camera detected by gphoto2: check that it is on, connected by USB, "
                        "and not mounted by another program"
                    )
                if len(detected) > 1:
                    log.warning(
                        "gphoto2: %d cameras found; using the first: %s", len(detected), detected[0]
                    )
                self.model, port = detected[0][0], detected[0][1]
            camera = gp.Camera()
            ports = gp.PortInfoList()
            ports.load()
            try:
                index = ports.lookup_path(port)
            except error_type:
                raise CameraError(f"gphoto2 knows no port {port!r}") from None
            camera.set_port_info(ports[index])
            if port.startswith(("ptpip:", "ip:")):
                # libgphoto2 detects models on USB only: on a network port gp_camera_init fails
                # with "Unknown model" unless the generic PTP/IP driver is chosen first.
                abilities = gp.CameraAbilitiesList()
                abilities.load()
                camera.set_abilities(abilities[abilities.lookup_model(PTPIP_MODEL)])
                self.model = self.model or PTPIP_MODEL
            camera.init()
        except CameraError:
            raise
        except error_type as exc:
            raise self._gp_error(exc, f"opening the camera on {port}") from None
        self._camera = camera
        self.port = port
        log.info("gphoto2: opened %s on %s", self.model or "camera", port)

    def _configure(self) -> None:
        gp = self._gp
        error_type = getattr(gp, "GPhoto2Error", Exception)
        try:
            config = self._camera.get_config()
        except error_type as exc:
            raise self._gp_error(exc, "reading the configuration") from None
        wanted = {k: v for k, v in DEFAULT_SETTINGS.items() if k not in self.camera_settings}
        for name, value in {**wanted, **self.camera_settings}.items():
            explicit = name in self.camera_settings
            widget, widget_name = None, name
            for candidate in (name, *SETTING_ALIASES.get(name, ())):
                try:
                    widget, widget_name = config.get_child_by_name(candidate), candidate
                    break
                except error_type:
                    continue
            if widget is None:
                if explicit:
                    raise CameraError(
                        f"camera has no setting {name!r} (see `gphoto2 --list-config`)"
                    )
                continue
            try:
                self._set_widget(widget, widget_name, value)
            except CameraError:
                if explicit:
                    raise
                log.info("gphoto2: default %s=%r not available; left as is", name, value)
        try:
            self._camera.set_config(config)
        except error_type as exc:
            raise self._gp_error(exc, "writing the settings") from None

    def _set_widget(self, widget: Any, name: str, value: Any) -> None:
        gp = self._gp
        kind = widget.get_type()
        if kind in (getattr(gp, "GP_WIDGET_RADIO", 5), getattr(gp, "GP_WIDGET_MENU", 6)):
            choices = [widget.get_choice(i) for i in range(widget.count_choices())]
            match = _match_choice(name, value, choices)
            if match is None:
                raise CameraError(f"camera setting {name}={str(value)!r} is not one of {choices}")
            widget.set_value(match)
        elif kind == getattr(gp, "GP_WIDGET_TOGGLE", 4):
            widget.set_value(int(bool(value)))
        elif kind == getattr(gp, "GP_WIDGET_RANGE", 3):
            widget.set_value(float(value))
        else:
            widget.set_value(str(value))
        log.debug("gphoto2: %s = %r", name, value)

    @property
    def settings(self) -> dict[str, Any]:  # noqa: D102 - documented on the base class
        return {
            **super().settings,
            "port": self.port,
            "model": self.model,
            "camera": dict(self.camera_settings),
        }

    @property
    def exposure_s(self) -> float | None:
        """Exposure from the ``shutterspeed`` setting, if it names one."""
        return parse_shutter_speed(self.camera_settings.get("shutterspeed", ""))

    # -- capture --------------------------------------------------------------------------
    def _drain_events(self) -> None:
        """Take events left from an earlier shot (e.g. a late JPEG sibling) off the queue."""
        gp = self._gp
        for _ in range(100):
            event_type, data = self._camera.wait_for_event(10)
            if event_type == gp.GP_EVENT_TIMEOUT:
                return
            if event_type == gp.GP_EVENT_FILE_ADDED:
                log.info("gphoto2: ignoring leftover file %s/%s", data.folder, data.name)
                self._delete(data.folder, data.name)

    def _delete(self, folder: str, name: str) -> None:
        if self.keep_on_camera:
            return
        try:
            self._camera.file_delete(folder, name)
        except getattr(self._gp, "GPhoto2Error", Exception) as exc:
            log.debug("gphoto2: could not delete %s/%s: %s", folder, name, exc)

    def _connect(self) -> None:
        """Open the camera and apply the settings; closed again if either fails."""
        self._open()
        try:
            self._configure()
        except BaseException:
            self._do_close()
            raise

    def _reconnect(self) -> None:
        """Open the camera again after a capture lost it (e.g. a dropped PTP/IP connection)."""
        log.info("gphoto2: connecting to %s again", self.port)
        self._connect()
        if self._stale is not None:  # the file whose download was cut off
            self._delete(*self._stale)
            self._stale = None

    def _trigger(self, deadline: float, label: str) -> None:
        """trigger_capture, again every BUSY_RETRY_S while the camera answers busy."""
        gp = self._gp
        busy = getattr(gp, "GP_ERROR_CAMERA_BUSY", -110)
        while True:
            try:
                self._camera.trigger_capture()
                return
            except getattr(gp, "GPhoto2Error", Exception) as exc:
                if getattr(exc, "code", None) != busy:
                    raise
                if time.monotonic() + BUSY_RETRY_S > deadline:
                    raise CameraError(
                        f"gphoto2: camera stayed busy for {self.timeout_s:g} s when triggering "
                        f"{label}"
                    ) from None
                log.info("gphoto2: camera busy; triggering %s again in %g s", label, BUSY_RETRY_S)
                time.sleep(BUSY_RETRY_S)

    def _do_capture(self, path: Path, frame_index: int, label: str) -> float | None:
        gp = self._gp
        error_type = getattr(gp, "GPhoto2Error", Exception)
        if self._camera is None:  # an earlier capture lost the connection
            self._reconnect()
        found: tuple[str, str] | None = None
        try:
            self._drain_events()
            deadline = time.monotonic() + self.timeout_s
            self._trigger(deadline, label)
            while found is None:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise CameraError(
                        f"gphoto2: no RAW file within {self.timeout_s:g} s after triggering "
                        f"{label} (is the image format RAW?)"
                    )
                event_type, data = self._camera.wait_for_event(
                    max(1, int(min(remaining, 1.0) * 1000))
                )
                if event_type != gp.GP_EVENT_FILE_ADDED:
                    continue
                if Path(data.name).suffix.lower() in CAMERA_RAW_SUFFIXES:
                    found = (data.folder, data.name)
                else:
                    log.info("gphoto2: ignoring non-RAW file %s/%s", data.folder, data.name)
                    self._delete(data.folder, data.name)
            folder, name = found
            camera_file = self._camera.file_get(folder, name, gp.GP_FILE_TYPE_NORMAL)
            camera_file.save(str(path))
            self._delete(folder, name)
        except CameraError:
            raise
        except error_type as exc:
            # libgphoto2 cannot talk to a camera again after an I/O failure in the middle of an
            # operation (a dropped PTP/IP connection leaves every later call failing): close it
            # here and connect again at the next capture.
            self._stale = found
            self._do_close()
            raise CameraError(
                f"gphoto2 lost the camera while capturing {label} ({exc}); "
                "connecting again at the next capture"
            ) from None
        log.info("gphoto2: %s/%s -> %s", found[0], found[1], path)
        return self.exposure_s  # None: the base class reads it from the file

    def _do_close(self) -> None:
        if self._camera is None:
            return
        try:
            _keeping_fd0(self._camera.exit)
        except getattr(self._gp, "GPhoto2Error", Exception) as exc:
            log.debug("gphoto2: exit failed: %s", exc)
        finally:
            self._camera = None
