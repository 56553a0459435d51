"""``ps-lab view``: the result's layers and tiles (numpy), then the page in headless Chromium.

The browser tests start the real command (``ps-lab view --no-browser``), load its page in
Chromium over the DevTools protocol (tests/helpers/browser.py), drag the light and compare
screenshots with a numpy render of the same normals and albedo: the page shows
``srgb(clip(albedo / albedo_scale * max(n . l, 0)))`` from half-float textures, so a pixel shown
1:1 may differ from the float64 render by the half-float rounding of n and albedo
(< 2^-11 relative, under 0.2 of an 8-bit level) plus the 8-bit rounding: at most 1 level; 2 are
allowed. They skip with a message when no Chromium is installed (`.ci/run` installs Debian's).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from ps_lab.cli import app
from ps_lab.io.encoding import linear_to_srgb
from ps_lab.view import ViewSite, export_site, load_result
from ps_lab.view.result import CHANNELS, decimate_mesh, vertex_normals
from ps_lab.view.tiles import TILE, pyramid
from tests.helpers.browser import Browser, default_sigint, find_chromium

runner = CliRunner()
DILIGENT = Path(__file__).resolve().parents[2] / "shared" / "data" / "diligent-8bit"


@pytest.fixture(scope="module")
def sim_result(tmp_path_factory) -> Path:
    """A simulated relief (96 px, 24 lights) reconstructed with depth and mesh."""
    root = tmp_path_factory.mktemp("view")
    data, out = root / "relief", root / "relief-sbl"
    result = runner.invoke(
        app, ["simulate", str(data), "--scene", "relief", "--size", "96", "--lights", "24"]
    )
    assert result.exit_code == 0, result.output
    result = runner.invoke(
        app, ["reconstruct", str(data), "--method", "ls", "--depth", "poisson", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture(scope="module")
def diligent_result(tmp_path_factory) -> Path:
    """DiLiGenT cat (320 x 296, 96 lights), least squares, when the shared data is present."""
    data = DILIGENT / "cat"
    if not (data / "light_directions.txt").exists():
        pytest.skip(f"DiLiGenT data not found at {DILIGENT}")
    out = tmp_path_factory.mktemp("view-diligent") / "cat-ls"
    result = runner.invoke(app, ["reconstruct", str(data), "--method", "ls", "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


# ---- layers and tiles --------------------------------------------------------------------------


def test_layers_hold_the_result_files(sim_result):
    view = load_result(sim_result)
    normals = np.load(sim_result / "normals.npy")
    albedo = np.load(sim_result / "albedo.npy")
    mask = np.linalg.norm(normals, axis=2) > 0.5
    assert view.layers.shape == (*normals.shape[:2], len(CHANNELS))
    np.testing.assert_array_equal(view.layers[..., :3], normals)
    np.testing.assert_allclose(view.layers[..., 3][mask] * view.albedo_scale, albedo[mask], 1e-6)
    assert view.has == {"outliers": True, "error": True, "depth": True, "mesh": True}
    # The error layer reproduces metrics.json's mean from the ground truth. metrics.json comes
    # from the solver's float64 normals, the layer from the float32 file: a dot product off by
    # d = 3 x 6e-8 reads, through arccos near 1, as up to sqrt(2 d) = 6e-4 rad = 0.035 deg.
    error = view.layers[..., CHANNELS.index("error_deg")]
    metrics = json.loads((sim_result / "metrics.json").read_text())
    assert np.nanmean(error) == pytest.approx(metrics["angular_error_deg"]["mean"], abs=0.035)
    vertices, vertex_n, colours, triangles = view.mesh
    assert len(triangles) == metrics["depth"]["mesh"]["triangles"]
    # Unit vertex normals that face the camera on a relief seen from the front.
    np.testing.assert_allclose(np.linalg.norm(vertex_n, axis=1), 1.0, atol=1e-5)
    assert np.mean(vertex_n[:, 2] > 0) > 0.99


def test_pyramid_levels_average_and_tiles_round_trip():
    # A 1100 x 700 plane of constant normal, albedo ramp: every level keeps the normal, and a tile
    # decoded from its bytes is the level's float16 values.
    from ps_lab.view.result import ViewResult

    h, w = 700, 1100
    n = np.array([0.3, -0.2, 0.9327379])
    layers = np.zeros((h, w, 8), np.float32)
    layers[..., :3] = n
    layers[..., 3] = np.linspace(0, 1, w)[None, :]
    layers[..., 5:8] = np.nan
    levels = pyramid(ViewResult(Path("."), "plane", layers, 1.0, {}))
    sizes = levels.level_sizes()
    assert [(s["width"], s["height"]) for s in sizes] == [(1100, 700), (550, 350), (275, 175)]
    assert sizes[0]["cols"] == 3 and sizes[0]["rows"] == 2 and sizes[2]["cols"] == 1
    ramp = layers[0, :, 3].astype(np.float64)
    np.testing.assert_allclose(levels.levels[1][0, :, 3], (ramp[0::2] + ramp[1::2]) / 2, atol=1e-3)
    for level in levels.levels:
        plane = np.broadcast_to(n, (*level.shape[:2], 3))
        np.testing.assert_allclose(level[..., :3].astype(float), plane, atol=1e-3)
    data = np.frombuffer(levels.tile(0, 2, 1), "<f2")
    tile_h, tile_w = h - TILE, w - 2 * TILE
    planes = data.reshape(2, tile_h, tile_w, 4)
    np.testing.assert_array_equal(planes[0], levels.levels[0][TILE:, 2 * TILE :, :4])
    assert np.all(planes[1][..., 1] == -1)  # no ground truth: the error channel says "missing"
    assert levels.tile(0, 3, 0) is None and levels.tile(3, 0, 0) is None


def test_appearance_tiles_follow_the_layer_pyramid_and_rbf_is_tiled():
    # hsh3 coefficients on a 1100 x 700 plane: the same levels as the layers, a tile's planes
    # are the level's coefficients term-major (3k + c) over the albedo scale; rbf is not tiled.
    from ps_lab.appearance.models import Appearance
    from ps_lab.view.appearance_tiles import appearance_entry, appearance_tiles

    h, w = 700, 1100
    mask = np.ones((h, w), bool)
    rng = np.random.default_rng(3)
    coefficients = rng.uniform(-1, 1, size=(h, w, 3, 9)).astype(np.float32)
    tiles = appearance_tiles(Appearance("hsh3", coefficients, {"K": 9}), mask, 2.0)
    assert [level.shape[:2] for level in tiles.levels] == [(700, 1100), (350, 550), (175, 275)]
    assert tiles.planes == 7  # 27 coefficients, four to a plane
    data = np.frombuffer(tiles.tile(0, 2, 1), "<f2").reshape(7, h - TILE, w - 2 * TILE, 4)
    flat = data.transpose(1, 2, 0, 3).reshape(h - TILE, w - 2 * TILE, 28)[..., :27]
    expected = coefficients[TILE:, 2 * TILE :].transpose(0, 1, 3, 2).reshape(*flat.shape[:2], 27)
    np.testing.assert_array_equal(flat, (expected / 2.0).astype(np.float16))
    block = coefficients[:2, :2].mean(axis=(0, 1)).T.reshape(27) / 2.0
    np.testing.assert_allclose(tiles.levels[1][0, 0].astype(float), block, atol=2e-3)
    assert tiles.tile(0, 3, 0) is None and tiles.tile(3, 0, 0) is None
    # rbf: per-channel coefficients tiled 3k + c; channels sharing them (RelightLab's mrgb read
    # back) tiled k; the manifest carries the lights, sigma and the basis repeated to 3 channels
    lights = rng.normal(size=(5, 3))
    basis = rng.uniform(size=(1, 5, 4))
    rbf = Appearance("rbf", coefficients[..., :4], {"K": 4, "sigma": 0.5},
                     {"lights": lights, "basis": basis})
    tiles = appearance_tiles(rbf, mask, 1.0)
    assert tiles.planes == 3 and tiles.levels[0].shape[2] == 12
    entry = appearance_entry(rbf, tiles)
    assert entry["shared"] is False and entry["note"] is None
    np.testing.assert_allclose(np.reshape(entry["rbf"]["basis"], (3, 5, 4)),
                               np.repeat(basis, 3, axis=0))
    shared = Appearance("rbf", np.repeat(coefficients[..., :1, :4], 3, axis=2), rbf.meta,
                        rbf.extra)
    tiles = appearance_tiles(shared, mask, 2.0)
    assert tiles.planes == 1 and appearance_entry(shared, tiles)["shared"] is True
    np.testing.assert_array_equal(tiles.levels[0][TILE:, 2 * TILE:],
                                  (coefficients[TILE:, 2 * TILE:, 0, :4] / 2.0).astype(np.float16))
    # a model the page cannot relight (more terms than its uniforms) is Lambertian, with a note
    wide = Appearance("rbf", rng.uniform(size=(h, w, 1, 40)).astype(np.float32),
                      {"K": 40, "sigma": 0.5}, {"lights": lights, "basis": basis})
    assert appearance_tiles(wide, mask, 1.0) is None
    entry = appearance_entry(wide, None)
    assert entry["planes"] is None and "Lambertian" in entry["note"]
    # gp and bln are tiled as rbf is, their entries carry the solve matrix / the grid resolution
    solve = rng.normal(size=(11, 5))
    gp = Appearance("gp", rbf.coefficients, {"K": 4, "sigma": 0.5, "ridge": 0.01},
                    {**rbf.extra, "solve": solve})
    entry = appearance_entry(gp, appearance_tiles(gp, mask, 1.0))
    assert entry["planes"] == 3 and entry["note"] is None
    np.testing.assert_array_equal(np.reshape(entry["rbf"]["solve"], (11, 5)), solve)
    bln = Appearance("bln", rbf.coefficients, {"K": 4, "sigma": 0.2, "resolution": 8}, rbf.extra)
    entry = appearance_entry(bln, appearance_tiles(bln, mask, 1.0))
    assert entry["rbf"]["resolution"] == 8 and entry["space"] == "linear" and entry["gain"] == 1
    # an sRGB-space fit: coefficients not scaled (the page decodes, then multiplies by the gain)
    ptm = Appearance("ptm", coefficients[..., :6], {"K": 6, "space": "srgb"})
    tiles = appearance_tiles(ptm, mask, 4.0)
    entry = appearance_entry(ptm, tiles)
    assert entry["space"] == "srgb" and entry["gain"] == 0.25
    np.testing.assert_array_equal(tiles.levels[0][..., :3],
                                  coefficients[..., :, 0].astype(np.float16))


def test_vertex_normals_of_a_tilted_plane_and_decimation():
    ys, xs = np.mgrid[0:60, 0:60].astype(np.float64)
    z = 0.5 * xs - 0.25 * ys
    vertices = np.stack([xs.ravel(), -ys.ravel(), z.ravel()], axis=1)
    index = np.arange(3600).reshape(60, 60)
    a, b, c, d = index[:-1, :-1], index[1:, :-1], index[:-1, 1:], index[1:, 1:]
    triangles = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([c, b, d], -1).reshape(-1, 3)]
    )
    expected = np.array([-0.5, -0.25, 1.0]) / np.linalg.norm([-0.5, -0.25, 1.0])
    normals = vertex_normals(vertices, triangles)
    np.testing.assert_allclose(normals, np.broadcast_to(expected, normals.shape), atol=1e-6)
    colours = np.full((3600, 3), 100, np.uint8)
    v2, c2, t2 = decimate_mesh(vertices, colours, triangles, 2000)
    assert 500 < len(t2) <= 2000
    kept = vertex_normals(v2, t2)[np.unique(t2)]
    # Merged positions are float32 (about 4e-6 px at 60 px): 1e-5 on the normals of small faces.
    np.testing.assert_allclose(kept, np.broadcast_to(expected, kept.shape), atol=1e-5)


def test_export_writes_every_path_and_refuses_a_foreign_folder(sim_result, tmp_path):
    site = ViewSite([load_result(sim_result)])
    out = tmp_path / "site"
    export_site(site, out)
    written = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert written == sorted(site.paths())
    assert "data/r0/mesh.bin" in written
    # Written again over itself: replaced; over a folder that is not an export: refused.
    export_site(site, out)
    foreign = tmp_path / "notes"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("mine")
    result = runner.invoke(app, ["view", str(sim_result), "--export", str(foreign)])
    assert result.exit_code == 2
    assert "not a ps-lab view export" in result.output
    assert (foreign / "keep.txt").read_text() == "mine"


def test_view_refuses_a_folder_that_is_not_a_result(tmp_path):
    result = runner.invoke(app, ["view", str(tmp_path), "--no-browser"])
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [
        f"error: {tmp_path}: not a ps-lab result (no normals.npy)"
    ]


# ---- in the browser ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def browser():
    executable = find_chromium()
    if executable is None:
        pytest.skip("no Chromium installed (apt-get install chromium): browser tests skipped")
    with Browser(executable, width=1100, height=700) as b:
        yield b


class ViewServer:
    """``ps-lab view --no-browser`` in a child process; its address from the first line."""

    def __init__(self, *results: Path) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "ps_lab", "view", *map(str, results), "--no-browser"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            preexec_fn=default_sigint,  # noqa: PLW1509 - one signal call before exec
        )
        line = self.process.stdout.readline()
        match = re.search(r"http://127\.0\.0\.1:(\d+)/", line)
        assert match, line + self.process.stderr.read()
        self.url = match.group(0)

    def stop(self) -> tuple[int, str]:
        """Ctrl-C: the exit code and stderr."""
        self.process.send_signal(signal.SIGINT)
        try:
            _, err = self.process.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.communicate()
            raise
        return self.process.returncode, err


def expected_shading(result: Path, light, exposure: float = 1.0, use_albedo: bool = True):
    """The page's relight formula in float64 on float16-rounded normals and albedo, 0..255."""
    view = load_result(result)
    normals = view.layers[..., :3].astype(np.float16).astype(np.float64)
    albedo = view.layers[..., 3].astype(np.float16).astype(np.float64) if use_albedo else 1.0
    norm = np.linalg.norm(normals, axis=2)
    mask = norm > 0.5
    unit = normals / np.where(mask, norm, 1.0)[..., None]
    shade = np.maximum(unit @ np.asarray(light), 0)
    colour = np.load(result / "albedo.npy")
    if use_albedo and colour.ndim == 3:  # colour results: per channel, then the screenshot's mean
        colour = (colour / view.albedo_scale).astype(np.float16).astype(np.float64)
        linear = np.clip(shade[..., None] * colour * exposure, 0, 1)
    else:
        linear = np.clip(shade * albedo * exposure, 0, 1)
    srgb = linear_to_srgb(linear)
    srgb = srgb.mean(axis=-1) if srgb.ndim == 3 else srgb
    return srgb * 255.0, mask


