"""``ps-lab view`` against hostile input (issue 34): damaged result files and hostile clients.

Damaged results: each case damages one file of a small result folder (written here with numpy,
24 x 24) and runs the real command in a subprocess, served and with ``--export``. The promise
(README, "Failure behaviour"): exit 2, exactly one ``error:`` line on stderr naming the file,
nothing on stdout, no traceback, no line of a C library (libpng), nothing created or changed.
Cases that must load (NaN in metrics.json, infinite normals) are checked in-process, with
numpy warnings as errors (pytest's ``filterwarnings = error``).

Hostile clients: one ``ps-lab view`` server (a subprocess) answers a table of raw requests
(foreign Host headers, foreign Origins, other methods, numbers of 5,000 digits, huge lines,
garbage), then 200 concurrent clients of which some reset and some stall; every good client
must get its whole answer and the server's stderr, after Ctrl-C, must be its one line. Stalled
and slow clients are timed out by an in-process server with a short timeout.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from helpers.bad_input import CaseTable
from typer.testing import CliRunner

from ps_lab.cli import app
from ps_lab.view import ViewSite, load_result
from ps_lab.view.site import REQUEST_TIMEOUT, ViewServer
from ps_lab.view.tiles import mesh_address, tile_address
from tests.helpers.browser import default_sigint

SIZE = 24
runner = CliRunner()
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


# ---- a small result folder -------------------------------------------------------------------


def png_bytes(picture: np.ndarray) -> bytes:
    """An 8-bit grey PNG, written by hand (one IDAT, filter 0)."""
    h, w = picture.shape
    rows = b"".join(b"\0" + picture[y].astype(np.uint8).tobytes() for y in range(h))

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = struct.pack(">I", zlib.crc32(kind + data))
        return struct.pack(">I", len(data)) + kind + data + crc

    header = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows))
        + chunk(b"IEND", b"")
    )


def ply_text(vertices, faces, extra_vertex: str = "", colours: str = "uchar") -> str:
    """An ASCII PLY: ``x y z red green blue`` vertices, ``vertex_indices`` faces as given."""
    lines = [
        "ply",
        "format ascii 1.0",
        f"element vertex {len(vertices)}",
        "property float x",
        "property float y",
        "property float z",
        f"property {colours} red",
        f"property {colours} green",
        f"property {colours} blue",
        f"element face {len(faces)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    for v in vertices:
        lines.append(" ".join(str(x) for x in v) + extra_vertex)
    for f in faces:
        lines.append(" ".join(str(x) for x in (len(f), *f)))
    return "\n".join(lines) + "\n"


def grid_mesh(n: int = 4) -> tuple[list, list]:
    vertices = [(x, -y, 0.1 * x, 100, 150, 200) for y in range(n) for x in range(n)]
    faces = []
    for y in range(n - 1):
        for x in range(n - 1):
            a, b, c, d = y * n + x, (y + 1) * n + x, y * n + x + 1, (y + 1) * n + x + 1
            faces += [(a, b, c), (c, b, d)]
    return vertices, faces


def write_result(root: Path, size: int = SIZE) -> Path:
    """A result: a hemisphere's normals, albedo, depth, relief, outliers, mesh, metrics."""
    root.mkdir(parents=True)
    ys, xs = (np.mgrid[0:size, 0:size] + 0.5) / size * 2 - 1
    inside = xs**2 + ys**2 < 0.8
    z = np.sqrt(np.clip(1 - xs**2 - ys**2, 0, 1))
    normals = np.where(inside[..., None], np.stack([xs, -ys, z], -1), 0).astype(np.float32)
    normals /= np.maximum(np.linalg.norm(normals, axis=2, keepdims=True), 1e-12)
    np.save(root / "normals.npy", normals)
    np.save(root / "albedo.npy", np.where(inside, 0.7, 0).astype(np.float32))
    np.save(root / "depth.npy", np.where(inside, z, np.nan).astype(np.float32))
    (root / "depth.png").write_bytes(png_bytes((inside * 180).astype(np.uint8)))
    (root / "corruption.png").write_bytes(png_bytes(np.zeros((size, size), np.uint8)))
    (root / "mesh.ply").write_text(ply_text(*grid_mesh()))
    metrics = {"method": "ls", "lights": 12, "angular_error_deg": {"mean": 1.5}}
    (root / "metrics.json").write_text(json.dumps(metrics))
    return root


@pytest.fixture(scope="module")
def good_result(tmp_path_factory) -> Path:
    return write_result(tmp_path_factory.mktemp("hostile-view") / "result")


# ---- running the command ---------------------------------------------------------------------


