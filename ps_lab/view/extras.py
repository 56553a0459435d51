"""The viewer's colour, appearance and captured-light data (issue 32), beside the layer tiles.

:class:`SiteExtras` is what :class:`ps_lab.view.site.ViewSite` adds for these: three more
things per result, each optional:

- ``data/r{i}/c/{level}/{col}_{row}.bin``: a colour result's albedo (``albedo.npy`` H×W×3) as a
  pyramid of :mod:`ps_lab.view.tiles` (channels: the normals, the albedo's R, G, B divided by
  the result's ``albedo_scale``, zeros), two RGBA16F planes per tile (:func:`colour_layers`);
- ``data/r{i}/a/{level}/{col}_{row}.bin``: its appearance fit's coefficients
  (:mod:`ps_lab.view.appearance_tiles`);
- in the manifest, per result: ``colour`` (bool), ``appearance`` (model, terms, planes, note) and
  ``captured_lights`` (the light disc's dots; :func:`ps_lab.appearance.export.result_lights`).
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator

import numpy as np

from ps_lab.appearance.export import result_lights
from ps_lab.errors import DatasetError
from ps_lab.view.appearance_tiles import AppearanceTiles, appearance_entry, appearance_tiles
from ps_lab.view.readers import present, read_array
from ps_lab.view.relightlab import result_appearance
from ps_lab.view.result import ViewResult
from ps_lab.view.tiles import Pyramid, pyramid

__all__ = ["SiteExtras", "colour_layers"]

_COLOUR_PATH = re.compile(r"^data/r(\d{1,6})/c/(\d{1,3})/(\d{1,7})_(\d{1,7})\.bin$")
_APPEARANCE_PATH = re.compile(r"^data/r(\d{1,6})/a/(\d{1,3})/(\d{1,7})_(\d{1,7})\.bin$")


def colour_layers(result: ViewResult) -> np.ndarray | None:
    """A colour result's colour layers (H, W, 8), or None for a grey one.

    Channels as :data:`ps_lab.view.result.CHANNELS` lays them out for the pyramid: the normals
    (0-2), the albedo's R, G, B divided by :attr:`ViewResult.albedo_scale` (3-5), zeros (6-7).

    Raises
    ------
    DatasetError
        ``albedo.npy`` unreadable, or of another size than the normals.
    """
    albedo_file = result.root / "albedo.npy"
    if not present(albedo_file, "albedo"):
        return None
    albedo = read_array(albedo_file, "albedo", (2, 3))  # checked before it is read
    if albedo.ndim != 3 or albedo.shape[2] != 3:
        return None
    if tuple(albedo.shape[:2]) != tuple(result.shape):
        raise DatasetError(
            f"{albedo_file}: size {albedo.shape[1]}x{albedo.shape[0]} differs from normals.npy "
            f"({result.shape[1]}x{result.shape[0]})"
        )
    normals = result.layers[..., 0:3]
    mask = np.einsum("...k,...k->...", normals, normals) > 0.25
    out = np.zeros((*result.shape, 8), np.float32)
    out[..., 0:3] = normals
    with np.errstate(all="ignore"):
        colour = np.nan_to_num(np.asarray(albedo, np.float32), posinf=0.0, neginf=0.0)
        out[..., 3:6] = np.where(mask[..., None], colour / np.float32(result.albedo_scale), 0.0)
    return out


class _Layers:
    """What :func:`ps_lab.view.tiles.pyramid` reads of a result: its layers."""

    def __init__(self, layers: np.ndarray) -> None:
        self.layers = layers
        self.shape = layers.shape[:2]


class SiteExtras:
    """Colour tiles, appearance tiles and manifest entries of a list of results."""

    def __init__(self, results: list[ViewResult]) -> None:
        self.results = results
        self.colour: list[Pyramid | None] = []
        self.appearance: list[AppearanceTiles | None] = []
        self.entries: list[dict | None] = []
        for result in results:
            layers = colour_layers(result)
            self.colour.append(None if layers is None else pyramid(_Layers(layers)))
            fit = result_appearance(result.root)
            tiles = None
            if fit is not None:
                normals = result.layers[..., :3]
                mask = np.einsum("...k,...k->...", normals, normals) > 0.25
                tiles = appearance_tiles(fit, mask, result.albedo_scale)
            self.appearance.append(tiles)
            self.entries.append(appearance_entry(fit, tiles))

    def manifest(self, data: bytes) -> bytes:
        """The manifest ``data`` with ``colour``, ``appearance`` and ``captured_lights`` added."""
        value = json.loads(data)
        for entry, result, levels, fit in zip(
            value["results"], self.results, self.colour, self.entries, strict=True
        ):
            entry["colour"] = levels is not None
            entry["appearance"] = fit
            lights = result_lights(result.root)
            entry["captured_lights"] = None if lights is None else [
                [float(x) for x in row] for row in lights
            ]
        return json.dumps(value, indent=1).encode()

    def get(self, path: str) -> bytes | None:
        """The bytes of a colour or appearance tile path, or None."""
        for pattern, tiles in ((_COLOUR_PATH, self.colour), (_APPEARANCE_PATH, self.appearance)):
            match = pattern.match(path)
            if match:
                index, level, col, row = (int(g) for g in match.groups())
                if index >= len(tiles) or tiles[index] is None:
                    return None
                return tiles[index].tile(level, col, row)
        return None

    def paths(self) -> Iterator[str]:
        """Every colour and appearance tile path."""
        for kind, sets in (("c", self.colour), ("a", self.appearance)):
            for index, tiles in enumerate(sets):
                for level, col, row in tiles.tiles() if tiles is not None else ():
                    yield f"data/r{index}/{kind}/{level}/{col}_{row}.bin"