def shown_pixels(browser, panel: int, shape) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Screen (row, col) of every image pixel of panel ``panel`` at 1:1, and the screenshot."""
    h, w = shape
    x0, y0 = browser.evaluate(f"psView.imageToClient({panel}, 0, 0)")
    picture = browser.screenshot()
    rows = np.floor(y0 + np.arange(h)).astype(int)
    cols = np.floor(x0 + np.arange(w)).astype(int)
    return rows, cols, picture


def shown_rgb(browser, panel: int, shape) -> np.ndarray:
    """Panel ``panel`` shown 1:1: its (h, w, 3) RGB levels (0..255, float64) on the screenshot."""
    rows, cols, picture = shown_pixels(browser, panel, shape)
    return picture[rows][:, cols].astype(np.float64)[..., :3]


def interior(mask: np.ndarray) -> np.ndarray:
    """The mask without the image's border rows and columns (half-pixel alignment there)."""
    inner = mask.copy()
    inner[[0, -1], :] = inner[:, [0, -1]] = False
    return inner


def assert_shown(browser, panel: int, expected: np.ndarray, mask: np.ndarray) -> None:
    """Panel ``panel`` shown 1:1 equals ``expected`` (0..255 grey) within 2 levels in the mask."""
    rows, cols, picture = shown_pixels(browser, panel, expected.shape)
    shown = picture[rows][:, cols].astype(np.float64).mean(axis=2)
    difference = np.abs(shown - expected)[interior(mask)]
    assert difference.max() <= 2.0, (difference.mean(), difference.max())