@dataclass
class Run:
    code: int
    stdout: str
    stderr: str

    @property
    def lines(self) -> list[str]:
        return [line for line in ANSI.sub("", self.stderr).splitlines() if line.strip()]


def command(*args: str) -> list[str]:
    return [sys.executable, "-m", "ps_lab", *args]


def env() -> dict[str, str]:
    out = {k: v for k, v in os.environ.items() if k not in ("FORCE_COLOR", "PY_COLORS")}
    out.update(NO_COLOR="1", COLUMNS="100", PYTHONUNBUFFERED="1")
    return out


def run(args: list[str], cwd: Path, timeout: float = 90) -> Run:
    try:
        done = subprocess.run(
            command(*args),
            cwd=cwd,
            capture_output=True,
            text=True,
            errors="replace",
            stdin=subprocess.DEVNULL,
            env=env(),
            timeout=timeout,
        )
    except subprocess.TimeoutExpired as exc:  # a hang: reported by the case
        return Run(-1, str(exc.stdout or ""), f"timed out after {timeout} s")
    return Run(done.returncode, done.stdout, done.stderr)


def snapshot(folder: Path) -> dict[str, tuple]:
    """Names, kinds, sizes and mtimes under ``folder`` (links and FIFOs not followed)."""
    entries = {}
    for dirpath, dirnames, filenames in os.walk(folder, followlinks=False):
        for name in dirnames + filenames:
            st = Path(dirpath, name).lstat()
            entries[str(Path(dirpath, name).relative_to(folder))] = (
                st.st_mode,
                st.st_size,
                st.st_mtime_ns,
            )
    return entries


# ---- damaged result files: the table ----------------------------------------------------------


@dataclass
class Case:
    id: str
    damage: Callable[[Path], str]  # damages the result; returns the file the line must name


def save(name: str, array) -> Callable[[Path], str]:
    def damage(root: Path) -> str:
        np.save(root / name, array, allow_pickle=True)
        return name

    return damage


def write(name: str, data: bytes | str) -> Callable[[Path], str]:
    def damage(root: Path) -> str:
        target = root / name
        target.unlink()
        if isinstance(data, str):
            target.write_text(data)
        else:
            target.write_bytes(data)
        return name

    return damage


def fifo(name: str) -> Callable[[Path], str]:
    def damage(root: Path) -> str:
        (root / name).unlink()
        os.mkfifo(root / name)
        return name

    return damage


def folder(name: str) -> Callable[[Path], str]:
    def damage(root: Path) -> str:
        (root / name).unlink()
        (root / name).mkdir()
        return name

    return damage


def link(name: str, target: str) -> Callable[[Path], str]:
    def damage(root: Path) -> str:
        (root / name).unlink()
        (root / name).symlink_to(target)
        return name

    return damage


def truncate(name: str, keep: float) -> Callable[[Path], str]:
    def damage(root: Path) -> str:
        raw = (root / name).read_bytes()
        (root / name).write_bytes(raw[: int(len(raw) * keep)])
        return name

    return damage


