"""A PTP/IP camera on 127.0.0.1 (``ps-lab rig serve-camera``): libgphoto2 talks to it over TCP.

Written from PTP (ISO 15740) and PTP/IP (CIPA DC-005). An initiator (libgphoto2's ``ptpip``
port) opens the command/data connection with an Init Command Request and gets an Init Command
Ack carrying a connection number, then opens the event connection with an Init Event Request
naming that number. Operations, their data phases (Start Data, Data..., End Data) and
responses then run on the first connection; ObjectAdded and CaptureComplete arrive on the
second. One initiator at a time: a second one gets Init Fail (busy) — unless the place is
held by a dead or half-open initiator: one whose connection was closed or reset (seen at once),
whose event connection has not come within ``EVENT_WAIT_S``, that stopped halfway through a
packet for ``STALL_S`` (either: ``CONTENDED_S`` when another initiator asks), that was silent
for ``YIELD_S`` with no capture running when another one asks, or that vanished from the network
(TCP keepalive). Its place is released and the newcomer served.

Supported: GetDeviceInfo (also outside a session), OpenSession / CloseSession, GetStorageIDs /
GetStorageInfo (one flat in-memory store), GetNumObjects / GetObjectHandles / GetObjectInfo /
GetObject / DeleteObject, InitiateCapture (each capture renders a DNG through ``shoot`` and
reports it by ObjectAdded then CaptureComplete) and GetDevicePropDesc / GetDevicePropValue /
SetDevicePropValue for ExposureTime, ExposureIndex (ISO) and FNumber, which set the next frame's
exposure and gain. Anything else is answered OperationNotSupported; an unknown property
DevicePropNotSupported, a value off the enumeration InvalidDevicePropValue, a capture or setting
change while a capture is in progress DeviceBusy.

Faults (``at`` = the n-th InitiateCapture received, 1-based): ``busy`` (answered DeviceBusy),
``timeout`` (accepted, but no object is ever reported), ``disconnect`` (both connections are
dropped halfway through that capture's GetObject), ``slow`` (that download is spread over
``slow_s`` seconds).
"""

from __future__ import annotations

import hashlib
import logging
import select
import socket
import struct
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ps_lab.capture.faults import PTPIP_FAULT_KINDS, Fault
from ps_lab.capture.simulated import ptp
from ps_lab.capture.simulated.serving import ThreadServedSimulator
from ps_lab.errors import RigError

__all__ = ["DEFAULT_PORT", "PtpIpCamera", "ServedFrame", "dng_shooter"]

log = logging.getLogger("ps_lab.capture.simulated.ptpip")

#: The PTP/IP port (IANA: ptp-ip, 15740).
DEFAULT_PORT = 15740
STORAGE_ID = 0x00010001
_CHUNK = 256 * 1024  # payload bytes per Data packet
#: Seconds a connection has for its first packet, and a packet (or a send) for its remaining bytes.
STALL_S = 10.0
#: Seconds an initiator has between its Init Command Ack and its Init Event Request
#: (libgphoto2 sends it at once).
EVENT_WAIT_S = 5.0
#: ... and, with another initiator waiting, for that or for the rest of a packet it started.
CONTENDED_S = 0.25
#: Seconds of silence after which a connected initiator yields to a new one (no capture running).
YIELD_S = 5.0
_POLL_S = 0.25  # housekeeping period of a connection's thread
_MAX_HANDSHAKES = 256  # connections waiting for their first packet; more are closed at once

#: shoot(frame_index, exposure_s, gain_scale) -> the DNG file's bytes.
Shooter = Callable[[int, float, float], bytes]

_SUPPORTED_OPERATIONS = (
    ptp.GET_DEVICE_INFO,
    ptp.OPEN_SESSION,
    ptp.CLOSE_SESSION,
    ptp.GET_STORAGE_IDS,
    ptp.GET_STORAGE_INFO,
    ptp.GET_NUM_OBJECTS,
    ptp.GET_OBJECT_HANDLES,
    ptp.GET_OBJECT_INFO,
    ptp.GET_OBJECT,
    ptp.DELETE_OBJECT,
    ptp.INITIATE_CAPTURE,
    ptp.GET_DEVICE_PROP_DESC,
    ptp.GET_DEVICE_PROP_VALUE,
    ptp.SET_DEVICE_PROP_VALUE,
)
_PROPERTIES = {
    ptp.PROP_F_NUMBER: ptp.EnumProperty(ptp.PROP_F_NUMBER, ptp.UINT16, 800, ptp.F_NUMBERS),
    ptp.PROP_EXPOSURE_TIME: ptp.EnumProperty(
        ptp.PROP_EXPOSURE_TIME, ptp.UINT32, 500, ptp.EXPOSURE_TIMES
    ),
    ptp.PROP_EXPOSURE_INDEX: ptp.EnumProperty(
        ptp.PROP_EXPOSURE_INDEX, ptp.UINT16, 100, ptp.ISO_VALUES
    ),
}


