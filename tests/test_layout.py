"""The package layout and its import direction (STYLE.md): cli on top; capture and calibration
never import each other; reconstruct imports neither; simulators load only when selected."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _loaded_after_import(module: str) -> set[str]:
    code = (
        f"import json, sys; import {module}; "
        "print(json.dumps(sorted(m for m in sys.modules if m.startswith('ps_lab'))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return set(json.loads(out.stdout))


@pytest.mark.parametrize(
    ("module", "forbidden"),
    [
        ("ps_lab.reconstruct", ("ps_lab.capture", "ps_lab.calibration", "ps_lab.dataset")),
        ("ps_lab.calibration", ("ps_lab.capture", "ps_lab.reconstruct")),
        ("ps_lab.capture", ("ps_lab.calibration", "ps_lab.reconstruct", "ps_lab.capture.sim_lights",
                            "ps_lab.capture.render")),
    ],
)
def test_import_direction(module: str, forbidden: tuple[str, ...]) -> None:
    loaded = _loaded_after_import(module)
    assert module in loaded
    assert not loaded & set(forbidden), sorted(loaded & set(forbidden))


def test_sub_packages_live_in_the_top_level_folders() -> None:
    import ps_lab.calibration
    import ps_lab.capture
    import ps_lab.reconstruct

    assert Path(ps_lab.__file__).parent == ROOT / "ps_lab"
    for package, folder in (
        (ps_lab.capture, "capture"),
        (ps_lab.calibration, "calibration"),
        (ps_lab.reconstruct, "reconstruct"),
    ):
        assert Path(package.__file__).parent == ROOT / folder
        assert set(package.__all__) <= set(dir(package))