def assert_relit_as(browser, fit, light, view, mask: np.ndarray, label: str) -> None:
    """Panel 0 (shown 1:1) relit from ``light`` is the appearance ``fit`` of the view's normals
    as numpy evaluates it (a fit whose coefficients carry the albedo: hsh3, rbf), sRGB-encoded,
    within 2 levels in the mask; prints the levels' mean and max after ``label``."""
    from ps_lab.appearance.models import evaluate_appearance

    browser.evaluate(f"psView.setLight({json.dumps(light)})")
    settle(browser)
    linear = np.clip(evaluate_appearance(fit, np.asarray(light), view.layers[..., :3],
                                         np.zeros(view.shape)).astype(np.float64), 0, 1)
    difference = np.abs(shown_rgb(browser, 0, view.shape) - 255 * linear_to_srgb(linear))
    difference = difference[interior(mask)]
    print(f"{label} vs numpy (levels): mean", float(difference.mean()), "max",
          float(difference.max()))
    assert difference.max() <= 2.0


@contextmanager
def opened(browser, result: Path):
    """``result`` served by ``ps-lab view``, open in ``browser`` and ready: yields its entry
    (``psView.results()[0]``); the server is stopped (Ctrl-C) after."""
    server = ViewServer(result)
    try:
        browser.open(server.url)
        assert browser.evaluate("psView.ready") is True
        yield browser.evaluate("psView.results()[0]")
    finally:
        server.stop()


