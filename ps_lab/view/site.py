"""The viewer as files: served on 127.0.0.1 (``ps-lab view``) or written out (``--export``).

:class:`ViewSite` maps a page-relative path to its bytes: the static page (``index.html``,
``render.js``, ``viewer.js``, ``viewer.css``, shipped in ``ps_lab/view/static``) and the data of
:mod:`ps_lab.view.tiles`, built on first request. :func:`serve` answers GET requests for those
paths only, from one address on the loopback interface; :func:`export_site` writes every path
into a folder that any static web server (or ``python -m http.server``) serves as it is.
"""

from __future__ import annotations

import functools
import logging
import re
from collections.abc import Callable, Iterator
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path

from ps_lab.errors import OutputError
from ps_lab.io.files import staged_folder
from ps_lab.view.extras import SiteExtras
from ps_lab.view.result import ViewResult
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


class ViewSite:
    """Page-relative path -> bytes for a list of results."""

    def __init__(self, results: list[ViewResult]) -> None:
        self.results = results
        self.pyramids: list[Pyramid] = [pyramid(result) for result in results]
        self._manifest = manifest(results, self.pyramids)
        self.extras = SiteExtras(results)  # colour, appearance, captured lights (issue 32)
        self._manifest = self.extras.manifest(self._manifest)

    def get(self, path: str) -> tuple[bytes, str] | None:
        """``(bytes, content type)`` of a page-relative path, or None when there is none."""
        path = path.lstrip("/") or "index.html"
        if path in STATIC_FILES:
            return _static(path), STATIC_FILES[path]
        extra = self.extras.get(path)
        if extra is not None:
            return extra, "application/octet-stream"
        if path == "data/manifest.json":
            return self._manifest, "application/json"
        match = _TILE_PATH.match(path)
        if match:
            index, level, col, row = (int(g) for g in match.groups())
            if index >= len(self.pyramids):
                return None
            data = self.pyramids[index].tile(level, col, row)
            return None if data is None else (data, "application/octet-stream")
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
        yield from self.extras.paths()


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
