"""PTP (ISO 15740 / PIMA 15740) and PTP/IP (CIPA DC-005) codes and data-set packing.

Everything on the wire is little-endian. A PTP string is a uint8 count of UTF-16 code units
(terminating NUL included; 0 for the empty string) followed by those units in UTF-16LE. An
array is a uint32 element count followed by the elements. A PTP/IP packet is a uint32 length
(the whole packet, header included), a uint32 packet type and the payload.
"""

from __future__ import annotations

import select
import socket
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

# -- PTP/IP packet types (CIPA DC-005, 2.3) ----------------------------------------------------
INIT_COMMAND_REQUEST = 1
INIT_COMMAND_ACK = 2
INIT_EVENT_REQUEST = 3
INIT_EVENT_ACK = 4
INIT_FAIL = 5
OPERATION_REQUEST = 6
OPERATION_RESPONSE = 7
EVENT = 8
START_DATA = 9
DATA = 10
CANCEL = 11
END_DATA = 12
PROBE_REQUEST = 13
PROBE_RESPONSE = 14

#: Init Fail reasons.
FAIL_REJECTED_INITIATOR = 1
FAIL_BUSY = 2
FAIL_UNSPECIFIED = 3

#: PTP/IP protocol version 1.0 (major in the high 16 bits).
PTPIP_VERSION = 0x00010000

# -- operation codes (ISO 15740, 10.4) ---------------------------------------------------------
GET_DEVICE_INFO = 0x1001
OPEN_SESSION = 0x1002
CLOSE_SESSION = 0x1003
GET_STORAGE_IDS = 0x1004
GET_STORAGE_INFO = 0x1005
GET_NUM_OBJECTS = 0x1006
GET_OBJECT_HANDLES = 0x1007
GET_OBJECT_INFO = 0x1008
GET_OBJECT = 0x1009
DELETE_OBJECT = 0x100B
INITIATE_CAPTURE = 0x100E
GET_DEVICE_PROP_DESC = 0x1014
GET_DEVICE_PROP_VALUE = 0x1015
SET_DEVICE_PROP_VALUE = 0x1016

# -- response codes (ISO 15740, 11) ------------------------------------------------------------
OK = 0x2001
GENERAL_ERROR = 0x2002
SESSION_NOT_OPEN = 0x2003
OPERATION_NOT_SUPPORTED = 0x2005
PARAMETER_NOT_SUPPORTED = 0x2006
INVALID_STORAGE_ID = 0x2008
INVALID_OBJECT_HANDLE = 0x2009
DEVICE_PROP_NOT_SUPPORTED = 0x200A
INVALID_OBJECT_FORMAT_CODE = 0x200B
DEVICE_BUSY = 0x2019
INVALID_PARENT_OBJECT = 0x201A
INVALID_DEVICE_PROP_FORMAT = 0x201B
INVALID_DEVICE_PROP_VALUE = 0x201C
INVALID_PARAMETER = 0x201D
SESSION_ALREADY_OPEN = 0x201E

# -- event codes (ISO 15740, 12) ---------------------------------------------------------------
OBJECT_ADDED = 0x4002
OBJECT_REMOVED = 0x4003
CAPTURE_COMPLETE = 0x400D

# -- device properties (ISO 15740, 13) and data types ------------------------------------------
PROP_F_NUMBER = 0x5007
PROP_EXPOSURE_TIME = 0x500D
PROP_EXPOSURE_INDEX = 0x500F
UINT16 = 0x0004
UINT32 = 0x0006
FORM_ENUMERATION = 2

# -- object formats and storage ----------------------------------------------------------------
FORMAT_ASSOCIATION = 0x3001
FORMAT_TIFF = 0x380D  # DNG is a TIFF/EP file; PTP has no code of its own for it
STORAGE_FIXED_RAM = 0x0003
FILESYSTEM_GENERIC_FLAT = 0x0001
ACCESS_READ_ONLY_WITH_DELETE = 0x0002
STANDARD_VERSION = 100  # PTP 1.00


def u16(value: int) -> bytes:  # noqa: D103 - one-liners
    return struct.pack("<H", value)


def u32(value: int) -> bytes:  # noqa: D103
    return struct.pack("<I", value)


def u64(value: int) -> bytes:  # noqa: D103
    return struct.pack("<Q", value)


def ptp_string(text: str) -> bytes:
    """Pack a PTP string: uint8 count of UTF-16 units with the NUL, then UTF-16LE."""
    if not text:
        return b"\x00"
    units = text.encode("utf-16-le") + b"\x00\x00"
    count = len(units) // 2
    if count > 255:
        raise ValueError(f"PTP strings hold at most 254 characters, got {len(text)}")
    return bytes([count]) + units