def forged_npy(shape: tuple[int, ...]) -> bytes:
    header = repr({"descr": "<f4", "fortran_order": False, "shape": shape}).encode()
    header += b" " * (63 - (10 + len(header)) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header + b"\0" * 64


def mesh_with(faces=None, vertices=None, **kwargs) -> Callable[[Path], str]:
    v, f = grid_mesh()
    return write("mesh.ply", ply_text(v if vertices is None else vertices, faces or f, **kwargs))


_V, _F = grid_mesh()
_NAN_VERTEX = [("nan", 0, 0, 1, 2, 3), *_V[1:]]
_PLY_POINTS = (
    ply_text(_V, []).split("element face")[0]
    + "end_header\n"
    + ply_text(_V, []).split("end_header\n")[1]
)
_PLY_FORGED = ply_text(_V, _F).replace(f"element vertex {len(_V)}", "element vertex 999999999999")

CASES = [
    Case("albedo-1-d", save("albedo.npy", np.ones(SIZE * SIZE, np.float32))),
    Case("albedo-scalar", save("albedo.npy", np.float32(0.5))),
    Case("albedo-strings", save("albedo.npy", np.full((SIZE, SIZE), "x"))),
    Case("albedo-complex", save("albedo.npy", np.ones((SIZE, SIZE), np.complex64))),
    Case("albedo-objects", save("albedo.npy", np.full((SIZE, SIZE), None, object))),
    Case("albedo-four-channels", save("albedo.npy", np.ones((SIZE, SIZE, 4), np.float32))),
    Case("albedo-4-d", save("albedo.npy", np.ones((SIZE, SIZE, 3, 1), np.float32))),
    Case("albedo-other-size", save("albedo.npy", np.ones((SIZE, SIZE + 1), np.float32))),
    Case("albedo-device", link("albedo.npy", "/dev/zero")),
    Case("albedo-broken-link", link("albedo.npy", "nowhere.npy")),
    Case("depth-scalar", save("depth.npy", np.float32(1.0))),
    Case("depth-1-d", save("depth.npy", np.ones(SIZE, np.float32))),
    Case("depth-three-channels", save("depth.npy", np.ones((SIZE, SIZE, 3), np.float32))),
    Case("depth-records", save("depth.npy", np.zeros((SIZE, SIZE), "f4,f4"))),
    Case("depth-truncated", truncate("depth.npy", 0.5)),
    Case("depth-forged-header", write("depth.npy", forged_npy((100_000, 100_000)))),
    Case("depth-fifo", fifo("depth.npy")),
    Case("normals-2-d", save("normals.npy", np.ones((SIZE, SIZE), np.float32))),
    Case("normals-four-channels", save("normals.npy", np.ones((SIZE, SIZE, 4), np.float32))),
    Case("normals-strings", save("normals.npy", np.full((SIZE, SIZE, 3), "1"))),
    Case("normals-bytes-dtype", save("normals.npy", np.zeros((SIZE, SIZE, 3), "S4"))),
    Case("normals-empty", save("normals.npy", np.zeros((0, SIZE, 3), np.float32))),
    Case("normals-forged-header", write("normals.npy", forged_npy((90_000, 90_000, 3)))),
    Case("normals-sparse-120-gb", lambda root: _sparse_npy(root / "normals.npy")),
    Case("normals-not-npy", write("normals.npy", b"this is not numpy\n")),
    Case("normals-fifo", fifo("normals.npy")),
    Case("normals-folder", folder("normals.npy")),
    Case("mesh-mixed-polygons", mesh_with(faces=[*_F[:-1], (0, 1, 5, 4)])),
    Case("mesh-missing-vertex", mesh_with(faces=[*_F[:-1], (0, 1, 9999)])),
    Case("mesh-negative-index", mesh_with(faces=[(-1, 1, 2), *_F[1:]])),
    Case("mesh-nan-vertex", mesh_with(vertices=_NAN_VERTEX)),
    Case("mesh-forged-count", write("mesh.ply", _PLY_FORGED)),
    Case("mesh-no-faces", write("mesh.ply", _PLY_POINTS)),
    Case("mesh-not-ply", write("mesh.ply", b"\x00\x01binary garbage")),
    Case("mesh-truncated", truncate("mesh.ply", 0.6)),
    Case("mesh-fifo", fifo("mesh.ply")),
    Case("metrics-not-json", write("metrics.json", "{'method': ls")),
    Case("metrics-not-utf8", write("metrics.json", b'{"method": "\xff\xfe"}')),
    Case("metrics-nested-too-deep", write("metrics.json", "[" * 200_000 + "]" * 200_000)),
    Case("metrics-fifo", fifo("metrics.json")),
    Case("metrics-folder", folder("metrics.json")),
    Case("metrics-device", link("metrics.json", "/dev/zero")),
    Case("depth-png-truncated", truncate("depth.png", 0.7)),
    Case("depth-png-bad-crc", lambda root: write("depth.png", _flip_idat_byte(root))(root)),
    Case("depth-png-fifo", fifo("depth.png")),
    Case("depth-png-other-size", write("depth.png", png_bytes(np.zeros((SIZE, 9), np.uint8)))),
    Case("corruption-png-not-png", write("corruption.png", b"GIF89a not a png")),
]


def _sparse_npy(path: Path) -> str:
    """A normal map of 100,000 x 100,000 pixels that the file holds (sparse: no disk used)."""
    header = forged_npy((100_000, 100_000, 3))[:-64]
    with path.open("wb") as stream:
        stream.write(header)
        stream.truncate(len(header) + 100_000 * 100_000 * 3 * 4)
    return path.name


def _flip_idat_byte(root: Path) -> bytes:
    raw = bytearray((root / "depth.png").read_bytes())
    at = raw.index(b"IDAT") + 6
    raw[at] ^= 0xFF
    return bytes(raw)


def _check_refused(result: Run, before: dict, after: dict, named: Path, root: Path) -> None:
    """The README's promise: exit 2, one ``error:`` line naming the file, nothing else."""
    text = ANSI.sub("", result.stderr)
    assert "Traceback" not in text and "libpng" not in text, text
    assert result.code == 2, f"exit {result.code}: {text}"
    assert result.stdout == "", result.stdout
    assert len(result.lines) == 1, text
    line = result.lines[0]
    assert line.startswith("error:"), line
    assert str(named) in line or (named.name == "normals.npy" and str(root) in line), line
    assert "internal error" not in line, line
    assert after == before  # nothing created, changed or removed


def _damaged_copy(case: Case, good: Path, workspace: Path) -> tuple[Path, Path]:
    workspace.mkdir()
    root = workspace / "result"
    subprocess.run(["cp", "-a", str(good), str(root)], check=True)
    return root, root / case.damage(root)


@pytest.mark.parametrize("case", CASES, ids=[case.id for case in CASES])
def test_damaged_result_file(case, good_result, tmp_path):
    # In-process (fast) with --export, so that a result that loads cannot start a server.
    root, named = _damaged_copy(case, good_result, tmp_path / "case")
    before = snapshot(tmp_path)
    result = runner.invoke(app, ["view", str(root), "--export", str(tmp_path / "site")])
    run_ = Run(result.exit_code, result.stdout, result.stderr)
    _check_refused(run_, before, snapshot(tmp_path), named, root)


#: Cases run as a user runs them too (a ``ps-lab view`` process, served, with a timeout: a
#: FIFO must not hang it, libpng must not print); ``pytest -m slow`` runs every case so.
PROCESS_CASES = {
    "albedo-1-d",
    "depth-fifo",
    "mesh-mixed-polygons",
    "mesh-fifo",
    "metrics-fifo",
    "depth-png-truncated",
    "depth-png-bad-crc",
}

#: Process cases also run with ``--export``.
EXPORT_CASES = {"metrics-fifo", "depth-png-truncated", "mesh-mixed-polygons"}


@dataclass
class Outcome:
    named: Path
    root: Path
    run: Run
    before: dict
    after: dict


def _run_case(case: Case, workspace: Path, good: Path, export: bool) -> Outcome:
    root, named = _damaged_copy(case, good, workspace)
    before = snapshot(workspace)
    args = ["view", str(root)]
    args += ["--export", str(workspace / "site")] if export else ["--no-browser", "--port", "0"]
    result = run(args, workspace, timeout=60)
    return Outcome(named, root, result, before, snapshot(workspace))


@pytest.fixture(scope="module")
def outcomes(request, good_result, tmp_path_factory) -> dict[tuple[str, bool], Outcome]:
    """Every selected process case run at once, four commands at a time."""
    chosen = [
        (item.callspec.params["case"], item.callspec.params["export"])
        for item in request.session.items
        if getattr(item, "originalname", "") == "test_damaged_result_file_in_a_process"
        and Path(str(item.fspath)) == Path(__file__)
    ]
    base = tmp_path_factory.mktemp("cases")
    with ThreadPoolExecutor(max_workers=4) as pool:
        futures = {
            (case.id, export): pool.submit(
                _run_case, case, base / f"{case.id}-{int(export)}", good_result, export
            )
            for case, export in chosen
        }
        return {key: future.result() for key, future in futures.items()}


def _process_params():
    params = []
    for case in CASES:
        slow = () if case.id in PROCESS_CASES else pytest.mark.slow
        params.append(pytest.param(case, False, id=case.id, marks=slow))
        if case.id in EXPORT_CASES:
            params.append(pytest.param(case, True, id=f"{case.id}-export"))
    return params


@pytest.mark.parametrize(("case", "export"), _process_params())
def test_damaged_result_file_in_a_process(outcomes, case, export):
    outcome = outcomes[(case.id, export)]
    _check_refused(outcome.run, outcome.before, outcome.after, outcome.named, outcome.root)


def test_every_process_case_is_a_case():
    assert EXPORT_CASES <= PROCESS_CASES <= {case.id for case in CASES}


# ---- damaged but readable: loaded, and passed on as valid JSON -------------------------------


def strict_json(raw: bytes):
    def refuse(name):
        raise ValueError(f"{name} is not JSON")

    return json.loads(raw, parse_constant=refuse)


def test_non_finite_metrics_reach_the_page_as_null(good_result, tmp_path):
    root = tmp_path / "result"
    subprocess.run(["cp", "-a", str(good_result), str(root)], check=True)
    (root / "metrics.json").write_text(
        '{"method": "ls", "lights": NaN, "pixels": 1e400, "angular_error_deg": '
        '{"mean": Infinity, "median": -Infinity, "p90": 2.5}, "depth": {"unit": "px"}, '
        f'"huge": {"9" * 5000}, "list": [NaN, 1]}}'
    )
    view = load_result(root)
    assert view.metrics["lights"] is None and view.metrics["huge"] is None
    assert view.metrics["list"] == [None, 1]
    manifest = strict_json(ViewSite([view]).get("data/manifest.json")[0])
    entry = manifest["results"][0]
    assert entry["lights"] is None and entry["pixels"] is None
    assert entry["angular_error_deg"] is None  # no finite mean: the page shows none
    assert entry["depth_unit"] == "px"


@pytest.mark.parametrize(
    ("metrics", "expected"),
    [
        ('{"angular_error_deg": {"mean": 1.5, "median": NaN, "p90": 3}}', {"mean": 1.5, "p90": 3}),
        ('{"angular_error_deg": {"mean": "1.5"}}', None),
        ('{"angular_error_deg": 2.0}', None),
        ('{"angular_error_deg": [1, 2]}', None),
        ('{"angular_error_deg": {"mean": true}}', None),
    ],
)
def test_metrics_reach_the_page_with_the_types_it_reads(good_result, tmp_path, metrics, expected):
    root = tmp_path / "result"
    subprocess.run(["cp", "-a", str(good_result), str(root)], check=True)
    (root / "metrics.json").write_text(metrics)
    manifest = strict_json(ViewSite([load_result(root)]).get("data/manifest.json")[0])
    assert manifest["results"][0]["angular_error_deg"] == expected


def test_non_finite_and_scaled_values_load_as_finite_layers(good_result, tmp_path):
    # Under filterwarnings = error: no numpy overflow or invalid-value warning either.
    root = tmp_path / "result"
    subprocess.run(["cp", "-a", str(good_result), str(root)], check=True)
    normals = np.load(root / "normals.npy")
    inside = np.linalg.norm(normals, axis=2) > 0.5
    damaged = normals.astype(np.float64) * 1e200  # scaled far beyond float32
    damaged[0, 0] = [np.nan, np.inf, -np.inf]
    np.save(root / "normals.npy", damaged)
    albedo = np.where(inside, 0.7, 0.0)
    albedo[12, 12] = np.inf
    albedo[12, 13] = 1e300
    np.save(root / "albedo.npy", albedo)
    depth = np.load(root / "depth.npy").astype(np.float64)
    depth[12, 12] = np.inf
    np.save(root / "depth.npy", depth)
    view = load_result(root)
    layers = view.layers
    assert np.all(np.isfinite(layers[..., :5]))
    unit = np.linalg.norm(layers[..., :3], axis=2)[inside]
    np.testing.assert_allclose(unit, 1.0, atol=1e-6)  # float32 rounding of a unit vector
    np.testing.assert_allclose(layers[..., :3][inside], normals[inside], atol=1e-6)
    assert np.isnan(layers[12, 12, 7])
    site = ViewSite([view])
    for path in site.paths():
        assert site.get(path) is not None, path
    strict_json(site.get("data/manifest.json")[0])


def test_mesh_with_float_colours_and_no_normals_loads(good_result, tmp_path):
    root = tmp_path / "result"
    subprocess.run(["cp", "-a", str(good_result), str(root)], check=True)
    vertices = [(*v[:3], 0.5, 1.0, 0.0) for v in _V]
    (root / "mesh.ply").write_text(ply_text(vertices, _F, colours="float"))
    _, normals, colours, triangles = load_result(root).mesh
    assert colours[0].tolist() == [128, 255, 0]
    assert len(triangles) == len(_F)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)


