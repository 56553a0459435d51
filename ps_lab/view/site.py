"""The viewer as files: served on 127.0.0.1 (``ps-lab view``) or written out (``--export``).

:class:`ViewSite` maps a page-relative path to its bytes: the static page (``index.html``,
``render.js``, ``viewer.js``, ``viewer.css``, shipped in ``ps_lab/view/static``) and the data of
:mod:`ps_lab.view.tiles`, built on first request. :func:`serve` answers GET requests for those
paths only, from one address on the loopback interface; :func:`export_site` writes every path
into a folder that any static web server (or ``python -m http.server``) serves as it is.
"""

from __future__ import annotations

import functools
import json
import logging
import re
from collections.abc import Callable, Iterator
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path

import numpy as np

from ps_lab.errors import OutputError
from ps_lab.io.files import staged_folder
from ps_lab.view.appearance_tiles import AppearanceTiles, appearance_entry, appearance_tiles
from ps_lab.view.relightlab import result_appearance, result_lights
from ps_lab.view.result import ViewResult, colour_layers
from ps_lab.view.tiles import Pyramid, manifest, mesh_bytes, pyramid

__all__ = ["HOST", "STATIC_FILES", "ViewSite", "export_site", "serve"]

log = logging.getLogger(__name__)

#: The only interface the viewer listens on: labs share results by ``--export``, not by port.
HOST = "127.0.0.1"

#: The page's own files, in ``ps_lab/view/static``.
STATIC_FILES = {
    "index.html": "text/html; charset=utf-8",
    "render.js": "text/javascript; charset=utf-8",
    "viewer.js": "text/javascript; charset=utf-8",
    "viewer.css": "text/css; charset=utf-8",
}

_TILE_PATH = re.compile(r"^data/r(\d+)/(\d+)/(\d+)_(\d+)\.bin$")
_MESH_PATH = re.compile(r"^data/r(\d+)/mesh\.bin$")
_COLOUR_PATH = re.compile(r"^data/r(\d+)/c/(\d+)/(\d+)_(\d+)\.bin$")
_APPEARANCE_PATH = re.compile(r"^data/r(\d+)/a/(\d+)/(\d+)_(\d+)\.bin$")


class ViewSite:
    """Page-relative path -> bytes for a list of results."""

    def __init__(self, results: list[ViewResult]) -> None:
        self.results = results
        self.pyramids: list[Pyramid] = [pyramid(result) for result in results]
        self._manifest = manifest(results, self.pyramids)
        self.colour = _colour_pyramids(results)
        self.appearance, entries = _appearance_layers(results)
        self._manifest = _manifest_extras(self._manifest, results, self.colour, entries)

    def get(self, path: str) -> tuple[bytes, str] | None:
        """``(bytes, content type)`` of a page-relative path, or None when there is none."""
        path = path.lstrip("/") or "index.html"
        if path in STATIC_FILES:
            return _static(path), STATIC_FILES[path]
        if path == "data/manifest.json":
            return self._manifest, "application/json"
        match = _TILE_PATH.match(path)
        if match:
            index, level, col, row = (int(g) for g in match.groups())
            if index >= len(self.pyramids):
                return None
            data = self.pyramids[index].tile(level, col, row)
            return None if data is None else (data, "application/octet-stream")
        found = _colour_tile(self.colour, path) or _appearance_tile(self.appearance, path)
        if found is not None:
            return found, "application/octet-stream"
        match = _MESH_PATH.match(path)
        if match and int(match.group(1)) < len(self.results):
            data = mesh_bytes(self.results[int(match.group(1))])
            return None if data is None else (data, "application/octet-stream")
        return None

    def paths(self) -> Iterator[str]:
        """Every path the site holds."""
        yield from STATIC_FILES
        yield "data/manifest.json"
        for index, (result, levels) in enumerate(zip(self.results, self.pyramids, strict=True)):
            for level, col, row in levels.tiles():
                yield f"data/r{index}/{level}/{col}_{row}.bin"
            if result.mesh is not None:
                yield f"data/r{index}/mesh.bin"
        for index, levels in enumerate(self.colour):
            for level, col, row in levels.tiles() if levels is not None else ():
                yield f"data/r{index}/c/{level}/{col}_{row}.bin"
        for index, tiles in enumerate(self.appearance):
            for level, col, row in tiles.tiles() if tiles is not None else ():
                yield f"data/r{index}/a/{level}/{col}_{row}.bin"


# --- colour and captured lights (issue 32) ------------------------------------------------------


def _colour_pyramids(results: list[ViewResult]) -> list[Pyramid | None]:
    """Per result, the pyramid of its colour layers (:func:`colour_layers`), None when grey."""
    out: list[Pyramid | None] = []
    for result in results:
        layers = colour_layers(result)
        out.append(None if layers is None else pyramid(_ColourLayers(result, layers)))
    return out


