"""The files the viewer page loads: a manifest, tiled image pyramids, mesh buffers.

Each result's layers (:data:`ps_lab.view.result.CHANNELS`) become a pyramid: level 0 is the full
image, level k+1 halves level k (2 x 2 blocks averaged over their mask pixels; normals
renormalised), up to the first level that fits one tile. Every level is cut into tiles of
:data:`TILE` x :data:`TILE` pixels, each stored as two RGBA half-float (IEEE binary16,
little-endian) planes, ``(nx, ny, nz, albedo)`` then ``(outliers, error, relief, depth)``, which
WebGL 2 uploads as ``RGBA16F`` textures without conversion. The page draws the one-tile top level
first, then the tiles of the level that matches the zoom (so a 12 MP result is interactive at
once and sharpens as its tiles arrive).

Paths, relative to the page: ``data/manifest.json``, ``data/r{i}/{level}/{col}_{row}.bin``,
``data/r{i}/mesh.bin`` (float32 positions, float32 normals, uint32 triangles, RGBA8 colours).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterator

import numpy as np

from ps_lab.io.files import json_safe
from ps_lab.view.result import CHANNELS, ViewResult

__all__ = [
    "TILE",
    "Pyramid",
    "block_sum",
    "half_float",
    "manifest",
    "mesh_address",
    "mesh_bytes",
    "pad_even",
    "pyramid",
    "tile_address",
]

#: Tile side in pixels.
TILE = 512

#: Stored in place of a missing value in the error and relief channels (the shader tests < 0).
MISSING = -1.0


#: A number in a data path: decimal ASCII digits, no sign, no leading zero, at most 6 digits
#: (a tile index of 5,000 digits is no path of the site, and never reaches ``int()``).
_NUMBER = r"(0|[1-9][0-9]{0,5})"
_TILE_PATH = re.compile(rf"data/r{_NUMBER}/{_NUMBER}/{_NUMBER}_{_NUMBER}\.bin", re.ASCII)
_MESH_PATH = re.compile(rf"data/r{_NUMBER}/mesh\.bin", re.ASCII)

#: No data path is longer (four 6-digit numbers and the words around them).
_MAX_PATH = 64


def tile_address(path: str) -> tuple[int, int, int, int] | None:
    """``(result, level, col, row)`` of a tile path ``data/r{i}/{level}/{col}_{row}.bin``.

    None for anything else: a longer path, a number with a sign, a leading zero, more than six
    digits or a digit that is not ASCII (the length and the pattern are checked before any
    ``int()``, so no request can make it convert a long number).
    """
    match = _TILE_PATH.fullmatch(path) if len(path) <= _MAX_PATH else None
    if match is None:
        return None
    index, level, col, row = (int(g) for g in match.groups())
    return index, level, col, row


def mesh_address(path: str) -> int | None:
    """The result index of a mesh path ``data/r{i}/mesh.bin``, or None (as :func:`tile_address`)."""
    match = _MESH_PATH.fullmatch(path) if len(path) <= _MAX_PATH else None
    return None if match is None else int(match.group(1))


class Pyramid:
    """Levels of float16 (H_k, W_k, C) planes, each cut into :data:`TILE` x :data:`TILE` tiles of
    ``ceil(C / 4)`` RGBA16F planes: a result's layers (C = 8, :func:`pyramid`), its colour layers
    and its appearance coefficients (:mod:`ps_lab.view.appearance_tiles`)."""

    def __init__(self, levels: list[np.ndarray]) -> None:
        self.levels = levels

    @property
    def planes(self) -> int:
        """RGBA planes per tile."""
        return -(-self.levels[0].shape[2] // 4)

    def level_sizes(self) -> list[dict[str, int]]:
        """Per level: ``width``, ``height``, ``cols``, ``rows`` (tiles)."""
        sizes = []
        for level in self.levels:
            h, w = level.shape[:2]
            sizes.append({"width": w, "height": h, "cols": -(-w // TILE), "rows": -(-h // TILE)})
        return sizes

    def tile(self, level: int, col: int, row: int) -> bytes | None:
        """One tile's bytes, or None when it does not exist: its ``planes`` RGBA16F planes of
        ``w × h`` one after the other (channels ``4p .. 4p + 3`` in plane ``p``, zero-padded)."""
        if not 0 <= level < len(self.levels):
            return None
        data = self.levels[level]
        h, w = data.shape[:2]
        if not (0 <= col and col * TILE < w and 0 <= row and row * TILE < h):
            return None
        block = data[row * TILE : (row + 1) * TILE, col * TILE : (col + 1) * TILE]
        padded = np.zeros((*block.shape[:2], 4 * self.planes), np.float16)
        padded[..., : block.shape[2]] = block
        planes = [padded[..., 4 * p : 4 * p + 4].ravel() for p in range(self.planes)]
        return np.concatenate(planes).astype("<f2").tobytes()

    def tiles(self) -> Iterator[tuple[int, int, int]]:
        """Every ``(level, col, row)``."""
        for level, size in enumerate(self.level_sizes()):
            for row in range(size["rows"]):
                for col in range(size["cols"]):
                    yield level, col, row


def pyramid(result: ViewResult) -> Pyramid:
    """Build the tiled pyramid of a result's layers (see the module docstring)."""
    layers = result.layers.astype(np.float32)
    for channel in (CHANNELS.index("error_deg"), CHANNELS.index("relief")):
        layers[..., channel] = np.where(
            np.isfinite(layers[..., channel]), layers[..., channel], MISSING
        )
    levels = [half_float(layers)]
    current = layers
    while max(current.shape[:2]) > TILE:
        current = _halve(current)
        levels.append(half_float(current))
    return Pyramid(levels)