# ---- request paths ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("path", "expected"),
    [
        ("data/r0/0/0_0.bin", (0, 0, 0, 0)),
        ("data/r12/3/45_6.bin", (12, 3, 45, 6)),
        ("data/r0/0/" + "9" * 5000 + "_0.bin", None),
        ("data/r0/0/1234567_0.bin", None),
        ("data/r0/0/00_0.bin", None),
        ("data/r0/0/-1_0.bin", None),
        ("data/r0/0/+1_0.bin", None),
        ("data/r0/0/\u0663_0.bin", None),  # an Arabic-Indic digit, which int() takes
        ("data/r0/0/0_0.bin/", None),
        ("data/r0/0/0_0.binx", None),
        ("/data/r0/0/0_0.bin", None),
    ],
)
def test_tile_paths_are_parsed_within_bounds(path, expected):
    assert tile_address(path) == expected


def test_mesh_paths_are_parsed_within_bounds():
    assert mesh_address("data/r3/mesh.bin") == 3
    assert mesh_address("data/r" + "1" * 5000 + "/mesh.bin") is None
    assert mesh_address("data/r\u0661/mesh.bin") is None


# ---- hostile clients -------------------------------------------------------------------------


class Server:
    """``ps-lab view --no-browser`` in a subprocess; its port from the first line."""

    def __init__(self, root: Path) -> None:
        self.process = subprocess.Popen(
            command("view", str(root), "--no-browser"),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
            text=True,
            env=env(),
            preexec_fn=default_sigint,  # noqa: PLW1509 - one signal call before exec
        )
        line = self.process.stdout.readline()
        match = re.search(r"http://127\.0\.0\.1:(\d+)/", line)
        if not match:
            self.process.kill()
            pytest.fail(f"no address: {line!r} {self.process.stderr.read()}")
        self.port = int(match.group(1))

    def stop(self) -> tuple[int, str, str]:
        self.process.send_signal(signal.SIGINT)
        out, err = self.process.communicate(timeout=30)
        return self.process.returncode, out, err


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    # 600 x 600: the first tile is 4 MiB, more than a socket's buffers, so that a client that
    # resets after its request makes the server's write fail.
    root = write_result(tmp_path_factory.mktemp("served") / "result", size=600)
    (root / "metrics.json").write_text('{"method": "ls", "lights": NaN, "pixels": Infinity}')
    served = Server(root)
    yield served
    code, out, err = served.stop()
    # After every hostile client: the one Ctrl-C line, no traceback, nothing after the address.
    assert code == 130, err
    assert ANSI.sub("", err).strip().splitlines() == [
        "error: interrupted (Ctrl-C); viewer stopped"
    ], err
    assert out == "", out


