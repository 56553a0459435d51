"""An OpenEXR file's layout checked from its bytes, before the OpenEXR library reads it.

The OpenEXR binding allocates what a file's header claims before it reads a pixel, and a
truncated file makes it print on stdout and stderr. :func:`exr_layout` reads the layout
itself (OpenEXR File Layout, openexr.com): the magic number ``76 2f 31 01``, the version field
(bit 9 tiled, 10 long names, 11 deep, 12 multi-part), each header's attributes
(``name\\0 type\\0 int32 size, value``) up to a null byte, then the offset table (one uint64
per chunk) and each chunk's leader (its size). Its answer, the data window and channels,
lets the caller check the memory the image needs; a header whose chunks do not fit in the
file is refused with the reason.
"""

from __future__ import annotations

import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from ps_lab.errors import DatasetError

__all__ = ["ExrLayout", "exr_layout"]

MAGIC = b"\x76\x2f\x31\x01"
_TILED, _LONG_NAMES, _DEEP, _MULTIPART = 0x200, 0x400, 0x800, 0x1000
#: Scan lines per chunk for each compression (NONE RLE ZIPS ZIP PIZ PXR24 B44 B44A DWAA DWAB).
LINES_PER_CHUNK = {0: 1, 1: 1, 2: 1, 3: 16, 4: 32, 5: 16, 6: 32, 7: 32, 8: 32, 9: 256}
_SAMPLE_BYTES = {0: 4, 1: 2, 2: 4}  # UINT, HALF, FLOAT
#: No OpenEXR compression packs pixels tighter than this (zlib's limit is 1032:1); a header
#: claiming more pixels than its chunks can hold this way is forged.
MAX_COMPRESSION_RATIO = 2100
_MAX_HEADER = 16 << 20  # bytes of attributes a header may hold


@dataclass(frozen=True)
class ExrLayout:
    """What the headers claim: every part's size, and the bytes its pixels take decoded."""

    height: int  # of the first part (the one read)
    width: int
    channels: int
    pixel_bytes: int  # decoded size of every part together


class _Reader:
    def __init__(self, stream: BinaryIO, size: int) -> None:
        self.stream, self.size = stream, size

    def read(self, count: int, what: str) -> bytes:
        data = self.stream.read(count)
        if len(data) < count:
            raise _Broken(f"truncated OpenEXR file ({what} cut short at byte {self.size})")
        return data

    def name(self, limit: int, what: str) -> bytes:
        out = bytearray()
        while True:
            byte = self.read(1, what)
            if byte == b"\0":
                return bytes(out)
            out += byte
            if len(out) > limit:
                raise _Broken(f"corrupt OpenEXR header ({what} longer than {limit} bytes)")


class _Broken(Exception):
    pass


def exr_layout(path: Path) -> ExrLayout:
    """Check an OpenEXR file's headers, offset tables and chunk sizes against its bytes.

    Parameters
    ----------
    path : Path
        The ``.exr`` file.

    Returns
    -------
    ExrLayout
        The first part's data window height and width and channel count, and the bytes the
        pixels of all parts take decoded (for the caller's memory check).

    Raises
    ------
    DatasetError
        Not an OpenEXR file, a header cut short or malformed, or chunks that lie beyond the end
        of the file or hold fewer bytes than the data window needs (truncated or forged); the
        message names the file.

    """
    path = Path(path)
    try:
        with open(path, "rb") as stream:
            return _layout(_Reader(stream, os.fstat(stream.fileno()).st_size))
    except _Broken as exc:
        raise DatasetError(f"{path}: {exc}") from None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read file ({exc.strerror})") from None