class _ColourLayers:
    """What :func:`ps_lab.view.tiles.pyramid` reads of a result: its layers."""

    def __init__(self, result: ViewResult, layers) -> None:
        self.layers = layers
        self.shape = result.shape


def _colour_tile(colour: list[Pyramid | None], path: str) -> bytes | None:
    match = _COLOUR_PATH.match(path)
    if not match:
        return None
    index, level, col, row = (int(g) for g in match.groups())
    if index >= len(colour) or colour[index] is None:
        return None
    return colour[index].tile(level, col, row)


def _appearance_layers(
    results: list[ViewResult],
) -> tuple[list[AppearanceTiles | None], list[dict | None]]:
    """Per result, its appearance fit's tiles (None: none, or not one the page relights) and
    manifest entry (:mod:`ps_lab.view.appearance_tiles`)."""
    tiles: list[AppearanceTiles | None] = []
    entries: list[dict | None] = []
    for result in results:
        appearance = result_appearance(result.root)
        layers = None
        if appearance is not None:
            mask = np.einsum("...k,...k->...", result.layers[..., :3], result.layers[..., :3])
            layers = appearance_tiles(appearance, mask > 0.25, result.albedo_scale)
        tiles.append(layers)
        entries.append(appearance_entry(appearance, layers))
    return tiles, entries


def _appearance_tile(tiles: list[AppearanceTiles | None], path: str) -> bytes | None:
    match = _APPEARANCE_PATH.match(path)
    if not match:
        return None
    index, level, col, row = (int(g) for g in match.groups())
    if index >= len(tiles) or tiles[index] is None:
        return None
    return tiles[index].tile(level, col, row)


def _manifest_extras(
    data: bytes, results: list[ViewResult], colour: list, appearance: list
) -> bytes:
    """The manifest with, per result, ``colour`` (colour tiles exist), ``appearance`` (the
    fitted model's entry) and ``captured_lights``."""
    value = json.loads(data)
    for entry, result, levels, fit in zip(
        value["results"], results, colour, appearance, strict=True
    ):
        entry["colour"] = levels is not None
        entry["appearance"] = fit
        lights = result_lights(result.root)
        entry["captured_lights"] = None if lights is None else [
            [float(x) for x in row] for row in lights
        ]
    return json.dumps(value, indent=1).encode()


@functools.cache
def _static(name: str) -> bytes:
    return resources.files("ps_lab.view").joinpath("static", name).read_bytes()


def export_site(site: ViewSite, out: Path, progress: Callable[[], None] | None = None) -> int:
    """Write every file of ``site`` into the folder ``out`` (staged: complete or absent).

    Returns
    -------
    int
        Bytes written.
    """
    total = 0
    out = Path(out)
    if out.exists() and (not out.is_dir() or _foreign(out)):
        raise OutputError(
            f"{out}: not a ps-lab view export and not empty (choose a new or empty folder)"
        )
    with staged_folder(out) as staging:
        for path in site.paths():
            found = site.get(path)
            assert found is not None
            target = staging / path
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(found[0])
            total += len(found[0])
            if progress is not None:
                progress()
    return total


def _foreign(folder: Path) -> bool:
    """Whether ``folder`` holds anything but an earlier export (which may be replaced)."""
    names = {p.name for p in folder.iterdir()}
    return bool(names) and not (
        names <= {*STATIC_FILES, "data"} and (folder / "data" / "manifest.json").is_file()
    )


def _handler(site: ViewSite) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        server_version = "ps-lab-view"

        def do_GET(self) -> None:  # noqa: N802 - the http.server hook's name
            found = site.get(self.path.split("?", 1)[0])
            if found is None:
                self.send_error(HTTPStatus.NOT_FOUND)
                return
            body, kind = found
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, format: str, *args) -> None:  # noqa: A002 - the hook's signature
            log.debug("%s " + format, self.address_string(), *args)

    return Handler


def serve(
    site: ViewSite, port: int = 0, on_ready: Callable[[str], None] | None = None
) -> None:
    """Serve ``site`` on ``http://127.0.0.1:PORT/`` until interrupted (Ctrl-C, SIGTERM).

    Parameters
    ----------
    site : ViewSite
        What to serve.
    port : int
        0 picks a free port.
    on_ready : callable, optional
        Called with the address once the server listens.

    Raises
    ------
    OutputError
        The port is taken or cannot be opened.
    KeyboardInterrupt
        How serving ends; the socket is closed first.
    """
    try:
        server = ThreadingHTTPServer((HOST, port), _handler(site))
    except OSError as exc:
        raise OutputError(f"port {port}: cannot listen on {HOST} ({exc.strerror})") from None
    server.daemon_threads = True
    address = f"http://{HOST}:{server.server_address[1]}/"
    try:
        if on_ready is not None:
            on_ready(address)
        server.serve_forever(poll_interval=0.25)
    finally:
        server.server_close()
