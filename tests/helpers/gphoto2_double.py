"""A test double of the python-gphoto2 API surface that ps-lab's Gphoto2Camera uses.

Build one with :func:`make_gphoto2_double` and pass it as ``gp_module=``. It mimics the
object-oriented python-gphoto2 interface (``gp.Camera``, ``gp.PortInfoList``, config widgets,
``wait_for_event`` returning ``(event_type, data)``, ``GPhoto2Error`` with ``.code``) and
records what the driver did so tests can assert on it. Names and constant values follow
libgphoto2 (gphoto2-port-result.h, gphoto2-result.h, gphoto2-camera.h, gphoto2-widget.h).
"""

from __future__ import annotations

import types
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

GP_OK = 0
GP_ERROR = -1
GP_ERROR_BAD_PARAMETERS = -2
GP_ERROR_UNKNOWN_PORT = -5
GP_ERROR_IO_USB_FIND = -52
GP_ERROR_IO_USB_CLAIM = -53
GP_ERROR_IO_LOCK = -60
GP_ERROR_CAMERA_BUSY = -110
GP_ERROR_MODEL_NOT_FOUND = -105

GP_EVENT_UNKNOWN = 0
GP_EVENT_TIMEOUT = 1
GP_EVENT_FILE_ADDED = 2
GP_EVENT_FOLDER_ADDED = 3
GP_EVENT_CAPTURE_COMPLETE = 4

GP_FILE_TYPE_NORMAL = 1

GP_WIDGET_WINDOW = 0
GP_WIDGET_SECTION = 1
GP_WIDGET_TEXT = 2
GP_WIDGET_RANGE = 3
GP_WIDGET_TOGGLE = 4
GP_WIDGET_RADIO = 5
GP_WIDGET_MENU = 6


class GPhoto2Error(Exception):
    """Like gphoto2.GPhoto2Error: carries the libgphoto2 result code."""

    def __init__(self, code: int) -> None:
        super().__init__(f"[{code}] simulated libgphoto2 error")
        self.code = code
        self.string = str(self)


@dataclass
class CameraFilePath:
    folder: str
    name: str


@dataclass
class Widget:
    name: str
    kind: int = GP_WIDGET_SECTION
    value: object = None
    choices: list[str] = field(default_factory=list)
    children: dict[str, Widget] = field(default_factory=dict)

    def get_name(self) -> str:
        return self.name

    def get_type(self) -> int:
        return self.kind

    def get_value(self) -> object:
        return self.value

    def set_value(self, value: object) -> None:
        if self.kind in (GP_WIDGET_RADIO, GP_WIDGET_MENU) and value not in self.choices:
            raise GPhoto2Error(GP_ERROR_BAD_PARAMETERS)
        self.value = value

    def count_choices(self) -> int:
        return len(self.choices)

    def get_choice(self, index: int) -> str:
        return self.choices[index]

    def get_choices(self):
        return iter(self.choices)

    def get_child_by_name(self, name: str) -> Widget:
        for child in self.children.values():
            if child.name == name:
                return child
            if child.children:
                try:
                    return child.get_child_by_name(name)
                except GPhoto2Error:
                    pass
        raise GPhoto2Error(GP_ERROR_BAD_PARAMETERS)

    def copy(self) -> Widget:
        return Widget(
            self.name,
            self.kind,
            self.value,
            list(self.choices),
            {k: v.copy() for k, v in self.children.items()},
        )


def canon_like_config() -> Widget:
    """A configuration tree shaped like a Canon EOS one (main/settings, main/capturesettings...)."""
    radio = GP_WIDGET_RADIO
    settings = Widget(
        "settings",
        GP_WIDGET_SECTION,
        children={
            "capturetarget": Widget(
                "capturetarget", radio, "Memory card", ["Internal RAM", "Memory card"]
            ),
        },
    )
    image = Widget(
        "imgsettings",
        GP_WIDGET_SECTION,
        children={
            "imageformat": Widget(
                "imageformat",
                radio,
                "Large Fine JPEG",
                ["Large Fine JPEG", "RAW + Large Fine JPEG", "RAW"],
            ),
            "iso": Widget("iso", radio, "Auto", ["Auto", "100", "200", "400"]),
        },
    )
    capture = Widget(
        "capturesettings",
        GP_WIDGET_SECTION,
        children={
            "shutterspeed": Widget(
                "shutterspeed", radio, "1/60", ["bulb", "2", "1", "0.5", "1/20", "1/60"]
            ),
            "aperture": Widget("aperture", radio, "5.6", ["4", "5.6", "8", "11"]),
            "eosremoterelease": Widget("eosremoterelease", GP_WIDGET_TEXT, "None"),
            "mirrorlock": Widget("mirrorlock", GP_WIDGET_TOGGLE, 0),
        },
    )
    return Widget(
        "main",
        GP_WIDGET_WINDOW,
        children={
            "settings": settings,
            "imgsettings": image,
            "capturesettings": capture,
        },
    )