def u16_array(values: Iterable[int]) -> bytes:
    """Pack a PTP array of uint16."""
    items = list(values)
    return u32(len(items)) + b"".join(u16(v) for v in items)


def u32_array(values: Iterable[int]) -> bytes:
    """Pack a PTP array of uint32."""
    items = list(values)
    return u32(len(items)) + b"".join(u32(v) for v in items)


def utf16_name(payload: bytes) -> str:
    """Read a NUL-terminated UTF-16LE name (PTP/IP's friendly name) from the start of payload."""
    for end in range(0, len(payload) - 1, 2):
        if payload[end : end + 2] == b"\x00\x00":
            return payload[:end].decode("utf-16-le", errors="replace")
    return payload.decode("utf-16-le", errors="replace")


def packet(kind: int, payload: bytes = b"") -> bytes:
    """A PTP/IP packet: uint32 length (header included), uint32 type, payload."""
    return struct.pack("<II", 8 + len(payload), kind) + payload


def response(code: int, transaction: int, params: Sequence[int] = ()) -> bytes:
    """An Operation Response packet."""
    return packet(
        OPERATION_RESPONSE, u16(code) + u32(transaction) + b"".join(u32(p) for p in params)
    )


def event(code: int, transaction: int, params: Sequence[int] = ()) -> bytes:
    """An Event packet (on the event connection)."""
    return packet(EVENT, u16(code) + u32(transaction) + b"".join(u32(p) for p in params))


def device_info(model: str, operations: Sequence[int], properties: Sequence[int]) -> bytes:
    """The DeviceInfo data set of a generic PTP camera storing DNG (as TIFF) files."""
    return (
        u16(STANDARD_VERSION)
        + u32(0)  # VendorExtensionID: none, a generic PTP camera
        + u16(0)
        + ptp_string("")
        + u16(0)  # FunctionalMode: standard
        + u16_array(operations)
        + u16_array((OBJECT_ADDED, OBJECT_REMOVED, CAPTURE_COMPLETE))
        + u16_array(properties)
        + u16_array((FORMAT_TIFF,))
        + u16_array((FORMAT_TIFF,))
        + ptp_string("ps-lab")
        + ptp_string(model)
        + ptp_string("1.0")
        + ptp_string("PSLAB0001")
    )


def storage_info(capacity: int, free: int) -> bytes:
    """The StorageInfo data set of one flat in-memory store."""
    return (
        u16(STORAGE_FIXED_RAM)
        + u16(FILESYSTEM_GENERIC_FLAT)
        + u16(ACCESS_READ_ONLY_WITH_DELETE)
        + u64(capacity)
        + u64(free)
        + u32(0xFFFFFFFF)  # free space in images: not used
        + ptp_string("Internal RAM")
        + ptp_string("")
    )


def object_info(storage: int, size: int, name: str, date: str) -> bytes:
    """The ObjectInfo data set of a DNG file (as TIFF) in the root of ``storage``."""
    return (
        u32(storage)
        + u16(FORMAT_TIFF)
        + u16(0)  # protection: none
        + u32(size)
        + u16(0)  # no thumbnail
        + u32(0) * 3
        + u32(0) * 3  # image size and depth: not reported
        + u32(0)  # parent: the root
        + u16(0)
        + u32(0)
        + u32(0)
        + ptp_string(name)
        + ptp_string(date)
        + ptp_string(date)
        + ptp_string("")
    )


