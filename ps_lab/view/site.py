"""The viewer as files: served on 127.0.0.1 (``ps-lab view``) or written out (``--export``).

:class:`ViewSite` maps a page-relative path to its bytes: the static page (``index.html``,
``render.js``, ``viewer.js``, ``viewer.css``, shipped in ``ps_lab/view/static``) and the data of
:mod:`ps_lab.view.tiles`, built on first request. :func:`serve` answers GET requests for those
paths only, from one address on the loopback interface; :func:`export_site` writes every path
into a folder that any static web server (or ``python -m http.server``) serves as it is.
"""

from __future__ import annotations

import functools
import io
import logging
import resource
import socket
import socketserver
import threading
import time
from collections.abc import Callable, Iterator
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path

from ps_lab.errors import OutputError
from ps_lab.io.files import staged_folder
from ps_lab.view.extras import SiteExtras
from ps_lab.view.result import ViewResult
from ps_lab.view.tiles import Pyramid, manifest, mesh_address, mesh_bytes, pyramid, tile_address

__all__ = [
    "HOST",
    "STATIC_FILES",
    "ViewServer",
    "ViewSite",
    "allowed_hosts",
    "export_site",
    "refusal",
    "serve",
]

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
        address = tile_address(path)
        if address is not None:
            index, level, col, row = address
            if index >= len(self.pyramids):
                return None
            data = self.pyramids[index].tile(level, col, row)
            return None if data is None else (data, "application/octet-stream")
        index = mesh_address(path)
        if index is not None and index < len(self.results):
            data = mesh_bytes(self.results[index])
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


# ---- the server ------------------------------------------------------------------------------

#: Seconds a client has to send a request's line and headers (in all, however slowly it sends
#: them) and, separately, to take the response; a stalled client is disconnected after it.
REQUEST_TIMEOUT = 10.0

#: Connections the kernel queues while every handler is busy (the listen backlog).
LISTEN_BACKLOG = 1024

#: Connections served at once, one thread each; more wait in the backlog. Fewer when the
#: process may open few files (half its limit), so that ``accept`` never fails for want of one.
MAX_CONNECTIONS = 512