@dataclass
class Shot:
    """What one trigger produces: files (name -> bytes) announced in order, then completion."""

    files: dict[str, bytes]
    delay_events: int = 0  # GP_EVENT_TIMEOUT events before the first file


class CameraFile:
    def __init__(self, data: bytes) -> None:
        self._data = data

    def save(self, path: str) -> None:
        Path(path).write_bytes(self._data)

    def get_data_and_size(self) -> bytes:
        return self._data


class Rig:
    """State shared by the double's classes: cameras, ports, config, scripted shots, call log."""

    def __init__(self) -> None:
        self.cameras = [("Canon EOS 6D", "usb:001,004")]
        self.ports = ["usb:", "usb:001,004", "serial:/dev/ttyS0"]
        self.config = canon_like_config()
        self.shots: deque[Shot] = deque()
        self.leftover_events: list[tuple[int, object]] = []
        self.init_error: int | None = None
        self.trigger_error: int | None = None
        self.calls: list[tuple] = []
        self.storage: dict[tuple[str, str], bytes] = {}
        self.events: deque[tuple[int, object]] = deque()
        self.counter = 0


def make_gphoto2_double() -> types.SimpleNamespace:
    """A fresh module-like namespace; ``.rig`` controls and records the simulated camera."""
    rig = Rig()

    class PortInfo:
        def __init__(self, path: str) -> None:
            self.path = path

        def get_path(self) -> str:
            return self.path

    class PortInfoList:
        def load(self) -> None:
            rig.calls.append(("ports.load",))

        def lookup_path(self, path: str) -> int:
            if path not in rig.ports:
                raise GPhoto2Error(GP_ERROR_UNKNOWN_PORT)
            return rig.ports.index(path)

        def __getitem__(self, index: int) -> PortInfo:
            return PortInfo(rig.ports[index])

    class Camera:
        @staticmethod
        def autodetect():
            return list(rig.cameras)

        def __init__(self) -> None:
            self.port: str | None = None
            self.initialised = False

        def set_port_info(self, info: PortInfo) -> None:
            self.port = info.get_path()
            rig.calls.append(("set_port_info", self.port))

        def init(self) -> None:
            rig.calls.append(("init", self.port))
            if rig.init_error is not None:
                raise GPhoto2Error(rig.init_error)
            if self.port not in {addr for _, addr in rig.cameras}:
                raise GPhoto2Error(GP_ERROR_MODEL_NOT_FOUND)
            self.initialised = True
            rig.events.extend(rig.leftover_events)

        def exit(self) -> None:
            rig.calls.append(("exit",))
            self.initialised = False

        def _check(self) -> None:
            if not self.initialised:
                raise GPhoto2Error(GP_ERROR)

        def get_config(self) -> Widget:
            self._check()
            return rig.config.copy()

        def set_config(self, config: Widget) -> None:
            self._check()
            rig.calls.append(("set_config",))
            rig.config = config.copy()

        def trigger_capture(self) -> None:
            self._check()
            rig.calls.append(("trigger_capture",))
            if rig.trigger_error is not None:
                raise GPhoto2Error(rig.trigger_error)
            if not rig.shots:
                return  # the camera never delivers: the driver must time out
            shot = rig.shots.popleft()
            rig.events.extend([(GP_EVENT_TIMEOUT, None)] * shot.delay_events)
            folder = (
                "/"
                if rig.config.get_child_by_name("capturetarget").value == "Internal RAM"
                else "/store_00020001/DCIM/100CANON"
            )
            for name, data in shot.files.items():
                rig.storage[(folder, name)] = data
                rig.events.append((GP_EVENT_FILE_ADDED, CameraFilePath(folder, name)))
            rig.events.append((GP_EVENT_CAPTURE_COMPLETE, None))

        def wait_for_event(self, timeout_ms: int):
            self._check()
            rig.calls.append(("wait_for_event", timeout_ms))
            if rig.events:
                return rig.events.popleft()
            return GP_EVENT_TIMEOUT, None

        def file_get(self, folder: str, name: str, kind: int) -> CameraFile:
            self._check()
            rig.calls.append(("file_get", folder, name, kind))
            if (folder, name) not in rig.storage:
                raise GPhoto2Error(GP_ERROR_BAD_PARAMETERS)
            return CameraFile(rig.storage[(folder, name)])

        def file_delete(self, folder: str, name: str) -> None:
            self._check()
            rig.calls.append(("file_delete", folder, name))
            rig.storage.pop((folder, name), None)

    module = types.SimpleNamespace(
        Camera=Camera,
        PortInfoList=PortInfoList,
        GPhoto2Error=GPhoto2Error,
        rig=rig,
    )
    for name, value in list(globals().items()):
        if name.startswith("GP_"):
            setattr(module, name, value)
    return module