def exchange(port: int, request: bytes, timeout: float = 30) -> bytes:
    """Send ``request``, read until the server closes."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
        try:
            sock.sendall(request)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server may answer before it has read everything
        chunks = []
        try:
            while True:
                chunk = sock.recv(1 << 16)
                if not chunk:
                    break
                chunks.append(chunk)
        except ConnectionResetError:
            pass
    return b"".join(chunks)


def status_of(response: bytes) -> int | None:
    match = re.match(rb"HTTP/1\.[01] (\d{3}) ", response)
    return int(match.group(1)) if match else None


def get(path: str, host: str | None = "127.0.0.1:{port}", extra: str = "", version="HTTP/1.1"):
    """A GET request; ``{port}`` in it stands for the server's port (:func:`_fill`)."""

    def build(port: int) -> bytes:
        lines = [f"GET {path} {version}"]
        if host is not None:
            lines.append(f"Host: {host}")
        text = "\r\n".join(lines) + "\r\n" + extra + "\r\n"
        return text.encode("latin-1")

    return build


def request(method: str, path: str = "/", headers: str = "") -> Callable[[int], bytes]:
    def build(port: int) -> bytes:
        body = b"x" * 100_000 if "X-Pad" in headers else b""
        return (
            f"{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n{headers}"
            f"Content-Length: {len(body)}\r\n\r\n"
        ).encode("latin-1") + body

    return build