@dataclass(frozen=True)
class ServedFrame:
    """A frame the camera shot: object handle, file name, SHA-256 and size of its bytes."""

    handle: int
    name: str
    sha256: str
    size: int


@dataclass
class _Object:
    handle: int
    name: str
    data: bytes
    date: str
    fault: str | None = None  # "disconnect" | "slow" on its download


def _nearest(values: Iterable[int], target: float) -> int:
    return min(values, key=lambda v: abs(v - target))


def dng_shooter(camera: Any) -> Shooter:
    """Turn a :class:`~ps_lab.capture.simulated.simulated_camera.SimulatedCamera` into a shooter.

    Each call sets the camera's exposure and gain (``gain_scale`` times the rig's, from ISO and
    f-number), renders the frame under the lights lit now, and returns the DNG's bytes.
    """
    base_gain = camera.gain
    lock = threading.Lock()

    def shoot(frame_index: int, exposure_s: float, gain_scale: float) -> bytes:
        with lock, tempfile.TemporaryDirectory(prefix="ps-lab-ptpip-") as folder:
            camera.exposure_s = exposure_s
            camera.gain = base_gain * gain_scale
            path = Path(folder) / "frame.dng"
            camera.capture(path, frame_index=frame_index)
            return path.read_bytes()

    return shoot


