"""The package layout. Import direction is declared once, as import-linter contracts in
pyproject.toml (`make test` runs `lint-imports`); what is checked here is what a static import
graph cannot see: which modules a real `ps-lab reconstruct` run, and a real rig's capture, load."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers.capture_runs import write_tethered_rig

import ps_lab
import ps_lab.calibration
import ps_lab.capture
import ps_lab.reconstruct
from ps_lab.io.dng import write_dng

ROOT = Path(__file__).resolve().parents[1]

# Run `ps-lab reconstruct` through the console-script entry point (so the CLI's lazy command
# loading is part of what is checked), then list what got loaded.
_RECONSTRUCT_RUN = """
import json, sys
from ps_lab.cli import main
try:
    main(["reconstruct", sys.argv[1], "--method", "ls", "--out", sys.argv[2]])
except SystemExit as exc:
    assert not exc.code, exc.code
print(json.dumps(sorted(sys.modules)))
"""


def _write_lights(folder: Path, n: int) -> None:
    angles = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    lights = np.stack([0.5 * np.cos(angles), 0.5 * np.sin(angles), np.ones(n)], axis=1)
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    np.savetxt(folder / "light_directions.txt", lights)


def _png_dataset(folder: Path, n: int = 4) -> Path:
    folder.mkdir()
    rng = np.random.default_rng(1)
    for i in range(n):
        cv2.imwrite(str(folder / f"{i + 1:03d}.png"), rng.integers(0, 65535, (24, 32), np.uint16))
    _write_lights(folder, n)
    return folder


def _dng_dataset(folder: Path, n: int = 4) -> Path:
    folder.mkdir()
    rng = np.random.default_rng(2)
    for i in range(n):
        mosaic = rng.integers(512, 16000, (64, 64)).astype(np.uint16)
        write_dng(folder / f"{i + 1:03d}.dng", mosaic, black_level=512, white_level=16383)
    _write_lights(folder, n)
    return folder


@pytest.mark.parametrize("make", [_png_dataset, _dng_dataset], ids=["png", "dng"])
def test_reading_a_dataset_for_reconstruct_loads_no_capture_code(make, tmp_path):
    folder = make(tmp_path / "data")
    out = subprocess.run(
        [sys.executable, "-c", _RECONSTRUCT_RUN, str(folder), str(tmp_path / "out")],
        capture_output=True,
        text=True,
        check=True,
    )
    loaded = set(json.loads(out.stdout.splitlines()[-1]))
    assert {"ps_lab.io.dataset", "ps_lab.reconstruct.pipeline"} <= loaded
    assert (tmp_path / "out" / "normals.npy").is_file()
    forbidden = {
        m
        for m in loaded
        if m == "serial"
        or m.startswith(("serial.", "ps_lab.capture", "ps_lab.render", "ps_lab.calibration"))
    }
    assert not forbidden, sorted(forbidden)


# A real rig's capture: a serial controller (the in-process pslabsim:// URL) and a folder camera
# whose operator "presses the shutter" by dropping a DNG into the watched folder.
_REAL_CAPTURE_RUN = """
import json, sys
from pathlib import Path
import numpy as np
from ps_lab.capture.rig import load_rig
from ps_lab.capture.session import CaptureSession
from ps_lab.io.dng import write_dng
tether, rig_path, run = map(Path, sys.argv[1:4])
rng = np.random.default_rng(5)
shots = []
def operator(message):
    shots.append(message)
    hidden = tether / f".shot{len(shots)}.dng"
    write_dng(hidden, rng.integers(600, 4000, (32, 48)).astype(np.uint16), black_level=512,
              white_level=16383, exposure_s=0.01)
    hidden.rename(tether / f"IMG_{len(shots):04d}.dng")
result = CaptureSession(load_rig(rig_path), run, prompt=operator).run()
assert result.frames_captured == 3, result
print(json.dumps(sorted(sys.modules)))
"""


def test_a_real_rig_capture_loads_no_renderer_and_writes_no_truth(tmp_path):
    tether = tmp_path / "tether"
    tether.mkdir()
    rig_path = write_tethered_rig(tmp_path / "real.toml", tether, 2, "layout-test")
    run = tmp_path / "run"
    out = subprocess.run(
        [sys.executable, "-c", _REAL_CAPTURE_RUN, str(tether), str(rig_path), str(run)],
        capture_output=True,
        text=True,
        check=True,
    )
    loaded = set(json.loads(out.stdout.splitlines()[-1]))
    assert {"ps_lab.capture.session", "ps_lab.capture.camera_devices"} <= loaded
    forbidden = {
        m
        for m in loaded
        if m == "numba"
        or m.startswith(("numba.", "ps_lab.render", "ps_lab.capture.simulated.simulated_camera",
                         "ps_lab.capture.simulated.simulation"))
    }
    assert not forbidden, sorted(forbidden)
    assert (run / "manifest.json").is_file() and not (run / "simulation").exists()


def test_sub_packages_live_in_the_top_level_folders() -> None:
    assert Path(ps_lab.__file__).parent == ROOT / "ps_lab"
    for package, folder in (
        (ps_lab.capture, "capture"),
        (ps_lab.calibration, "calibration"),
        (ps_lab.reconstruct, "reconstruct"),
    ):
        # through the link ps_lab/<folder> (for lint-imports) or the package-dir mapping: the
        # files are the top-level folder's
        assert Path(package.__file__).resolve().parent == (ROOT / folder).resolve()
        assert set(package.__all__) <= set(dir(package))


# Modules are split by concept, not by length: a module holds one concept however long it is,
# and two concepts are two modules however short. This generous bound only catches a module
# that has grown into several concepts; it is not a size to split at.
MAX_MODULE_LINES = 1200


def test_no_module_is_over_the_generous_bound() -> None:
    """A module a reader can hold: far above any one concept's size (see above)."""
    folders = ("ps_lab", "capture", "calibration", "reconstruct")
    modules = {p.resolve() for folder in folders for p in (ROOT / folder).rglob("*.py")}
    assert len(modules) > 50
    long = {
        str(p.relative_to(ROOT)): n
        for p in sorted(modules)
        if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES
    }
    assert long == {}


def test_no_test_module_imports_another() -> None:
    """What tests share lives in tests/helpers/ (one module per concept) or tests/conftest.py."""
    import ast

    tests = ROOT / "tests"
    test_modules = {p.stem for p in tests.glob("test_*.py")}
    assert len(test_modules) > 40
    imports: dict[str, list[str]] = {}
    for path in sorted([*tests.glob("*.py"), *(tests / "helpers").glob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            else:
                continue
            found = [n for n in names if n.removeprefix("tests.").split(".")[0] in test_modules]
            if found:
                imports.setdefault(str(path.relative_to(ROOT)), []).extend(found)
    assert imports == {}