def half_float(values: np.ndarray) -> np.ndarray:
    """``values`` as float16, clipped to its finite range."""
    top = float(np.finfo(np.float16).max)
    return np.clip(values, -top, top).astype(np.float16)


def block_sum(x: np.ndarray) -> np.ndarray:
    """Sums over the 2 x 2 blocks of an array with even height and width (first two axes)."""
    return x[0::2, 0::2] + x[1::2, 0::2] + x[0::2, 1::2] + x[1::2, 1::2]


def pad_even(values: np.ndarray) -> np.ndarray:
    """``values`` (H, W, ...) zero-padded to an even height and width (itself when they are)."""
    h, w = values.shape[:2]
    if not (h % 2 or w % 2):
        return values
    padded = np.zeros((h + h % 2, w + w % 2, *values.shape[2:]), np.float32)
    padded[:h, :w] = values
    return padded


def _halve(layers: np.ndarray) -> np.ndarray:
    """One pyramid step: 2 x 2 blocks averaged over their mask pixels (valid values only)."""
    layers = pad_even(layers)
    c = layers.shape[2]
    n = layers[..., :3]
    inside = np.einsum("...k,...k->...", n, n) > 0.25
    count = block_sum(inside.astype(np.float32))
    keep = count >= 2  # a block is inside when at least half its pixels are
    out = np.empty((layers.shape[0] // 2, layers.shape[1] // 2, c), np.float32)
    # Normals, albedo and outlier share are zero outside the mask: a plain sum over it.
    out[..., :5] = block_sum(layers[..., :5]) / np.maximum(count, 1)[..., None]
    # Error and relief may be missing (MISSING), depth NaN: averaged over the valid ones.
    for k in range(5, c):
        values = layers[..., k]
        valid = inside & (np.isfinite(values) if k == 7 else values != MISSING)
        kept = block_sum(valid.astype(np.float32))
        summed = block_sum(np.where(valid, values, np.float32(0)))
        empty = MISSING if k < 7 else np.nan
        out[..., k] = np.where(keep & (kept > 0), summed / np.maximum(kept, 1), empty)
    normals = out[..., :3]
    norms = np.sqrt(np.einsum("...k,...k->...", normals, normals))[..., None]
    out[..., :3] = np.divide(normals, norms, out=np.zeros_like(normals), where=norms > 0)
    out[~keep, :5] = 0.0
    return out


def mesh_bytes(result: ViewResult) -> bytes | None:
    """The 3-D view's buffers: positions, normals (float32), triangles (uint32), RGBA8 colours."""
    if result.mesh is None:
        return None
    vertices, normals, colours, triangles = result.mesh
    rgba = np.full((len(colours), 4), 255, np.uint8)
    rgba[:, :3] = colours
    return b"".join(
        [
            np.ascontiguousarray(vertices, "<f4").tobytes(),
            np.ascontiguousarray(normals, "<f4").tobytes(),
            np.ascontiguousarray(triangles, "<u4").tobytes(),
            rgba.tobytes(),
        ]
    )


def _number(value: object) -> int | float | None:
    """A finite number (not a bool, an integer within a float's exact range), else None."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value if abs(value) <= 2**53 else None
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    return None


def _text(value: object) -> str | None:
    return value[:200] if isinstance(value, str) else None


def _error_summary(value: object) -> dict[str, float] | None:
    """The error summary's entries that are finite numbers; None without a finite mean.

    A result without errors has NaN there, which the page cannot show.
    """
    if not isinstance(value, dict):
        return None
    summary = {str(k): v for k, v in value.items() if _number(v) is not None}
    return summary if "mean" in summary else None


def manifest(results: list[ViewResult], pyramids: list[Pyramid]) -> bytes:
    """``data/manifest.json``: per result its size, levels, layers, metrics and mesh counts.

    The metrics come from a file: each is passed on only with the type the page reads (a
    string, a finite number, an error summary with a finite mean), else as null.
    """
    entries = []
    for result, levels in zip(results, pyramids, strict=True):
        h, w = result.shape
        mesh = None
        if result.mesh is not None:
            vertices = result.mesh[0]
            mesh = {
                "vertices": int(len(vertices)),
                "triangles": int(len(result.mesh[3])),
                "min": [float(x) for x in vertices.min(axis=0)] if len(vertices) else [0, 0, 0],
                "max": [float(x) for x in vertices.max(axis=0)] if len(vertices) else [0, 0, 0],
            }
        metrics = result.metrics if isinstance(result.metrics, dict) else {}
        depth = metrics.get("depth")
        entries.append(
            {
                "name": result.name,
                "width": w,
                "height": h,
                "tile": TILE,
                "levels": levels.level_sizes(),
                "albedo_scale": result.albedo_scale,
                "has": result.has,
                "method": _text(metrics.get("method")),
                "lights": _number(metrics.get("lights")),
                "pixels": _number(metrics.get("pixels")),
                "angular_error_deg": _error_summary(metrics.get("angular_error_deg")),
                "depth_unit": _text(depth.get("unit")) if isinstance(depth, dict) else None,
                "mesh": mesh,
            }
        )
    # Metrics come from a file: any value that JSON cannot hold (NaN, an infinity) becomes null.
    document = json_safe({"format": "ps-lab-view-1", "results": entries})
    return json.dumps(document, indent=1, allow_nan=False).encode()