def lambertian(browser) -> None:
    """Relight Lambertian (results reconstructed by default carry an appearance fit)."""
    browser.evaluate("psView.ready")
    browser.evaluate("psView.set({appearance: false})")


def settle(browser) -> None:
    """Redraw, wait until the viewer is idle with a new frame drawn and that frame presented."""
    frames = browser.evaluate("psView.stats.frames")
    browser.evaluate("psView.redraw()")
    browser.wait_for(f"psView.idle() && psView.stats.frames > {frames}", timeout=20)
    # the drawn frame on screen (two animation frames: composited)
    browser.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    browser.wait_for("psView.idle()", timeout=20)
    # every tile drawn arrived (a failed fetch is retried; one that failed for good says so here
    # instead of as a picture off by the whole shading)
    assert browser.evaluate("psView.stats.tilesFailed") == 0, browser.evaluate(
        "document.getElementById('status').textContent")


def check_relight(browser, result: Path, panel: int = 0) -> dict:
    """Drag the light on the disc twice; each screenshot matches n . l; return the numbers."""
    view = load_result(result)
    shape = view.shape
    browser.evaluate(f"psView.pixelScale({panel}, 1)")
    browser.evaluate("psView.setView({cx: 0.5, cy: 0.5})")
    disc = browser.evaluate(
        "(() => { const b = document.getElementById('light').getBoundingClientRect();"
        " return [b.left + b.width / 2, b.top + b.height / 2, b.width / 2]; })()"
    )
    cx, cy, r = disc
    numbers = {}
    shots = []
    for name, (u, v) in (("left", (-0.6, 0.3)), ("right", (0.5, -0.4))):
        browser.drag((cx, cy), (cx + u * r, cy - v * r))
        settle(browser)
        light = browser.evaluate("psView.state.light")
        # The disc maps (u, v) to (u, v, sqrt(1 - u^2 - v^2)) up to the pointer's pixel.
        assert light[0] == pytest.approx(u, abs=0.03) and light[1] == pytest.approx(v, abs=0.03)
        expected, mask = expected_shading(result, light)
        rows, cols, picture = shown_pixels(browser, panel, shape)
        shown = picture[rows][:, cols].astype(np.float64).mean(axis=2)
        inner = mask.copy()
        inner[[0, -1], :] = inner[:, [0, -1]] = False
        difference = np.abs(shown - expected)[inner]
        numbers[name] = {
            "light": light,
            "pixels": int(inner.sum()),
            "mean_abs_levels": float(difference.mean()),
            "max_abs_levels": float(difference.max()),
        }
        assert difference.max() <= 2.0, numbers[name]
        shots.append((shown, expected, inner))
    # The change between the two lights is the one n . l predicts.
    (s1, e1, m), (s2, e2, _) = shots
    change = np.corrcoef((s2 - s1)[m], (e2 - e1)[m])[0, 1]
    numbers["change_correlation"] = float(change)
    assert change > 0.999
    return numbers