def _connection_slots() -> int:
    try:
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    except (OSError, ValueError):
        return MAX_CONNECTIONS
    if soft == resource.RLIM_INFINITY:
        return MAX_CONNECTIONS
    return max(8, min(MAX_CONNECTIONS, soft // 2))


#: Bytes sent under one timeout.
_PIECE = 1 << 20

#: The server's own host names: a request that names another host (``evil.example``, a DNS
#: rebinding page's name) is refused, whatever address it reached.
HOST_NAMES = ("127.0.0.1", "localhost", "[::1]")

#: Methods HTTP defines that change state or are not served here: 405 (others: 501).
_OTHER_METHODS = frozenset({"POST", "PUT", "DELETE", "PATCH", "OPTIONS", "TRACE", "CONNECT"})

#: Headers of every answer: no sniffing, no framing, no reading by another site's page.
_SAFETY_HEADERS = (
    ("X-Content-Type-Options", "nosniff"),
    ("X-Frame-Options", "DENY"),
    ("Content-Security-Policy", "frame-ancestors 'none'"),
    ("Cross-Origin-Resource-Policy", "same-origin"),
    ("Referrer-Policy", "no-referrer"),
)


def allowed_hosts(port: int) -> frozenset[str]:
    """``Host`` values served: each of :data:`HOST_NAMES`, with ``:port`` or without a port."""
    return frozenset([*HOST_NAMES, *(f"{name}:{port}" for name in HOST_NAMES)])


def allowed_origins(port: int) -> frozenset[str]:
    """``Origin`` values accepted: the page's own (``http://`` + an allowed host)."""
    names = [f"{name}:{port}" for name in HOST_NAMES]
    if port == 80:
        names += HOST_NAMES
    return frozenset(f"http://{name}" for name in names)


def refusal(
    method: str, target: str, hosts: list[str], origins: list[str], port: int
) -> tuple[HTTPStatus, str] | None:
    """Why a parsed request is refused (status, reason), or None when it is served.

    In order: a ``Host`` that is missing, repeated or not the server's own (403); an ``Origin``
    that is repeated or another site's (403); a method other than GET and HEAD (405 for those
    HTTP defines, 501 for the rest); a target that is not a path (400).
    """
    if len(hosts) != 1 or hosts[0].strip().lower() not in allowed_hosts(port):
        return HTTPStatus.FORBIDDEN, (
            f"Host not served here (this server answers 127.0.0.1:{port}, localhost:{port} "
            f"and [::1]:{port} only; an SSH tunnel must forward to the same port)"
        )
    if len(origins) > 1 or (origins and origins[0].strip().lower() not in allowed_origins(port)):
        return HTTPStatus.FORBIDDEN, "requests from another site's page are refused"
    if method not in ("GET", "HEAD"):
        if method in _OTHER_METHODS:
            return HTTPStatus.METHOD_NOT_ALLOWED, "this server only reads (GET, HEAD)"
        return HTTPStatus.NOT_IMPLEMENTED, "unknown method"
    if not target.startswith("/"):
        return HTTPStatus.BAD_REQUEST, "the request target must be a path"
    return None


class _DeadlineReader(io.RawIOBase):
    """A socket's input that gives up at a deadline (the request's whole header, not per byte).

    Each receive waits at most until ``deadline()``: a client that stalls, or sends one byte
    at a time, gets ``TimeoutError`` there, which ``http.server`` answers by closing.
    """

    def __init__(self, sock: socket.socket, deadline: Callable[[], float]) -> None:
        self._sock = sock
        self._deadline = deadline

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:  # noqa: D102 - io.RawIOBase's
        left = self._deadline() - time.monotonic()
        if left <= 0:
            raise TimeoutError("the request took too long")
        self._sock.settimeout(left)
        return self._sock.recv_into(buffer)


class _Handler(BaseHTTPRequestHandler):
    """GET and HEAD of the site's paths, for the server's own host names only."""

    server_version = "ps-lab-view"
    sys_version = ""
    # A request line without a version (HTTP/0.9, or garbage) is answered with a status line.
    default_request_version = "HTTP/1.0"
    site: ViewSite
    timeout: float = REQUEST_TIMEOUT

    def version_string(self) -> str:
        return self.server_version

    def setup(self) -> None:
        super().setup()
        self._deadline = time.monotonic() + self.timeout
        self.rfile.close()  # the plain socket file, replaced by one with a deadline
        self.rfile = io.BufferedReader(_DeadlineReader(self.connection, lambda: self._deadline))

    def handle(self) -> None:
        try:
            super().handle()
        except OSError as exc:  # reset, broken pipe, timeout while answering: the client's end
            log.debug("client %s: %s", self.address_string(), exc)

    def finish(self) -> None:
        try:
            super().finish()
        except OSError as exc:
            log.debug("client %s: %s", self.address_string(), exc)

    def handle_one_request(self) -> None:
        self._deadline = time.monotonic() + self.timeout
        super().handle_one_request()

    def parse_request(self) -> bool:
        if not super().parse_request():
            return False
        self.connection.settimeout(self.timeout)  # for the answer
        refused = refusal(
            self.command,
            self.path,
            self.headers.get_all("Host") or [],
            self.headers.get_all("Origin") or [],
            self.server.server_address[1],
        )
        if refused is not None:
            self._refuse(*refused)
            return False
        return True

    def _refuse(self, status: HTTPStatus, reason: str) -> None:
        self.close_connection = True
        body = f"{status.value} {status.phrase}: {reason}\n".encode()
        self.send_response(status)
        if status == HTTPStatus.METHOD_NOT_ALLOWED:
            self.send_header("Allow", "GET, HEAD")
        self.send_header("Content-Type", "text/plain; charset=utf-8")
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Connection", "close")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def end_headers(self) -> None:
        for name, value in _SAFETY_HEADERS:
            self.send_header(name, value)
        super().end_headers()

    def do_GET(self) -> None:  # noqa: N802 - the http.server hook's name
        self._answer(with_body=True)

    def do_HEAD(self) -> None:  # noqa: N802 - the http.server hook's name
        self._answer(with_body=False)

    def _answer(self, with_body: bool) -> None:
        path = self.path.split("?", 1)[0].split("#", 1)[0]
        try:
            found = self.site.get(path)
        except Exception:  # noqa: BLE001 - a bug: logged (-vv), answered 500, never printed
            log.debug("GET %r failed", path, exc_info=True)
            self.send_error(HTTPStatus.INTERNAL_SERVER_ERROR)
            return
        if found is None:
            self.send_error(HTTPStatus.NOT_FOUND)
            return
        body, kind = found
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        if with_body:
            # In pieces: the timeout bounds each piece, so a slow reader of a large mesh is
            # served while a stalled one is cut off.
            view = memoryview(body)
            for start in range(0, len(body), _PIECE):
                self.wfile.write(view[start : start + _PIECE])

    def log_message(self, format: str, *args) -> None:  # noqa: A002 - the hook's signature
        log.debug("%s " + format, self.address_string(), *args)


def _drain(sock: socket.socket, limit: int = 1 << 20, seconds: float = 1.0) -> None:
    """Read what a client sent and was not read (a refused body, the rest of a long line).

    Closing a socket with unread input sends a reset, which can destroy the answer before the
    client reads it; a bounded read first (at most ``limit`` bytes, ``seconds``) lets the
    refusal arrive. A client with nothing pending costs nothing.
    """
    sock.setblocking(False)
    try:
        if not sock.recv(1 << 16):
            return
    except BlockingIOError:
        return
    deadline = time.monotonic() + seconds
    total = 0
    while total < limit:
        left = deadline - time.monotonic()
        if left <= 0:
            return
        sock.settimeout(left)
        chunk = sock.recv(1 << 16)
        if not chunk:
            return
        total += len(chunk)


class ViewServer(ThreadingHTTPServer):
    """The viewer's HTTP server: a thread per connection, a deep backlog, silent on bad clients.

    At most :data:`MAX_CONNECTIONS` connections are served at once (more wait in the listen
    backlog of :data:`LISTEN_BACKLOG`); each has :data:`REQUEST_TIMEOUT` seconds to send its
    request. A client that resets, stalls or sends garbage ends its own connection only:
    nothing is printed (``-vv`` logs it).
    """

    daemon_threads = True
    request_queue_size = LISTEN_BACKLOG

    def __init__(self, site: ViewSite, port: int = 0, timeout: float = REQUEST_TIMEOUT) -> None:
        handler = type("Handler", (_Handler,), {"site": site, "timeout": timeout})
        self._slots = threading.BoundedSemaphore(_connection_slots())
        super().__init__((HOST, port), handler)

    @property
    def address(self) -> str:
        """``http://127.0.0.1:PORT/``."""
        return f"http://{HOST}:{self.server_address[1]}/"

    def server_bind(self) -> None:  # noqa: D102
        # HTTPServer's would look the host's name up in DNS (getfqdn), which may wait.
        socketserver.TCPServer.server_bind(self)
        self.server_name, self.server_port = HOST, self.server_address[1]

    def process_request(self, request, client_address) -> None:  # noqa: D102
        self._slots.acquire()
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request, client_address) -> None:  # noqa: D102
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()

    def shutdown_request(self, request) -> None:  # noqa: D102
        try:
            request.shutdown(socket.SHUT_WR)  # the answer is complete
            _drain(request)
        except OSError:
            pass
        self.close_request(request)

    def handle_error(self, request, client_address) -> None:
        """A failed connection is the client's business: logged (``-vv``), never printed."""
        log.debug("connection from %s failed", client_address, exc_info=True)


def serve(
    site: ViewSite,
    port: int = 0,
    on_ready: Callable[[str], None] | None = None,
    timeout: float = REQUEST_TIMEOUT,
) -> None:
    """Serve ``site`` on ``http://127.0.0.1:PORT/`` until interrupted (Ctrl-C, SIGTERM).

    Only the server's own host names are answered (:func:`refusal`); see :class:`ViewServer`.

    Parameters
    ----------
    site : ViewSite
        What to serve.
    port : int
        0 picks a free port.
    on_ready : callable, optional
        Called with the address once the server listens.
    timeout : float
        Seconds a client has to send its request, and to take each answer.

    Raises
    ------
    OutputError
        The port is taken or cannot be opened.
    KeyboardInterrupt
        How serving ends; the socket is closed first.
    """
    try:
        server = ViewServer(site, port, timeout)
    except OSError as exc:
        raise OutputError(f"port {port}: cannot listen on {HOST} ({exc.strerror})") from None
    try:
        if on_ready is not None:
            on_ready(server.address)
        server.serve_forever(poll_interval=0.25)
    finally:
        server.server_close()