def raw(data: bytes) -> Callable[[int], bytes]:
    return lambda port: data


MANIFEST = "/data/manifest.json"
HTTP_CASES = [
    # Host: the server's own names only.
    ("host-own-address", get(MANIFEST), 200),
    ("host-localhost", get(MANIFEST, "localhost:{port}"), 200),
    ("host-ipv6-loopback", get(MANIFEST, "[::1]:{port}"), 200),
    ("host-localhost-no-port", get(MANIFEST, "localhost"), 200),
    ("host-upper-case", get(MANIFEST, "LocalHost:{port}"), 200),
    ("host-evil", get(MANIFEST, "evil.example"), 403),
    ("host-evil-with-port", get(MANIFEST, "evil.example:{port}"), 403),
    ("host-rebinding-suffix", get(MANIFEST, "127.0.0.1.evil.example:{port}"), 403),
    ("host-rebinding-prefix", get(MANIFEST, "localhost.evil.example"), 403),
    ("host-subdomain-of-localhost", get(MANIFEST, "evil.localhost:{port}"), 403),
    ("host-trailing-dot", get(MANIFEST, "localhost.:{port}"), 403),
    ("host-other-port", get(MANIFEST, "127.0.0.1:1"), 403),
    ("host-userinfo", get(MANIFEST, "me@127.0.0.1:{port}"), 403),
    ("host-empty", get(MANIFEST, ""), 403),
    ("host-decimal-ip", get(MANIFEST, "2130706433:{port}"), 403),
    ("host-missing-http-1.1", get(MANIFEST, None), 403),
    ("host-missing-http-1.0", get(MANIFEST, None, version="HTTP/1.0"), 403),
    ("host-twice", get(MANIFEST, extra="Host: evil.example\r\n"), 403),
    ("host-http-0.9", raw(b"GET /data/manifest.json\r\n\r\n"), 403),
    ("absolute-form-target", get("http://evil.example/data/manifest.json"), 400),
    # Origin and methods.
    ("get-own-origin", get(MANIFEST, extra="Origin: http://127.0.0.1:{port}\r\n"), 200),
    ("get-foreign-origin", get(MANIFEST, extra="Origin: http://evil.example\r\n"), 403),
    ("post-foreign-origin", request("POST", headers="Origin: http://evil.example\r\n"), 403),
    ("post-null-origin", request("POST", headers="Origin: null\r\n"), 403),
    ("post-no-origin", request("POST"), 405),
    ("put", request("PUT", MANIFEST), 405),
    ("delete", request("DELETE", MANIFEST), 405),
    ("options", request("OPTIONS", "*"), 405),
    ("trace", request("TRACE"), 405),
    ("unknown-method", request("BREW"), 501),
    ("lower-case-get", request("get", MANIFEST), 501),
    ("head", request("HEAD", MANIFEST), 200),
    # Paths and numbers.
    ("tile-5000-digits", get("/data/r0/0/" + "9" * 5000 + "_0.bin"), 404),
    ("tile-5000-digit-level", get("/data/r0/" + "1" * 5000 + "/0_0.bin"), 404),
    ("mesh-5000-digit-result", get("/data/r" + "7" * 5000 + "/mesh.bin"), 404),
    ("tile-leading-zeros", get("/data/r0/0/00_0.bin"), 404),
    ("tile-of-no-result", get("/data/r9/0/0_0.bin"), 404),
    ("tile-encoded-digit", get("/data/r0/0/%D9%A3_0.bin"), 404),
    ("tile", get("/data/r0/1/0_0.bin"), 200),
    ("mesh", get("/data/r0/mesh.bin"), 200),
    ("path-traversal", get("/../../../../etc/passwd"), 404),
    ("path-encoded-traversal", get("/%2e%2e/%2e%2e/etc/passwd"), 404),
    ("query-string", get(MANIFEST + "?x=" + "1" * 3000), 200),
    # Lines and headers out of bounds, and what is not HTTP.
    ("request-line-70-kb", get("/" + "a" * 70_000), 414),
    ("header-line-70-kb", get(MANIFEST, extra="X-Big: " + "b" * 70_000 + "\r\n"), 431),
    ("200-headers", get(MANIFEST, extra="".join(f"X-{i}: {i}\r\n" for i in range(200))), 431),
    ("binary-garbage", raw(bytes(range(1, 256)) * 4 + b"\r\n\r\n"), 400),
    ("bad-version", raw(b"GET / HTTP/9.9\r\nHost: localhost\r\n\r\n"), 505),
    ("header-without-colon", get(MANIFEST, extra="no colon here\r\n"), "any"),
    ("body-with-refused-post", request("POST", headers="X-Pad: 1\r\n"), 405),
]