def test_relight_in_chromium_matches_n_dot_l_and_3d_shows_the_mesh(browser, sim_result):
    server = ViewServer(sim_result)
    try:
        browser.open(server.url)
        lambertian(browser)
        assert browser.evaluate("psView.ready") is True
        assert browser.evaluate("psView.stats.glError") == 0
        assert browser.evaluate("!!document.createElement('canvas').getContext('webgl2')")
        numbers = check_relight(browser, sim_result)
        print("relight vs numpy:", json.dumps(numbers))
        # Raking light: the disc sets the azimuth, the slider the elevation (10 degrees).
        azimuth = np.arctan2(numbers["right"]["light"][1], numbers["right"]["light"][0])
        browser.evaluate("document.getElementById('raking').click()")
        settle(browser)
        raking = browser.evaluate("psView.lightVector()")
        assert np.degrees(np.arcsin(raking[2])) == pytest.approx(10.0, abs=1e-4)
        assert np.arctan2(raking[1], raking[0]) == pytest.approx(azimuth, abs=1e-6)
        assert browser.evaluate("psView.state.useAlbedo") is False
        expected, mask = expected_shading(sim_result, raking, use_albedo=False)
        assert_shown(browser, 0, expected, mask)
        browser.evaluate("document.getElementById('raking').click()")
        # The normal-map layer: RGB = (n + 1) / 2 of the unit half-float normals.
        browser.evaluate("psView.setMode('layers'); psView.setLayer('normal')")
        settle(browser)
        normals16 = np.load(sim_result / "normals.npy").astype(np.float16).astype(np.float64)
        norm = np.linalg.norm(normals16, axis=2, keepdims=True)
        rgb = (normals16 / np.maximum(norm, 1e-9) + 1) * 0.5 * 255
        rows, cols, picture = shown_pixels(browser, 0, mask.shape)
        shown = picture[rows][:, cols].astype(np.float64)
        assert np.abs(shown - rgb)[interior(mask)].max() <= 1.0
        # Layers and the probe under the cursor.
        browser.evaluate("psView.setMode('layers'); psView.setLayer('error')")
        settle(browser)
        x, y = browser.evaluate("psView.imageToClient(0, 48, 48)")
        browser.mouse("mouseMoved", x, y)
        probe = browser.evaluate("document.getElementById('probe').textContent")
        normals = np.load(sim_result / "normals.npy")
        assert "pixel   48, 48" in probe
        assert f"{normals[48, 48, 0]:.3f}"[:-1] in probe and "error" in probe
        # 3-D: every triangle drawn, and the mesh covers the panel's centre.
        browser.evaluate("psView.setMode('mesh')")
        browser.wait_for("psView.idle() && psView.stats.meshTriangles > 0", timeout=20)
        triangles = json.loads((sim_result / "metrics.json").read_text())["depth"]["mesh"]
        assert browser.evaluate("psView.stats.meshTriangles") == triangles["triangles"]
        panel = browser.evaluate("psView.panels()[0]")
        picture = browser.screenshot()
        x0, y0 = int(panel["x"] + panel["w"] / 2), int(panel["y"] + panel["h"] / 2)
        centre = picture[y0 - 50 : y0 + 50, x0 - 50 : x0 + 50].astype(int)
        background = np.array([32, 33, 36])
        assert np.mean(np.abs(centre - background).sum(axis=2) > 30) > 0.9
        browser.evaluate("psView.setOrbit({yaw: 0.6, pitch: 0.3})")
        settle(browser)
        turned = browser.screenshot()[y0 - 50 : y0 + 50, x0 - 50 : x0 + 50].astype(int)
        assert np.abs(turned - centre).mean() > 3  # the orbit moved the view
    finally:
        code, err = server.stop()
    assert code == 130, err
    assert err.strip().splitlines() == ["error: interrupted (Ctrl-C); viewer stopped"]


def test_compare_a_diligent_result_beside_the_simulated_one(browser, sim_result, diligent_result):
    server = ViewServer(diligent_result, sim_result)
    try:
        browser.open(server.url)
        lambertian(browser)
        assert browser.evaluate("psView.ready") is True
        results = browser.evaluate("psView.results()")
        h, w = np.load(diligent_result / "normals.npy", mmap_mode="r").shape[:2]
        assert [(r["width"], r["height"]) for r in results] == [(w, h), (96, 96)]
        assert results[0]["has"]["error"] is True
        panels = browser.evaluate("psView.panels()")
        assert panels[0]["x"] + panels[0]["w"] <= panels[1]["x"]  # side by side
        numbers = check_relight(browser, diligent_result, panel=0)
        print("DiLiGenT cat relight vs numpy:", json.dumps(numbers))
        # The light is shared: the second panel shows the same light's shading.
        light = browser.evaluate("psView.state.light")
        expected, mask = expected_shading(sim_result, light)
        browser.evaluate("psView.pixelScale(1, 1)")
        settle(browser)
        assert_shown(browser, 1, expected, mask)
    finally:
        server.stop()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_export_opens_from_a_plain_static_server(browser, sim_result, tmp_path):
    out = tmp_path / "site"
    result = runner.invoke(app, ["view", str(sim_result), "--export", str(out)])
    assert result.exit_code == 0, result.output
    port = free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "http.server", str(port), "-b", "127.0.0.1", "-d", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 10
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert time.monotonic() < deadline, "http.server did not start"
                time.sleep(0.05)
        browser.open(f"http://127.0.0.1:{port}/")
        lambertian(browser)
        assert browser.evaluate("psView.ready") is True
        check_relight(browser, sim_result)
    finally:
        server.terminate()
        server.wait(timeout=10)