class PtpIpCamera(ThreadServedSimulator):
    """A PTP/IP responder serving frames from ``shoot`` on ``host:port``.

    Parameters
    ----------
    shoot : callable
        ``shoot(frame_index, exposure_s, gain_scale) -> bytes`` renders one capture (a DNG);
        ``frame_index`` counts the frames shot (0-based), ``gain_scale`` is
        ``(iso / 100) * (8 / f_number) ** 2``.
    host, port : str, int
        Where to listen; port 0 picks a free port (see :attr:`port` after :meth:`start`).
    faults : iterable of Fault
        ``busy``, ``timeout``, ``disconnect``, ``slow`` at the n-th InitiateCapture.
    exposure_s, iso, f_number : float
        Initial property values (snapped to the nearest enumerated value).
    slow_s : float
        How long a ``slow`` download takes.
    keep_dir : path, optional
        Also write every frame shot there under its camera file name.
    model : str
        Model and friendly name reported to the initiator.

    """

    def __init__(
        self,
        shoot: Shooter,
        *,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        faults: Iterable[Fault] = (),
        exposure_s: float = 0.05,
        iso: float = 100,
        f_number: float = 8.0,
        slow_s: float = 2.0,
        keep_dir: Path | str | None = None,
        model: str = "ps-lab simulated camera",
        events_on_default_port: bool = False,
    ) -> None:
        self.shoot = shoot
        # libgphoto2 opens the event connection on 15740 for ``ptpip:HOST:N`` (only
        # ``ptpip:HOST:N:N`` names it): listening there too lets the short form work.
        self.events_on_default_port = bool(events_on_default_port)
        self.host = host
        self.port = int(port)
        self.faults: dict[int, str] = {}
        for fault in faults:
            if fault.kind not in PTPIP_FAULT_KINDS or fault.at is None:
                raise RigError(
                    f"PTP/IP camera fault {fault}: use KIND@N with KIND one of "
                    f"{', '.join(PTPIP_FAULT_KINDS)}"
                )
            self.faults[fault.at] = fault.kind
        self.slow_s = float(slow_s)
        self.keep_dir = Path(keep_dir) if keep_dir is not None else None
        self.model = model
        self.values = {
            ptp.PROP_EXPOSURE_TIME: _nearest(ptp.EXPOSURE_TIMES, exposure_s * 10000),
            ptp.PROP_EXPOSURE_INDEX: _nearest(ptp.ISO_VALUES, iso),
            ptp.PROP_F_NUMBER: _nearest(ptp.F_NUMBERS, f_number * 100),
        }
        self.guid = hashlib.md5(model.encode()).digest()  # stable 16-byte GUID
        #: Every frame shot, in order (downloaded or not).
        self.frames: list[ServedFrame] = []
        #: InitiateCapture requests received (the fault counter).
        self.captures = 0
        self._objects: dict[int, _Object] = {}
        self._next_handle = 1
        self._shots = 0
        self._lock = threading.RLock()
        self._event_lock = threading.Lock()
        self._listener: socket.socket | None = None
        self._extra_listener: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._command: socket.socket | None = None
        self._event: socket.socket | None = None
        self._connection = 0  # connection number of the active initiator
        self._held_since = 0.0  # time.monotonic() when the active initiator got its place
        self._heard = 0.0  # ... and when it last sent a packet
        self._handshakes = threading.BoundedSemaphore(_MAX_HANDSHAKES)
        self._reading: dict[socket.socket, float] = {}  # connection -> since when, mid-packet
        self._session = 0
        self._capturing = False
        self._operating = False
        self._workers: list[threading.Thread] = []

    # -- lifecycle --------------------------------------------------------------------------
    @property
    def address(self) -> str:
        """The gphoto2 port of this camera: ``ptpip:HOST:PORT:PORT`` (or ``ptpip:HOST`` on 15740).

        libgphoto2 opens the event connection on the port after a second colon, 15740 if none;
        this camera takes both connections on one port.
        """
        return self.address_of(self.host, self.port)

    @staticmethod
    def address_of(host: str, port: int) -> str:
        """The gphoto2 port of a PTP/IP camera taking both connections on ``host:port``."""
        return f"ptpip:{host}" if port == DEFAULT_PORT else f"ptpip:{host}:{port}:{port}"

    def start(self) -> PtpIpCamera:
        """Listen and serve in background threads; return self."""
        if self._thread is not None:
            raise RigError("the PTP/IP camera is already being served")
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            listener.bind((self.host, self.port))
        except OSError as exc:
            listener.close()
            raise RigError(f"cannot listen on {self.host}:{self.port}: {exc.strerror}") from None
        listener.listen(128)
        self._listener = listener
        self.port = listener.getsockname()[1]
        if self.events_on_default_port and self.port != DEFAULT_PORT:
            self._extra_listener = self._listen_on_default_port()
        if self.keep_dir is not None:
            self.keep_dir.mkdir(parents=True, exist_ok=True)
        self._stop.clear()
        self._thread = threading.Thread(target=self._accept, name="ps-lab-ptpip", daemon=True)
        self._thread.start()
        log.info("PTP/IP camera %r on %s", self.model, self.address)
        return self

    def _listen_on_default_port(self) -> socket.socket | None:
        """A second listener on 15740 for event connections, or None when it is taken."""
        extra = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        extra.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            extra.bind((self.host, DEFAULT_PORT))
        except OSError as exc:
            extra.close()
            log.info("PTP/IP camera: port %d taken (%s): use %s", DEFAULT_PORT, exc.strerror,
                     self.address)
            return None
        extra.listen(128)
        return extra

    def stop(self) -> None:
        """Stop serving and close every connection (idempotent)."""
        self._stop.set()
        self._drop()
        for attribute in ("_listener", "_extra_listener"):
            listener = getattr(self, attribute)
            if listener is not None:
                listener.close()
                setattr(self, attribute, None)
        self._end_thread()
        for worker in self._workers:
            worker.join(timeout=30.0)
        self._workers.clear()

    # -- connections ------------------------------------------------------------------------
    def _accept(self) -> None:
        while not self._stop.is_set():
            listeners = [x for x in (self._listener, self._extra_listener) if x is not None]
            if self._listener is None:
                return
            try:
                readable, _, _ = select.select(listeners, [], [], 0.1)
                if not readable:
                    continue
                conn, _ = readable[0].accept()
            except (OSError, ValueError):
                return
            try:
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                ptp.keep_alive(conn)
            except OSError:  # reset before we looked at it
                conn.close()
                continue
            if not self._handshakes.acquire(blocking=False):  # too many not yet introduced
                conn.close()
                continue
            threading.Thread(
                target=self._handshake, args=(conn,), name="ps-lab-ptpip-conn", daemon=True
            ).start()

    def _handshake(self, conn: socket.socket) -> None:
        """Serve one connection until it ends; nothing it does escapes as a traceback."""
        try:
            try:
                conn.settimeout(STALL_S)
                kind, payload = ptp.read_packet(conn)
            finally:
                self._handshakes.release()
            if kind == ptp.INIT_COMMAND_REQUEST:
                self._serve_command(conn, payload)
            elif kind == ptp.INIT_EVENT_REQUEST:
                self._serve_events(conn, payload)
            else:
                log.info("PTP/IP camera: first packet of type %d; closing", kind)
        except (ptp.ConnectionEnded, OSError, struct.error, ValueError) as exc:
            log.debug("PTP/IP camera: connection ended: %s", exc)
        except Exception as exc:  # a bug here must not take the camera down nor print
            log.warning("PTP/IP camera: connection dropped after an internal error: %r", exc)
            log.debug("PTP/IP camera: traceback", exc_info=True)
        finally:
            conn.close()

    def _packets(self, conn: socket.socket, check: Callable[[], str | None]):
        """Yield ``conn``'s packets; return when ``check()`` gives a reason to end (logged)."""
        while not self._stop.is_set():
            if not ptp.wait_readable(conn, _POLL_S):
                reason = check()
                if reason:
                    log.info("PTP/IP camera: %s; its place is released", reason)
                    return
                continue
            self._reading[conn] = time.monotonic()
            try:
                packet = ptp.read_packet(conn)  # the rest of it within STALL_S (socket timeout)
            finally:
                self._reading.pop(conn, None)
            yield packet

    def _stale_reason(self) -> str | None:
        """Why the active initiator should give its place to a newcomer, or None (lock held)."""
        now = time.monotonic()
        if ptp.is_dead(self._command):
            return "the initiator's command connection was closed"
        partial = [now - self._reading.get(c, now) for c in (self._command, self._event)]
        if max(partial) > CONTENDED_S:
            return f"the initiator stopped halfway through a packet {max(partial):.1f} s ago"
        if self._event is None:
            if now - self._held_since > CONTENDED_S:
                return "the initiator never opened its event connection"
        elif ptp.is_dead(self._event):
            return "the initiator's event connection was closed"
        elif now - self._heard > YIELD_S and not (self._capturing or self._operating):
            return f"the initiator was silent for {now - self._heard:.0f} s"
        return None

    def _serve_command(self, conn: socket.socket, payload: bytes) -> None:
        with self._lock:
            if self._command is not None:
                reason = self._stale_reason()
                if reason is None:
                    conn.sendall(ptp.packet(ptp.INIT_FAIL, ptp.u32(ptp.FAIL_BUSY)))
                    return
                log.info("PTP/IP camera: %s; a new initiator takes its place", reason)
                self._drop()
            self._connection += 1
            self._command = conn
            self._held_since = self._heard = time.monotonic()
            number = self._connection

        def check() -> str | None:
            waited = time.monotonic() - self._held_since
            if self._command is conn and self._event is None and waited > EVENT_WAIT_S:
                return f"no event connection {EVENT_WAIT_S:g} s after the Init Command Ack"
            return None

        try:
            initiator = ptp.utf16_name(payload[16:])
            log.info("PTP/IP camera: initiator %r connected (connection %d)", initiator, number)
            name = self.model.encode("utf-16-le") + b"\x00\x00"
            ack = ptp.u32(number) + self.guid + name + ptp.u32(ptp.PTPIP_VERSION)
            conn.sendall(ptp.packet(ptp.INIT_COMMAND_ACK, ack))
            for kind, payload in self._packets(conn, check):
                self._heard = time.monotonic()
                if kind == ptp.OPERATION_REQUEST:
                    self._operating = True  # a long download is not silence
                    try:
                        self._operation(conn, ptp.Request.parse(payload))
                    finally:
                        self._operating = False
                        self._heard = time.monotonic()
                elif kind == ptp.PROBE_REQUEST:
                    conn.sendall(ptp.packet(ptp.PROBE_RESPONSE))
                else:
                    log.info("PTP/IP camera: unexpected packet type %d on the command line", kind)
        finally:
            with self._lock:
                if self._command is conn:
                    self._drop()

    def _serve_events(self, conn: socket.socket, payload: bytes) -> None:
        number = struct.unpack_from("<I", payload)[0] if len(payload) >= 4 else -1
        with self._lock:
            if self._command is None or number != self._connection or self._event is not None:
                conn.sendall(ptp.packet(ptp.INIT_FAIL, ptp.u32(ptp.FAIL_REJECTED_INITIATOR)))
                return
            self._event = conn
            self._heard = time.monotonic()
        try:
            with self._event_lock:
                conn.sendall(ptp.packet(ptp.INIT_EVENT_ACK))
            for kind, _ in self._packets(conn, lambda: None):
                self._heard = time.monotonic()
                if kind == ptp.PROBE_REQUEST:
                    with self._event_lock:
                        conn.sendall(ptp.packet(ptp.PROBE_RESPONSE))
        finally:
            with self._lock:
                if self._event is conn:
                    self._drop()

    def _drop(self) -> None:
        """Close both connections and the session (the initiator must connect again)."""
        with self._lock:
            for sock in (self._command, self._event):
                if sock is not None:
                    try:
                        sock.shutdown(socket.SHUT_RDWR)
                    except OSError:
                        pass
                    sock.close()
            if self._command is not None:
                log.info("PTP/IP camera: initiator disconnected; session closed")
            self._command = self._event = None
            self._session = 0

    def _send_event(self, code: int, params: tuple[int, ...] = ()) -> None:
        with self._event_lock:
            sock = self._event
            if sock is None:
                log.info("PTP/IP camera: event 0x%04x lost: no event connection", code)
                return
            try:
                sock.sendall(ptp.event(code, 0xFFFFFFFF, params))
            except OSError as exc:
                log.info("PTP/IP camera: event 0x%04x lost: %s", code, exc)  # the reader drops it

    # -- operations -------------------------------------------------------------------------
    def _operation(self, conn: socket.socket, req: ptp.Request) -> None:
        data_out = None
        if req.code == ptp.SET_DEVICE_PROP_VALUE or req.phase == 2:
            data_out = ptp.read_data(conn)
        handler = _HANDLERS.get(req.code)
        if handler is None:
            code, data, params = ptp.OPERATION_NOT_SUPPORTED, None, ()
        elif req.code not in (ptp.GET_DEVICE_INFO, ptp.OPEN_SESSION) and not self._session:
            code, data, params = ptp.SESSION_NOT_OPEN, None, ()
        else:
            code, data, params = handler(self, req, data_out)
        log.debug("PTP/IP camera: op 0x%04x %s -> 0x%04x", req.code, req.params, code)
        if data is not None:
            if isinstance(data, _Object):
                self._send_object(conn, req.transaction, data)
            else:
                ptp.send_data(conn, req.transaction, data)
        conn.sendall(ptp.response(code, req.transaction, params))

    def _device_info(self, req: ptp.Request, _: bytes | None) -> tuple[int, bytes, tuple]:
        return ptp.OK, ptp.device_info(self.model, _SUPPORTED_OPERATIONS, sorted(_PROPERTIES)), ()

    def _open_session(self, req: ptp.Request, _: bytes | None) -> tuple[int, None, tuple]:
        session = req.params[0] if req.params else 0
        if self._session:
            return ptp.SESSION_ALREADY_OPEN, None, (self._session,)
        if session == 0:
            return ptp.INVALID_PARAMETER, None, ()
        self._session = session
        return ptp.OK, None, ()

    def _close_session(self, req: ptp.Request, _: bytes | None) -> tuple[int, None, tuple]:
        self._session = 0
        return ptp.OK, None, ()

    def _storage_ids(self, req: ptp.Request, _: bytes | None) -> tuple[int, bytes, tuple]:
        return ptp.OK, ptp.u32_array((STORAGE_ID,)), ()

    def _storage_info(self, req: ptp.Request, _: bytes | None) -> tuple[int, bytes | None, tuple]:
        if not req.params or req.params[0] != STORAGE_ID:
            return ptp.INVALID_STORAGE_ID, None, ()
        capacity = 1 << 30
        with self._lock:
            used = sum(len(o.data) for o in self._objects.values())
        return ptp.OK, ptp.storage_info(capacity, max(0, capacity - used)), ()

    def _handles(self, req: ptp.Request) -> tuple[int, list[int]]:
        storage = req.params[0] if req.params else 0xFFFFFFFF
        fmt = req.params[1] if len(req.params) > 1 else 0
        parent = req.params[2] if len(req.params) > 2 else 0
        if storage not in (STORAGE_ID, 0xFFFFFFFF):
            return ptp.INVALID_STORAGE_ID, []
        with self._lock:
            handles = sorted(self._objects)
        if parent not in (0, 0xFFFFFFFF):  # a flat store: no object is an association
            code = ptp.INVALID_PARENT_OBJECT if parent not in handles else ptp.OK
            return code, []
        if fmt not in (0, ptp.FORMAT_TIFF):
            return ptp.OK, []
        return ptp.OK, handles

    def _num_objects(self, req: ptp.Request, _: bytes | None) -> tuple[int, None, tuple]:
        code, handles = self._handles(req)
        return code, None, (len(handles),) if code == ptp.OK else ()

    def _object_handles(self, req: ptp.Request, _: bytes | None) -> tuple[int, Any, tuple]:
        code, handles = self._handles(req)
        return code, ptp.u32_array(handles) if code == ptp.OK else None, ()

    def _object(self, req: ptp.Request) -> _Object | None:
        with self._lock:
            return self._objects.get(req.params[0] if req.params else 0)

    def _object_info(self, req: ptp.Request, _: bytes | None) -> tuple[int, Any, tuple]:
        obj = self._object(req)
        if obj is None:
            return ptp.INVALID_OBJECT_HANDLE, None, ()
        return ptp.OK, ptp.object_info(STORAGE_ID, len(obj.data), obj.name, obj.date), ()

    def _get_object(self, req: ptp.Request, _: bytes | None) -> tuple[int, Any, tuple]:
        obj = self._object(req)
        if obj is None:
            return ptp.INVALID_OBJECT_HANDLE, None, ()
        return ptp.OK, obj, ()

    def _delete_object(self, req: ptp.Request, _: bytes | None) -> tuple[int, None, tuple]:
        handle = req.params[0] if req.params else 0
        with self._lock:
            if handle == 0xFFFFFFFF:
                self._objects.clear()
            elif self._objects.pop(handle, None) is None:
                return ptp.INVALID_OBJECT_HANDLE, None, ()
        return ptp.OK, None, ()

    def _prop(self, req: ptp.Request) -> ptp.EnumProperty | None:
        return _PROPERTIES.get(req.params[0] if req.params else 0)

    def _prop_desc(self, req: ptp.Request, _: bytes | None) -> tuple[int, Any, tuple]:
        prop = self._prop(req)
        if prop is None:
            return ptp.DEVICE_PROP_NOT_SUPPORTED, None, ()
        return ptp.OK, prop.describe(self.values[prop.code]), ()

    def _prop_value(self, req: ptp.Request, _: bytes | None) -> tuple[int, Any, tuple]:
        prop = self._prop(req)
        if prop is None:
            return ptp.DEVICE_PROP_NOT_SUPPORTED, None, ()
        return ptp.OK, prop.pack_value(self.values[prop.code]), ()

    def _set_prop(self, req: ptp.Request, data: bytes | None) -> tuple[int, None, tuple]:
        prop = self._prop(req)
        if prop is None:
            return ptp.DEVICE_PROP_NOT_SUPPORTED, None, ()
        try:
            value = prop.unpack_value(data or b"")
        except ValueError:
            return ptp.INVALID_DEVICE_PROP_FORMAT, None, ()
        if value not in prop.values:
            return ptp.INVALID_DEVICE_PROP_VALUE, None, ()
        with self._lock:
            if self._capturing:
                return ptp.DEVICE_BUSY, None, ()
            self.values[prop.code] = value
        log.info("PTP/IP camera: property 0x%04x = %d", prop.code, value)
        return ptp.OK, None, ()

    def _initiate_capture(self, req: ptp.Request, _: bytes | None) -> tuple[int, None, tuple]:
        storage = req.params[0] if req.params else 0
        fmt = req.params[1] if len(req.params) > 1 else 0
        if storage not in (0, STORAGE_ID):
            return ptp.INVALID_STORAGE_ID, None, ()
        if fmt not in (0, ptp.FORMAT_TIFF):
            return ptp.INVALID_OBJECT_FORMAT_CODE, None, ()
        with self._lock:
            self.captures += 1
            fault = self.faults.get(self.captures)
            if self._capturing or fault == "busy":
                log.info("PTP/IP camera: capture %d answered DeviceBusy", self.captures)
                return ptp.DEVICE_BUSY, None, ()
            if fault == "timeout":
                log.warning("PTP/IP camera: injected fault: capture %d unreported", self.captures)
                return ptp.OK, None, ()
            self._capturing = True
        worker = threading.Thread(
            target=self._capture, args=(req.transaction, fault), name="ps-lab-ptpip-capture"
        )
        self._workers = [w for w in self._workers if w.is_alive()] + [worker]
        worker.start()
        return ptp.OK, None, ()

    def _capture(self, transaction: int, fault: str | None) -> None:
        try:
            exposure_s = self.values[ptp.PROP_EXPOSURE_TIME] / 10000.0
            iso = self.values[ptp.PROP_EXPOSURE_INDEX]
            f_number = self.values[ptp.PROP_F_NUMBER] / 100.0
            data = self.shoot(self._shots, exposure_s, (iso / 100.0) * (8.0 / f_number) ** 2)
            with self._lock:
                self._shots += 1
                handle = self._next_handle
                self._next_handle += 1
                name = f"IMG_{handle:04d}.DNG"
                obj = _Object(handle, name, data, time.strftime("%Y%m%dT%H%M%S"), fault)
                self._objects[handle] = obj
                self.frames.append(
                    ServedFrame(handle, name, hashlib.sha256(data).hexdigest(), len(data))
                )
            if self.keep_dir is not None:
                (self.keep_dir / name).write_bytes(data)
            log.info("PTP/IP camera: captured %s (%d bytes)", name, len(data))
        except Exception:
            log.exception("PTP/IP camera: the capture failed")
            with self._lock:
                self._capturing = False
            return
        with self._lock:
            self._capturing = False
        self._send_event(ptp.OBJECT_ADDED, (handle,))
        self._send_event(ptp.CAPTURE_COMPLETE, (transaction,))

    def _send_object(self, conn: socket.socket, transaction: int, obj: _Object) -> None:
        data, fault = obj.data, obj.fault
        obj.fault = None  # a fault fires once
        conn.sendall(ptp.packet(ptp.START_DATA, ptp.u32(transaction) + ptp.u64(len(data))))
        chunk = {"slow": -(-len(data) // 20), "disconnect": -(-len(data) // 4)}.get(fault, _CHUNK)
        chunk = max(1, chunk)
        pause = self.slow_s / 20 if fault == "slow" else 0.0
        if fault == "slow":
            log.warning("PTP/IP camera: injected fault: %s takes %g s", obj.name, self.slow_s)
        for start in range(0, len(data), chunk):
            if fault == "disconnect" and start >= len(data) // 2:
                log.warning("PTP/IP camera: injected fault: dropped during %s", obj.name)
                self._drop()
                raise ptp.ConnectionEnded("injected disconnect")
            end = min(len(data), start + chunk)
            kind = ptp.END_DATA if end == len(data) else ptp.DATA
            conn.sendall(ptp.packet(kind, ptp.u32(transaction) + data[start:end]))
            if pause and end < len(data):
                time.sleep(pause)


_HANDLERS: dict[int, Callable[..., tuple[int, Any, tuple]]] = {
    ptp.GET_DEVICE_INFO: PtpIpCamera._device_info,
    ptp.OPEN_SESSION: PtpIpCamera._open_session,
    ptp.CLOSE_SESSION: PtpIpCamera._close_session,
    ptp.GET_STORAGE_IDS: PtpIpCamera._storage_ids,
    ptp.GET_STORAGE_INFO: PtpIpCamera._storage_info,
    ptp.GET_NUM_OBJECTS: PtpIpCamera._num_objects,
    ptp.GET_OBJECT_HANDLES: PtpIpCamera._object_handles,
    ptp.GET_OBJECT_INFO: PtpIpCamera._object_info,
    ptp.GET_OBJECT: PtpIpCamera._get_object,
    ptp.DELETE_OBJECT: PtpIpCamera._delete_object,
    ptp.INITIATE_CAPTURE: PtpIpCamera._initiate_capture,
    ptp.GET_DEVICE_PROP_DESC: PtpIpCamera._prop_desc,
    ptp.GET_DEVICE_PROP_VALUE: PtpIpCamera._prop_value,
    ptp.SET_DEVICE_PROP_VALUE: PtpIpCamera._set_prop,
}