def _fill(build: Callable[[int], bytes], port: int) -> bytes:
    return build(port).replace(b"{port}", str(port).encode())


@pytest.mark.parametrize(
    ("build", "expected"), [c[1:] for c in HTTP_CASES], ids=[c[0] for c in HTTP_CASES]
)
def test_request(server, build, expected):
    response = exchange(server.port, _fill(build, server.port))
    status = status_of(response)
    if expected == 200:
        assert status == 200, response[:300]
    elif expected == "any":
        pass  # any answer, or none: checked only by the server's silence (the fixture)
    else:
        # A refusal: never the data (the manifest names the format; every tile is over 8 kB).
        assert status != 200, response[:300]
        assert b"ps-lab-view-1" not in response and len(response) < 8192, response[:300]
        if expected is not None:
            assert status == expected, response[:300]
    if b"manifest" in _fill(build, server.port).split(b"\r\n")[0] and status == 200:
        body = response.split(b"\r\n\r\n", 1)[1]
        if body:  # HEAD has none
            manifest = strict_json(body)  # NaN in metrics.json: null here
            assert manifest["results"][0]["lights"] is None


def test_refusals_name_the_reason(server):
    response = exchange(server.port, _fill(get(MANIFEST, "evil.example"), server.port))
    assert b"Host not served here" in response
    response = exchange(server.port, _fill(request("PUT"), server.port))
    assert b"Allow: GET, HEAD" in response


def _good_client(port: int, path: str, results: list, barrier: threading.Barrier) -> None:
    barrier.wait()
    try:
        response = exchange(port, _fill(get(path), port), timeout=20)
        head, _, body = response.partition(b"\r\n\r\n")
        length = int(re.search(rb"Content-Length: (\d+)", head).group(1))
        results.append(status_of(response) == 200 and len(body) == length)
    except Exception as exc:  # noqa: BLE001 - counted as a failure
        results.append(repr(exc))