# ---- colour (issue 32) -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def colour_result(tmp_path_factory) -> Path:
    """A coloured relief (orange: R > G > B) written as 16-bit PNGs, least squares."""
    from ps_lab import render

    root = tmp_path_factory.mktemp("view-colour")
    data, out = root / "orange", root / "orange-ls"
    data.mkdir()
    rng = np.random.default_rng(4)
    shape = (64, 80)
    surface = render.relief_surface(shape, seed=2, albedo=(0.85, 0.45, 0.2))
    lights = render.random_light_directions(16, rng)
    images = render.render(surface, lights)
    scale = 0.9 / float(images.max())
    for i, image in enumerate(images):
        counts = np.rint(np.clip(image * scale, 0, 1) * 65535).astype(np.uint16)
        cv2.imwrite(str(data / f"{i:03d}.png"), np.ascontiguousarray(counts[..., ::-1]))
    np.savetxt(data / "light_directions.txt", lights)
    cv2.imwrite(str(data / "mask.png"), surface.mask.astype(np.uint8) * 255)
    result = runner.invoke(app, ["reconstruct", str(data), "--method", "ls", "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


def test_colour_relight_in_chromium_shows_the_albedo_colour(browser, colour_result):
    view = load_result(colour_result)
    colour = np.load(colour_result / "albedo.npy").astype(np.float64) / view.albedo_scale
    colour = colour.astype(np.float16).astype(np.float64)
    server = ViewServer(colour_result)
    try:
        browser.open(server.url)
        lambertian(browser)
        assert browser.evaluate("psView.ready") is True
        entry = browser.evaluate("psView.results()[0]")
        assert entry["colour"] is True and len(entry["captured_lights"]) == 16
        # the light disc has a dot (#8ab4f8) at each captured light's direction
        dots = browser.evaluate(
            "(() => { const c = document.getElementById('light'), g = c.getContext('2d');"
            " const w = c.width, r = w / 2 - 4;"
            " return psView.results()[0].captured_lights.map(([x, y]) =>"
            " Array.from(g.getImageData(Math.floor(w / 2 + x * r), Math.floor(w / 2 - y * r),"
            " 1, 1).data)); })()"
        )
        blue = [d for d in dots if abs(d[0] - 138) < 40 and abs(d[2] - 248) < 40 and d[3] > 128]
        assert len(blue) >= 14, dots  # (the current light's dot may cover one or two)
        browser.evaluate("psView.pixelScale(0, 1)")
        browser.evaluate("psView.setView({cx: 0.5, cy: 0.5})")
        light = [0.3, 0.2, float(np.sqrt(1 - 0.13))]
        browser.evaluate(f"psView.setLight({json.dumps(light)})")
        settle(browser)
        normals = view.layers[..., :3].astype(np.float16).astype(np.float64)
        norm = np.linalg.norm(normals, axis=2)
        mask = norm > 0.5
        shade = np.maximum((normals / np.where(mask, norm, 1)[..., None]) @ light, 0)
        linear = np.clip(shade[..., None] * colour, 0, 1)
        expected = 255 * linear_to_srgb(linear)
        shown = shown_rgb(browser, 0, view.shape)
        inner = interior(mask)
        difference = np.abs(shown - expected)[inner]
        print("colour relight vs numpy (levels, per channel): mean",
              difference.mean(axis=0).tolist(), "max", difference.max(axis=0).tolist())
        assert difference.max() <= 2.0
        # the three channels differ as the object's colour does (orange: R > G > B)
        means = shown[inner].mean(axis=0)
        assert means[0] > means[1] + 20 and means[1] > means[2] + 20, means
    finally:
        server.stop()


def _with_appearance(result: Path, folder: Path, model: str) -> Path:
    """A copy of ``result`` with an appearance fit: an HSH 3, an sRGB-space PTM, a gp or a bln
    fit of its Lambertian renders plus a gloss, or ps / rbf with seeded coefficients."""
    from ps_lab.appearance.models import PS_TERMS, Appearance, appearance_basis
    from ps_lab.appearance.store import write_appearance

    shutil.copytree(result, folder)
    normals = np.load(result / "normals.npy").astype(np.float64)
    albedo = np.load(result / "albedo.npy").astype(np.float64)
    h, w = normals.shape[:2]
    rng = np.random.default_rng(7)
    lights = np.loadtxt(json.loads((result / "metrics.json").read_text())["dataset"]
                        + "/light_directions.txt")
    shade = np.maximum(normals @ lights.T, 0)  # (H, W, n)
    gloss = 0.5 * shade ** 8
    images = albedo[..., None, :] * (shade + gloss)[..., None]  # (H, W, n, 3)
    if model in ("gp", "bln"):  # fitted (parameters and space chosen) on the glossy renders
        from ps_lab.appearance.fit import fit_appearance

        mask = np.all(np.isfinite(normals), axis=2)
        fit = fit_appearance(model, np.moveaxis(images[mask], 1, 0), lights, mask)
        write_appearance(folder, fit)
        return folder
    if model in ("gp-srgb", "bln-srgb"):  # in sRGB space, the parameters set (not chosen)
        from ps_lab.appearance.choice import Choice, smoother_setup

        model = model[:-5]
        params = {"sigma": 0.3, "ridge": 0.01} if model == "gp" else {"sigma": 0.2,
                                                                       "resolution": 8}
        mask = np.all(np.isfinite(normals), axis=2)
        obs = np.moveaxis(images[mask], 1, 0)  # (n, P, 3)
        meta, extra = smoother_setup(Choice(model, "srgb", params, 0.0), obs, lights)
        k = extra["basis"].shape[2]
        coefficients = np.zeros((h, w, 3, k))  # the orthonormal basis: x_c = B_cᵀ y_c
        coefficients[mask] = np.einsum("cnk,npc->pck", extra["basis"], linear_to_srgb(obs))
        meta = {"basis": model, "K": k, **meta}
    elif model == "hsh3":
        basis = appearance_basis("hsh3", lights)  # (n, 9)
        coefficients = np.einsum("kn,hwnc->hwck", np.linalg.pinv(basis), images)
        meta = {"basis": "hsh3", "K": 9}
    elif model == "ptm-srgb":  # PTM of the sRGB-encoded renders (evaluation decodes)
        basis = appearance_basis("ptm", lights)  # (n, 6)
        encoded = linear_to_srgb(np.nan_to_num(images))
        coefficients = np.einsum("kn,hwnc->hwck", np.linalg.pinv(basis), encoded)
        meta = {"basis": "ptm", "K": 6, "space": "srgb"}
        model = "ptm"
    elif model == "rbf":  # ps-lab's rbf: per-channel coefficients on a per-channel basis
        k = 5
        coefficients = rng.uniform(0, 0.3, size=(h, w, 3, k)) * albedo.mean()
        meta = {"basis": "rbf", "K": k, "sigma": 0.4}
        extra = {"lights": lights, "basis": rng.uniform(0, 1, size=(3, len(lights), k))}
    else:  # "ps": the default terms (with "ps-vis" a visibility); "ps-all": every kind of term
        terms = list(PS_TERMS) if model in ("ps", "ps-vis") else [
            "lambert", "lx", "ly", "lz", "ambient", "lobe:4", "lobex:16", "lobey:16", "hsh:2",
            "hsh:5",
        ]
        k = len(terms)
        coefficients = rng.uniform(0, 0.15, size=(h, w, 3, k)) * albedo.mean()
        meta = {"basis": "ps", "K": k, "terms": terms}
        if model == "ps-vis":  # V = clamp(w·[l, 1], 0, 1): a shadow edge across the object
            vis = np.zeros((h, w, 4), np.float32)
            vis[..., 0] = rng.uniform(-1.0, 2.0, (h, w))  # V from 0 to 0.85 under the light
            vis[..., 3] = 0.5
            extra = {"visibility": vis}
            meta["visibility"] = "clip-linear"
        model = "ps"
    write_appearance(folder, Appearance(model, coefficients.astype(np.float32), meta,
                                        extra if meta.get("visibility") or model in
                                        ("rbf", "gp", "bln") else {}))
    return folder


@pytest.mark.parametrize("model", ["hsh3", "ps", "ps-all", "ps-vis", "rbf", "gp", "bln",
                                   "ptm-srgb", "gp-srgb", "bln-srgb"])
def test_appearance_relight_in_chromium_matches_the_model(browser, colour_result, tmp_path, model):
    """The page's relit picture is ``evaluate_appearance`` of the half-float tiles (an sRGB-space
    fit: its coefficients unscaled, the decoded prediction divided by ``albedo_scale``), within
    2 levels (the half-float rounding of the coefficients, under 2^-11 relative, times the sRGB
    curve's slope, plus the 8-bit rounding)."""
    from ps_lab.appearance.models import Appearance, evaluate_appearance
    from ps_lab.appearance.store import read_appearance

    result = _with_appearance(colour_result, tmp_path / model, model)
    view = load_result(result)
    scale = view.albedo_scale
    fit = read_appearance(result)
    srgb = fit.meta.get("space") == "srgb"
    assert srgb == model.endswith("-srgb") or model in ("gp", "bln")  # (those: chosen)
    # the tiles hold coefficients / albedo_scale (linear fits) or as fitted (sRGB fits: the
    # decoded picture is divided)
    before, after = (1.0, scale) if srgb else (scale, 1.0)
    coefficients = (fit.coefficients / before).astype(np.float16).astype(np.float32)
    extra = {name: np.asarray(value).astype(np.float16).astype(np.float32)
             if name == "visibility" else value for name, value in fit.extra.items()}
    rounded = Appearance(fit.model, coefficients, fit.meta, extra)
    normals = view.layers[..., :3].astype(np.float16).astype(np.float64)
    norm = np.linalg.norm(normals, axis=2)
    mask = norm > 0.5
    unit = normals / np.where(mask, norm, 1)[..., None]
    albedo = (np.load(result / "albedo.npy") / scale).astype(np.float16).astype(np.float64)
    with opened(browser, result) as entry:
        assert entry["appearance"]["model"] == fit.model and entry["appearance"]["planes"]
        assert entry["appearance"]["note"] is None
        assert entry["appearance"]["space"] == ("srgb" if srgb else "linear")
        browser.evaluate("psView.pixelScale(0, 1)")
        browser.evaluate("psView.setView({cx: 0.5, cy: 0.5})")
        # two lights, the second nearer the rim (grazing on most of the object)
        first = [-0.35, 0.25, float(np.sqrt(1 - 0.35**2 - 0.25**2))]
        rim = [0.7, -0.55, float(np.sqrt(1 - 0.7**2 - 0.55**2))]
        numbers, pictures = {}, {}
        for key, light, switch in (("model", first, True), ("Lambertian", first, False),
                                   ("model at the rim", rim, True)):
            browser.evaluate(f"psView.setLight({json.dumps(light)})")
            browser.evaluate(f"psView.set({{appearance: {json.dumps(switch)}}})")
            settle(browser)
            if switch:
                linear = evaluate_appearance(rounded, np.asarray(light), unit, albedo) / after
            else:
                linear = np.maximum(unit @ light, 0)[..., None] * albedo
            linear = np.clip(linear.astype(np.float64), 0, 1)
            expected = 255 * linear_to_srgb(linear)
            shown = shown_rgb(browser, 0, view.shape)
            inner = interior(mask)
            difference = np.abs(shown - expected)[inner]
            numbers[key] = (float(difference.mean()), float(difference.max()))
            assert difference.max() <= 2.0, numbers
            pictures[key] = expected[inner]
        # the model's picture is not the Lambertian one: the switch shows a difference
        numbers["model_vs_lambertian"] = float(np.abs(pictures["model"]
                                                      - pictures["Lambertian"]).mean())
        assert numbers["model_vs_lambertian"] > 3.0, numbers
        print(f"{model} ({fit.model}, {fit.meta.get('space', 'linear')}) relight vs numpy "
              f"(mean, max levels): {numbers}")


def test_a_relightlab_export_relights_in_chromium(browser, colour_result, tmp_path):
    """ps-lab view opens RelightLab's web layout (its own export) and relights it as its fit."""
    from ps_lab.appearance.models import Appearance
    from ps_lab.appearance.relightlab import read_relightlab
    from ps_lab.view.relightlab import load_view_result

    result = _with_appearance(colour_result, tmp_path / "fit", "hsh3")
    out = tmp_path / "relightlab"
    done = runner.invoke(app, ["view", str(result), "--export", str(out), "--format", "relight"])
    assert done.exit_code == 0, done.output
    view = load_view_result(out)
    fit, _ = read_relightlab(out)
    rounded = Appearance("hsh3", (fit.coefficients / view.albedo_scale).astype(np.float16)
                         .astype(np.float32), fit.meta)
    mask = np.linalg.norm(view.layers[..., :3], axis=2) > 0.5
    with opened(browser, out) as entry:
        assert entry["appearance"]["model"] == "hsh3" and len(entry["captured_lights"]) == 16
        browser.evaluate("psView.pixelScale(0, 1)")
        browser.evaluate("psView.setView({cx: 0.5, cy: 0.5})")
        assert_relit_as(browser, rounded, [0.4, -0.2, float(np.sqrt(1 - 0.2))], view, mask,
                        "RelightLab folder relight")


def test_a_default_result_exported_for_openlime_relights_in_chromium_as_the_export(
    browser, colour_result, tmp_path
):
    """A default result (model ps) exported with --format relight (converted to RelightLab's
    rbf layout): ps-lab view of the export shows what the export relights (the numpy read of
    its planes, as OpenLIME reads them), within 2 levels."""
    from ps_lab.appearance.models import Appearance
    from ps_lab.appearance.store import read_appearance
    from ps_lab.appearance.relightlab import read_relightlab
    from ps_lab.view.relightlab import load_view_result

    assert read_appearance(colour_result).model == "ps"
    out = tmp_path / "openlime"
    done = runner.invoke(app, ["view", str(colour_result), "--export", str(out), "--format",
                               "relight"])
    assert done.exit_code == 0, done.output
    assert "rbf" in done.output and "dB PSNR" in done.output
    view = load_view_result(out)
    fit, info = read_relightlab(out)
    assert info["type"] == "rbf" and info["ps_lab"]["model"] == "ps"
    coefficients = (fit.coefficients / view.albedo_scale).astype(np.float16).astype(np.float32)
    rounded = Appearance("rbf", coefficients, fit.meta, fit.extra)
    mask = np.linalg.norm(view.layers[..., :3], axis=2) > 0.5
    with opened(browser, out) as entry:
        assert entry["appearance"]["model"] == "rbf" and entry["appearance"]["shared"] is True
        assert entry["appearance"]["note"] is None
        browser.evaluate("psView.pixelScale(0, 1)")
        browser.evaluate("psView.setView({cx: 0.5, cy: 0.5})")
        for light in ([0.4, -0.2, float(np.sqrt(1 - 0.2))], [-0.1, 0.3, float(np.sqrt(0.9))]):
            assert_relit_as(browser, rounded, light, view, mask,
                            "default result's OpenLIME export in the viewer")