@dataclass(frozen=True)
class Request:
    """An Operation Request: data-phase info, operation code, transaction id, parameters."""

    phase: int
    code: int
    transaction: int
    params: tuple[int, ...]

    @classmethod
    def parse(cls, payload: bytes) -> Request:
        """Read an Operation Request payload (after the 8-byte header)."""
        if len(payload) < 10:
            raise ValueError(f"operation request of {len(payload)} bytes; needs at least 10")
        phase, code, transaction = struct.unpack_from("<IHI", payload)
        count = min(5, (len(payload) - 10) // 4)
        params = struct.unpack_from(f"<{count}I", payload, 10) if count else ()
        return cls(phase, code, transaction, tuple(params))


@dataclass(frozen=True)
class EnumProperty:
    """A device property with an enumeration form: code, data type, current and allowed values."""

    code: int
    data_type: int
    default: int
    values: tuple[int, ...]

    def pack_value(self, value: int) -> bytes:
        """The value in the property's data type."""
        return u16(value) if self.data_type == UINT16 else u32(value)

    def unpack_value(self, data: bytes) -> int:
        """Read a value sent by SetDevicePropValue; ValueError if its size is wrong."""
        size = 2 if self.data_type == UINT16 else 4
        if len(data) != size:
            raise ValueError(f"expected {size} bytes, got {len(data)}")
        return int.from_bytes(data, "little")

    def describe(self, current: int) -> bytes:
        """The DevicePropDesc data set (get/set, enumeration form)."""
        return (
            u16(self.code)
            + u16(self.data_type)
            + bytes([1])  # GetSet: get/set
            + self.pack_value(self.default)
            + self.pack_value(current)
            + bytes([FORM_ENUMERATION])
            + u16(len(self.values))
            + b"".join(self.pack_value(v) for v in self.values)
        )


#: Standard exposure times in PTP's unit (0.1 ms), 1/2000 s to 30 s.
EXPOSURE_TIMES = (
    5, 10, 20, 40, 80, 125, 166, 250, 333, 400, 500, 666, 800, 1000, 1250, 1666, 2000, 2500,
    3333, 5000, 10000, 20000, 40000, 80000, 150000, 300000,
)  # fmt: skip
ISO_VALUES = (100, 200, 400, 800, 1600, 3200)
F_NUMBERS = (280, 400, 560, 800, 1100, 1600, 2200)  # in 1/100


class ConnectionEnded(Exception):
    """The connection ended (end of stream, reset, or an injected disconnect)."""


def recv_exact(conn: socket.socket, size: int) -> bytes:
    """Read exactly ``size`` bytes; ConnectionEnded at end of stream."""
    chunks, remaining = [], size
    while remaining:
        chunk = conn.recv(min(remaining, 1 << 20))
        if not chunk:
            raise ConnectionEnded("end of stream")
        chunks.append(chunk)
        remaining -= len(chunk)
    return b"".join(chunks)


def read_packet(conn: socket.socket) -> tuple[int, bytes]:
    """Read one PTP/IP packet: (type, payload)."""
    length, kind = struct.unpack("<II", recv_exact(conn, 8))
    if length < 8 or length > (64 << 20):
        raise ValueError(f"PTP/IP packet length {length}")
    return kind, recv_exact(conn, length - 8)


def read_data(conn: socket.socket, limit: int = 1 << 20) -> bytes:
    """Read an initiator's data phase: Start Data, then Data packets up to End Data.

    ValueError for a phase longer than ``limit`` bytes (this camera's settings are a few bytes).
    """
    kind, _ = read_packet(conn)
    if kind != START_DATA:
        raise ValueError(f"expected a Start Data packet, got type {kind}")
    parts, size = [], 0
    while True:
        kind, payload = read_packet(conn)
        if kind not in (DATA, END_DATA):
            raise ValueError(f"expected a Data packet, got type {kind}")
        parts.append(payload[4:])
        size += len(payload) - 4
        if size > limit:
            raise ValueError(f"data phase over {limit} bytes")
        if kind == END_DATA:
            return b"".join(parts)


def send_data(conn: socket.socket, transaction: int, data: bytes) -> None:
    """Send a data phase as one Start Data and one End Data packet."""
    conn.sendall(packet(START_DATA, u32(transaction) + u64(len(data))))
    conn.sendall(packet(END_DATA, u32(transaction) + data))


def keep_alive(conn: socket.socket, idle_s: int = 5, interval_s: int = 2, count: int = 3) -> None:
    """TCP keepalive: a peer that vanished (no FIN, no RST) is noticed in about 11 s."""
    conn.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    for name, value in (("TCP_KEEPIDLE", idle_s), ("TCP_KEEPINTVL", interval_s),
                        ("TCP_KEEPCNT", count)):  # fmt: skip
        if hasattr(socket, name):  # Linux; elsewhere the system's defaults
            conn.setsockopt(socket.IPPROTO_TCP, getattr(socket, name), value)


def wait_readable(conn: socket.socket, timeout_s: float) -> bool:
    """Whether ``conn`` has something to read (data, end of stream or an error) within timeout."""
    try:
        readable, _, _ = select.select([conn], [], [], timeout_s)
    except (OSError, ValueError):  # closed meanwhile: reading will say so
        return True
    return bool(readable)


def is_dead(conn: socket.socket | None) -> bool:
    """Whether the peer closed or reset ``conn`` (peeks; never consumes a byte)."""
    if conn is None or conn.fileno() < 0:
        return True
    if not wait_readable(conn, 0.0):
        return False
    try:
        return conn.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except (BlockingIOError, InterruptedError):  # its reader took the byte meanwhile
        return False
    except OSError:
        return True