def _resetting_client(port: int, request_first: bool, barrier: threading.Barrier) -> None:
    barrier.wait()
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        if request_first:  # a 4 MiB answer the client will not take
            sock.sendall(_fill(get("/data/r0/0/0_0.bin"), port))
            sock.recv(100)
        else:
            sock.sendall(b"GET /data/manifest.json HTTP/1.1\r\nHo")
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))


def _stalling_client(port: int, sockets: list, barrier: threading.Barrier) -> None:
    barrier.wait()
    sock = socket.create_connection(("127.0.0.1", port), timeout=30)
    sock.sendall(b"GET /data/manifest.json HTTP/1.1\r\nHost: 127.0")
    sockets.append(sock)


def test_200_concurrent_clients_some_resetting_some_stalling(server):
    good, resetting, stalling = 150, 25, 25
    barrier = threading.Barrier(good + resetting + stalling)
    results: list = []
    stalled: list[socket.socket] = []
    paths = [MANIFEST, "/data/r0/1/0_0.bin", "/index.html", "/data/r0/mesh.bin"]
    threads = [
        threading.Thread(target=_good_client, args=(server.port, paths[i % 4], results, barrier))
        for i in range(good)
    ]
    threads += [
        threading.Thread(target=_resetting_client, args=(server.port, i % 2 == 0, barrier))
        for i in range(resetting)
    ]
    threads += [
        threading.Thread(target=_stalling_client, args=(server.port, stalled, barrier))
        for _ in range(stalling)
    ]
    for thread in threads:
        thread.start()
    try:
        for thread in threads:
            thread.join(timeout=120)
        assert not any(thread.is_alive() for thread in threads)
        # Every good client got its whole answer while 25 others stalled.
        assert results == [True] * good, [r for r in results if r is not True][:5]
        assert len(stalled) == stalling
        # ... and the server still answers.
        assert status_of(exchange(server.port, _fill(get(MANIFEST), server.port))) == 200
    finally:
        for sock in stalled:
            sock.close()


# ---- stalled and slow clients time out (an in-process server, short timeout) ------------------


@pytest.fixture
def quick_server(good_result):
    server = ViewServer(ViewSite([load_result(good_result)]), 0, timeout=0.5)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05})
    thread.start()
    yield server
    server.shutdown()
    thread.join(timeout=10)
    server.server_close()


def _closed_within(sock: socket.socket, seconds: float) -> bool:
    """Whether the server closes ``sock`` within ``seconds`` (reading what it sends)."""
    sock.settimeout(seconds)
    try:
        while sock.recv(4096):
            pass
    except TimeoutError:
        return False
    except ConnectionResetError:
        pass
    return True


def test_a_silent_client_is_disconnected(quick_server, capfd):
    port = quick_server.server_address[1]
    with socket.create_connection(("127.0.0.1", port)) as sock:
        assert _closed_within(sock, 20 * quick_server.RequestHandlerClass.timeout)
    assert status_of(exchange(port, _fill(get(MANIFEST), port))) == 200
    out, err = capfd.readouterr()
    assert "Traceback" not in out + err and err == ""


def test_a_client_sending_a_byte_at_a_time_is_disconnected(quick_server, capfd):
    # Each byte comes within the socket timeout (0.5 s); the request as a whole does not, and
    # the server hangs up long before the 6 s the header would take.
    port = quick_server.server_address[1]
    request = _fill(get(MANIFEST, extra="X-Pad: " + "p" * 40 + "\r\n"), port)
    sent = 0
    with socket.create_connection(("127.0.0.1", port)) as sock:
        try:
            for byte in request[:-2]:
                sock.sendall(bytes([byte]))
                sent += 1
                time.sleep(0.1)
        except (BrokenPipeError, ConnectionResetError):
            pass
    assert sent < len(request) - 2
    out, err = capfd.readouterr()
    assert "Traceback" not in out + err and err == ""


def test_the_default_timeout_is_short_enough_to_free_a_connection():
    assert 1 <= REQUEST_TIMEOUT <= 30


# --- bad input: a folder that is not a result (the table's engine: tests/helpers/bad_input.py) ----


BAD_INPUT = CaseTable()
case = BAD_INPUT.case


@case("x-view-not-a-result", lambda w: (str(w.ds), "normals.npy"))
def _(w):
    return ["view", str(w.png()), "--no-browser"]


#: The cases CI runs; ``pytest -m slow`` runs every case of the table.
BAD_INPUT_CI = {
    "x-view-not-a-result",
}
test_bad_input = BAD_INPUT.test(BAD_INPUT_CI)