def _layout(reader: _Reader) -> ExrLayout:
    if reader.read(4, "magic number") != MAGIC:
        raise _Broken("not an OpenEXR file (no magic number)")
    version = struct.unpack("<I", reader.read(4, "version field"))[0]
    if version & 0xFF != 2:
        raise _Broken(f"corrupt or unreadable OpenEXR file (version {version & 0xFF}, not 2)")
    limit = 255 if version & _LONG_NAMES else 31
    multipart = bool(version & _MULTIPART)
    headers = []
    while True:
        header = _header(reader, limit)
        if not header:
            if not headers:
                raise _Broken("corrupt OpenEXR file (an empty header)")
            break
        headers.append(header)
        if not multipart:
            break
    parts = [_part(h, version, multipart) for h in headers]
    table_end = reader.stream.tell() + 8 * sum(p.chunks for p in parts)
    if table_end > reader.size:
        first = parts[0]
        raise _Broken(
            f"OpenEXR header claims {first.width}x{first.height} pixels in "
            f"{sum(p.chunks for p in parts)} chunks, but the file ends at byte {reader.size}, "
            "inside their offset table (forged data window, or truncated)"
        )
    tables = [struct.unpack(f"<{p.chunks}Q", reader.read(8 * p.chunks, "offset table"))
              for p in parts]  # fmt: skip
    packed = 0
    for part, table in zip(parts, tables, strict=True):
        leader = (4 if multipart else 0) + (20 if part.tiled else 8)  # (part,) x y [lx ly] size
        for k, offset in enumerate(table[: part.needed]):
            if offset + leader > reader.size:
                raise _Broken(
                    f"truncated OpenEXR file (chunk {k + 1} of {part.chunks} lies beyond its "
                    f"{reader.size} bytes)"
                )
            if part.deep:
                continue
            reader.stream.seek(offset + leader - 4)
            size = struct.unpack("<i", reader.read(4, "chunk leader"))[0]
            if size < 0 or offset + leader + size > reader.size:
                raise _Broken(
                    f"truncated OpenEXR file (chunk {k + 1} of {part.chunks} needs "
                    f"{leader + max(size, 0)} bytes from byte {offset}; the file has {reader.size})"
                )
            packed += size
    decoded = sum(p.pixel_bytes for p in parts)
    ratio = 1 if all(p.compression == 0 for p in parts) else MAX_COMPRESSION_RATIO
    if not any(p.deep for p in parts) and decoded > ratio * packed:
        first = parts[0]
        raise _Broken(
            f"OpenEXR header claims {first.width}x{first.height} pixels but the file holds only "
            f"{packed} bytes of pixel data (forged or truncated header)"
        )
    first = parts[0]
    return ExrLayout(first.height, first.width, first.channels, decoded)


def _header(reader: _Reader, limit: int) -> dict[bytes, tuple[bytes, bytes]]:
    """One header's attributes ``{name: (type, value)}``; empty for the null byte ending a list."""
    attributes: dict[bytes, tuple[bytes, bytes]] = {}
    total = 0
    while True:
        name = reader.name(limit, "attribute name")
        if not name:
            return attributes
        kind = reader.name(limit, f"type of attribute {name.decode('latin-1')!r}")
        size = struct.unpack("<i", reader.read(4, "attribute size"))[0]
        total += max(size, 0)
        if size < 0 or total > _MAX_HEADER or size > reader.size:
            raise _Broken(f"corrupt OpenEXR header (attribute {name.decode('latin-1')!r} of "
                          f"{size} bytes)")  # fmt: skip
        attributes[name] = (kind, reader.read(size, f"attribute {name.decode('latin-1')!r}"))


@dataclass(frozen=True)
class _Part:
    width: int
    height: int
    channels: int
    compression: int
    chunks: int
    pixel_bytes: int
    tiled: bool
    deep: bool
    needed: int  # the chunks read: every one, or the tiles of level 0 (the first listed)


