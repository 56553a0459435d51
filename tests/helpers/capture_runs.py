"""The tiny simulated rig the capture-session and capture CLI tests run (8 lights, 64x48), and a
real rig's file driven by simulators (a serial controller URL, a watched tether folder)."""

from __future__ import annotations

import hashlib
from pathlib import Path

N_LIGHTS = 8
N_FRAMES = N_LIGHTS + 1
TINY_RIG = """
name = "tiny"
[controller]
driver = "simulated"
lights = {lights}
watchdog_ms = 1500
timeout_s = 0.1
settle_ms = {settle_ms}

[camera]
driver = "simulated"
exposure_s = 0.05
timeout_s = 0.1
retries = {retries}
seed = 11

[calibration.chrome_sphere]
center = [16.0, 16.0]
radius = 12.0

[scene]
width = 64
height = 48

[scene.lights]
seed = 3
max_zenith_deg = 50.0
intensity_spread = 0.1

[[scene.objects]]
kind = "chrome"
center = [16.0, 16.0]
radius = 12.0

[[scene.objects]]
kind = "sphere"
center = [44.0, 26.0]
radius = 18.0
albedo = [0.7, 0.6, 0.5]
{faults}
"""


def write_rig(
    folder: Path,
    *,
    faults: str = "",
    retries: int = 1,
    settle_ms: int = 0,
    lights: int = N_LIGHTS,
    name="rig.toml",
) -> Path:
    path = folder / name
    path.write_text(
        TINY_RIG.format(faults=faults, retries=retries, settle_ms=settle_ms, lights=lights)
    )
    return path


TETHERED_RIG = """
[controller]
driver = "serial"
port = "pslabsim://{name}?lights={lights}"
lights = {lights}
timeout_s = 0.2
[camera]
driver = "folder"
folder = "{tether}"
pattern = "*.dng"
prompt = true
exposure_s = 0.01
file_type = "dng"
timeout_s = 10.0
"""


def write_tethered_rig(path: Path, tether: Path, lights: int, name: str) -> Path:
    """A real rig's file at ``path``: the serial driver on the in-process simulated board
    ``pslabsim://name`` with ``lights`` lights, and a folder camera that prompts for each frame
    and waits for a DNG in ``tether`` (what an operator's tethering software drops there)."""
    path.write_text(TETHERED_RIG.format(name=name, lights=lights, tether=tether))
    return path


def frame_hashes(run: Path) -> dict[str, str]:
    return {
        p.name: hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted((run / "frames").iterdir())
    }