def _part(header: dict[bytes, tuple[bytes, bytes]], version: int, multipart: bool) -> _Part:
    def value(name: bytes, kind: bytes, size: int) -> bytes:
        found = header.get(name)
        if found is None or found[0] != kind or len(found[1]) < size:
            raise _Broken(f"corrupt OpenEXR header (no valid {name.decode()!r} attribute)")
        return found[1]

    x0, y0, x1, y1 = struct.unpack("<4i", value(b"dataWindow", b"box2i", 16)[:16])
    width, height = x1 - x0 + 1, y1 - y0 + 1
    if width < 1 or height < 1:
        raise _Broken(f"corrupt OpenEXR header (data window {width}x{height})")
    channels = _channels(value(b"channels", b"chlist", 1))
    compression = value(b"compression", b"compression", 1)[0]
    kind = header.get(b"type", (b"", b""))[1].rstrip(b"\0")
    deep = bool(version & _DEEP) or kind.startswith(b"deep")
    tiled = (bool(version & _TILED) and not multipart) or kind in (b"tiledimage", b"deeptile")
    if multipart or deep:
        chunks = struct.unpack("<i", value(b"chunkCount", b"int", 4)[:4])[0]
    elif tiled:
        chunks = _tile_count(value(b"tiles", b"tiledesc", 9), width, height)
        needed = _tile_count(value(b"tiles", b"tiledesc", 9), width, height, first_level=True)
    elif compression in LINES_PER_CHUNK:
        chunks = -(-height // LINES_PER_CHUNK[compression])
    else:
        raise _Broken(f"OpenEXR compression {compression} is not one ps-lab knows")
    if not tiled or multipart or deep:
        needed = chunks
    if chunks < 1 or chunks > (1 << 31):
        raise _Broken(f"corrupt OpenEXR header ({chunks} chunks)")
    per_pixel = sum(b / (xs * ys) for b, xs, ys in channels)
    return _Part(width, height, len(channels), compression, chunks,
                 math.ceil(width * height * per_pixel), tiled, deep, needed)  # fmt: skip


def _channels(chlist: bytes) -> list[tuple[int, int, int]]:
    """``(bytes per sample, x sampling, y sampling)`` of each channel of a ``chlist``."""
    out, pos = [], 0
    while pos < len(chlist) and chlist[pos] != 0:
        end = chlist.find(b"\0", pos)
        if end < 0 or end + 17 > len(chlist):
            raise _Broken("corrupt OpenEXR header (channel list cut short)")
        pixel_type, _, xs, ys = struct.unpack("<iB3xii", chlist[end + 1 : end + 17])
        if pixel_type not in _SAMPLE_BYTES or xs < 1 or ys < 1:
            raise _Broken(f"corrupt OpenEXR header (channel {chlist[pos:end].decode('latin-1')!r})")
        out.append((_SAMPLE_BYTES[pixel_type], xs, ys))
        pos = end + 17
    if not out:
        raise _Broken("OpenEXR file without channels")
    return out


def _tile_count(desc: bytes, width: int, height: int, first_level: bool = False) -> int:
    """Tiles of every level (ONE_LEVEL, MIPMAP_LEVELS, RIPMAP_LEVELS; rounding down or up)."""
    tx, ty, mode = struct.unpack("<IIB", desc[:9])
    levels, rounding = mode & 0x0F, mode >> 4
    if tx < 1 or ty < 1 or levels > 2 or rounding > 1:
        raise _Broken(f"corrupt OpenEXR header (tiles {tx}x{ty}, mode {mode})")

    def count(n: int) -> int:  # levels down to 1 pixel: floor or ceil of log2(n), plus 1
        return ((n - 1).bit_length() if rounding else n.bit_length() - 1) + 1

    def size(n: int, level: int) -> int:
        return max(1, -(-n // (1 << level)) if rounding else n >> level)

    def tiles(w: int, h: int) -> int:
        return -(-w // tx) * -(-h // ty)

    if levels == 0 or first_level:
        return tiles(width, height)
    if levels == 1:  # mipmap: both axes halved together
        return sum(tiles(size(width, k), size(height, k)) for k in range(count(max(width, height))))
    return sum(tiles(size(width, i), size(height, j))
               for i in range(count(width)) for j in range(count(height)))  # fmt: skip
