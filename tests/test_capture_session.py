"""Capture sessions on a tiny simulated rig, through the pty path of the light controller.

Every run here opens the simulated firmware on a real pseudo-terminal and drives it with the
serial driver through the OS serial layer. Faults of the controller and the camera are injected
at seeded random points; each run completes or stops cleanly, and after ``resume`` the frame
files are byte-identical to an uninterrupted run.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
from helpers.capture_runs import N_FRAMES, N_LIGHTS, frame_hashes, write_rig, write_tethered_rig

from ps_lab.capture.rig import load_rig
from ps_lab.capture.session import CaptureSession, make_plan
from ps_lab.capture.simulated import simulated_camera as cameras
from ps_lab.capture.simulated.pty_server import PtyServer
from ps_lab.capture.simulated.simulation import build_simulation
from ps_lab.errors import CameraError, DatasetError, PsLabError, RigError
from ps_lab.io.dataset import load_frames
from ps_lab.io.dng import write_dng
from ps_lab.io.files import PARTIAL_PREFIX
from ps_lab.io.raw import load_raw
from ps_lab.io.run import MANIFEST_NAME, read_manifest
from ps_lab.render import render_scene

# Commands the controller receives in a clean session: handshake ID, WATCHDOG, LEVEL, OFF; the
# session's OFF; STATE after the dark frame; ON, STATE, OFF per light.
N_COMMANDS = 4 + 1 + 1 + 3 * N_LIGHTS


def assert_consistent(run: Path) -> dict:
    """The manifest lists only complete frames, in plan order, with matching checksums."""
    manifest = read_manifest(run)
    plan = make_plan(N_LIGHTS, manifest["plan"]["lights"], manifest["plan"]["repeat"], "dng")
    for record, planned in zip(manifest["frames"], plan.frames, strict=False):
        assert record["file"] == planned.file and record["index"] == planned.index
        data = (run / record["file"]).read_bytes()
        assert hashlib.sha256(data).hexdigest() == record["sha256"]
        load_raw(run / record["file"])
    return manifest


def wait_safe(firmware, timeout_s: float = 4.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if firmware.ended_safely():
            return True
        time.sleep(0.05)
    return firmware.ended_safely()


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """Frame hashes of an uninterrupted clean run."""
    folder = tmp_path_factory.mktemp("reference")
    rig = load_rig(write_rig(folder))
    run = folder / "run"
    result = CaptureSession(rig, run).run()
    assert result.frames_captured == N_FRAMES and result.retries == 0
    return frame_hashes(run)


def test_clean_capture_writes_every_frame_under_the_right_light(
    tmp_path: Path, reference: dict
) -> None:
    rig = load_rig(write_rig(tmp_path))
    run = tmp_path / "run"
    seen: list[tuple[int, str | None]] = []
    session = CaptureSession(rig, run)
    result = session.run(progress=lambda n=1, description=None: seen.append((n, description)))
    assert result.frames_total == N_FRAMES and result.frames_captured == N_FRAMES
    assert sum(n for n, _ in seen) == N_FRAMES
    assert any(d is not None and f"light {N_LIGHTS}/{N_LIGHTS}" in d for _, d in seen)
    # Seeded: a second run is byte-identical.
    assert frame_hashes(run) == reference
    assert session.opened is not None and session.opened.firmware.ended_safely()

    manifest = assert_consistent(run)
    assert manifest["format"] == "ps-lab-run" and manifest["version"] == 1
    assert manifest["plan"] == {"lights": list(range(1, N_LIGHTS + 1)), "repeat": 1}
    assert manifest["rig"]["calibration"]["chrome_sphere"] == {
        "center": [16.0, 16.0],
        "radius": 12.0,
    }
    kinds = [r["kind"] for r in manifest["frames"]]
    assert kinds == ["dark"] + ["light"] * N_LIGHTS
    assert [r["lights"] for r in manifest["frames"][1:]] == [[i] for i in range(1, N_LIGHTS + 1)]
    assert all(r["exposure_s"] == rig.camera.exposure_s for r in manifest["frames"])
    assert not any(p.name.startswith(PARTIAL_PREFIX) for p in run.rglob("*"))

    # Ground truth of the simulator, at the loaded resolution, lights in plan order.
    sim = build_simulation(rig)
    normals = np.load(run / "simulation" / "normal_gt.npy")
    assert normals.shape == (48, 64, 3)
    np.testing.assert_allclose(
        np.loadtxt(run / "simulation" / "light_directions_true.txt"),
        sim.light_directions,
        atol=1e-8,
    )
    np.testing.assert_allclose(
        np.loadtxt(run / "simulation" / "light_intensities_true.txt"),
        sim.light_intensities,
        atol=1e-8,
    )
    assert (run / "simulation" / "mask.png").stat().st_size > 0
    assert not (run / "light_directions_nominal.txt").exists()  # the tiny rig has none
    # The run is a dataset: the shared loader takes frames, dark frame and exposures from it.

    frames = load_frames(run)
    assert frames.images.shape == (N_LIGHTS, 48, 64, 3)
    assert frames.manifest is not None and frames.manifest["plan"]["repeat"] == 1

    # No mix-up: the dark-subtracted frame of light i looks like light i's rendering, not another's.
    dark = load_raw(run / manifest["frames"][0]["file"]).image.astype(np.float64)
    renders = [
        render_scene(sim.scene, sim.light_directions[i : i + 1], sim.light_intensities[i : i + 1])
        for i in range(N_LIGHTS)
    ]
    for record in manifest["frames"][1:]:
        image = load_raw(run / record["file"]).image.astype(np.float64) - dark
        scores = [np.corrcoef(image.ravel(), r.ravel())[0, 1] for r in renders]
        assert int(np.argmax(scores)) == record["lights"][0] - 1


def test_lights_subset_and_repeats(tmp_path: Path) -> None:
    rig = load_rig(write_rig(tmp_path))
    run = tmp_path / "run"
    CaptureSession(rig, run, lights=[2, 5], repeat=2).run()
    manifest = read_manifest(run)
    assert manifest["plan"] == {"lights": [2, 5], "repeat": 2}
    files = [r["file"] for r in manifest["frames"]]
    assert files == [
        "frames/0000-dark.dng",
        "frames/0001-L02-r0.dng",
        "frames/0002-L02-r1.dng",
        "frames/0003-L05-r0.dng",
        "frames/0004-L05-r1.dng",
    ]
    # Repeats differ only by their noise (the seed follows the frame index).
    a, b = (load_raw(run / f).image for f in files[1:3])
    assert not np.array_equal(a, b)
    assert abs(float(a.mean()) - float(b.mean())) < 0.01 * float(a.mean())
    np.testing.assert_allclose(
        np.loadtxt(run / "simulation" / "light_directions_true.txt"),
        build_simulation(rig).light_directions[[1, 4]],
        atol=1e-8,
    )


FAULTS = [
    ("controller", "drop", 1),
    ("controller", "garble", 1),
    ("controller", "delay", 1),
    ("controller", "reboot", 1),
    ("controller", "silence", 1),
    ("camera", "timeout", 1),
    ("camera", "truncated", 1),
    ("camera", "timeout", 0),
    ("camera", "truncated", 0),
]


@pytest.mark.parametrize(("device", "kind", "retries"), FAULTS)
def test_fault_at_a_random_point_then_resume_is_byte_identical(
    tmp_path: Path, reference: dict, device: str, kind: str, retries: int
) -> None:
    rng = np.random.default_rng(zlib.crc32(f"{device}-{kind}-{retries}".encode()))
    if device == "controller":
        at = int(rng.integers(1, N_COMMANDS + 1))
    else:
        at = int(rng.integers(1, N_FRAMES + 1))
    faults = f'[faults]\n{device} = [{{ kind = "{kind}", at = {at} }}]\n'
    rig = load_rig(write_rig(tmp_path, faults=faults, retries=retries, name="faulty.toml"))
    run = tmp_path / "run"
    session = CaptureSession(rig, run)
    recoverable = kind in ("drop", "garble", "delay", "reboot") or (
        device == "camera" and retries > 0
    )
    try:
        result = session.run()
        stopped = None
    except PsLabError as exc:
        stopped = exc
    assert session.opened is not None
    if recoverable:
        assert stopped is None, f"{kind}@{at} should be recovered from: {stopped}"
        assert result.frames_captured == N_FRAMES
        if device == "camera" and at <= N_FRAMES:
            assert result.retries == 1
        assert session.opened.firmware.ended_safely()
    else:
        assert stopped is not None
        message = str(stopped)
        assert "\n" not in message and "continue with --resume" in message
        assert "lights off" in message  # confirmed, or the watchdog's promise
        assert isinstance(stopped, CameraError if device == "camera" else RigError)
        # Stopped cleanly: lights off (by OFF or the watchdog), manifest lists only complete frames.
        assert wait_safe(session.opened.firmware)
        manifest = assert_consistent(run)
        assert len(manifest["frames"]) < N_FRAMES
        # The hung controller is power-cycled (the fault is gone); the run resumes from its
        # manifest.
        clean = load_rig(write_rig(tmp_path, retries=retries, name="clean.toml"))
        resumed = CaptureSession(clean, run, resume=True)
        assert len(resumed.remaining) == N_FRAMES - len(manifest["frames"])
        result = resumed.run()
        assert result.frames_skipped == len(manifest["frames"])
    assert_consistent(run)
    assert frame_hashes(run) == reference


def test_resume_cleans_up_what_a_crash_leaves(tmp_path: Path, reference: dict) -> None:
    rig = load_rig(write_rig(tmp_path))
    run = tmp_path / "run"
    CaptureSession(rig, run, lights=None).run()
    manifest = read_manifest(run)
    # Pretend the process died after renaming frame 5 but before the manifest listed it, and
    # while it was writing frame 6 and the manifest.
    manifest["frames"] = manifest["frames"][:5]
    (run / MANIFEST_NAME).write_text(json.dumps(manifest))
    (run / "frames" / "0005-L05-r0.dng").write_bytes(b"stale frame from a crashed session")
    (run / "frames" / (PARTIAL_PREFIX + "0006-L06-r0.dng")).write_bytes(b"half a frame")
    (run / (PARTIAL_PREFIX + MANIFEST_NAME)).write_text("{")
    for name in ("0006-L06-r0.dng", "0007-L07-r0.dng", "0008-L08-r0.dng"):
        (run / "frames" / name).unlink()
    session = CaptureSession(rig, run, resume=True)
    assert [f.index for f in session.remaining] == [5, 6, 7, 8]
    result = session.run()
    assert result.frames_captured == 4 and result.frames_skipped == 5
    assert frame_hashes(run) == reference
    assert not (run / (PARTIAL_PREFIX + MANIFEST_NAME)).exists()
    assert len(read_manifest(run)["sessions"]) == 2


def test_resume_refuses_changes(tmp_path: Path) -> None:
    rig = load_rig(write_rig(tmp_path))
    run = tmp_path / "run"
    CaptureSession(rig, run, lights=[1, 2, 3]).run()
    changed_text = (
        (tmp_path / "rig.toml").read_text().replace("exposure_s = 0.05", "exposure_s = 0.1")
    )
    (tmp_path / "changed.toml").write_text(changed_text)
    changed = load_rig(tmp_path / "changed.toml")
    with pytest.raises(RigError, match=r"camera\.exposure_s"):
        CaptureSession(changed, run, resume=True)
    with pytest.raises(RigError, match="--lights differs"):
        CaptureSession(rig, run, lights=[1, 2], resume=True)
    with pytest.raises(RigError, match="--repeat 2 differs"):
        CaptureSession(rig, run, repeat=2, resume=True)
    # A different port, timeout or fault list is not a different rig.
    relaxed = (tmp_path / "rig.toml").read_text().replace("timeout_s = 0.1", "timeout_s = 0.2")
    (tmp_path / "relaxed.toml").write_text(relaxed)
    assert CaptureSession(load_rig(tmp_path / "relaxed.toml"), run, resume=True).complete
    # A frame file that changed after it was captured cannot be resumed over.
    frame = run / "frames" / "0002-L02-r0.dng"
    frame.write_bytes(frame.read_bytes()[:-1] + b"\0")
    with pytest.raises(DatasetError, match="changed since it was captured"):
        CaptureSession(rig, run, resume=True)
    frame.unlink()
    with pytest.raises(DatasetError, match="is missing"):
        CaptureSession(rig, run, resume=True)


def signal_capture_at_frame(rig_path: Path, run: Path, k: int, signum: int) -> tuple[int, str]:
    """Run ``ps-lab capture`` in a subprocess; send ``signum`` once the manifest lists k frames."""
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "ps_lab",
            "capture",
            "--rig",
            str(rig_path),
            "--out",
            str(run),
            "-q",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and process.poll() is None:
            try:
                frames = len(json.loads((run / MANIFEST_NAME).read_text())["frames"])
            except (FileNotFoundError, json.JSONDecodeError):
                frames = 0
            if frames >= k:
                break
            time.sleep(0.002)
        assert process.poll() is None, "the capture finished before the signal"
        os.kill(process.pid, signum)
        _, stderr = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    return process.returncode, stderr


def test_sigkill_at_a_random_frame_then_resume(tmp_path: Path, reference: dict) -> None:
    # settle_ms slows each light frame down so that the kill lands mid-run.
    rig_path = write_rig(tmp_path, settle_ms=60)
    run = tmp_path / "run"
    k = int(np.random.default_rng(2012).integers(1, N_FRAMES - 1))
    returncode, _ = signal_capture_at_frame(rig_path, run, k, signal.SIGKILL)
    assert returncode == -signal.SIGKILL
    manifest = assert_consistent(run)
    assert k <= len(manifest["frames"]) < N_FRAMES
    result = CaptureSession(load_rig(rig_path), run, resume=True).run()
    assert result.frames_skipped == len(manifest["frames"])
    assert frame_hashes(run) == reference


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_or_sigterm_stops_cleanly_then_resume(
    tmp_path: Path, reference: dict, signum
) -> None:
    rig_path = write_rig(tmp_path, settle_ms=60)
    run = tmp_path / "run"
    k = int(np.random.default_rng(int(signum)).integers(1, N_FRAMES - 1))
    returncode, stderr = signal_capture_at_frame(rig_path, run, k, signum)
    assert returncode == 130, stderr
    errors = [line for line in stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "interrupted; lights off" in errors[0], stderr
    assert "Traceback" not in stderr
    manifest = assert_consistent(run)
    assert f"{len(manifest['frames'])} of {N_FRAMES} frames saved" in errors[0]
    CaptureSession(load_rig(rig_path), run, resume=True).run()
    assert frame_hashes(run) == reference


def test_failed_setup_writes_nothing(tmp_path: Path) -> None:
    # The controller hangs on its first command: the rig does not open, no run folder appears.
    faults = '[faults]\ncontroller = [{ kind = "silence", at = 1 }]\n'
    rig = load_rig(write_rig(tmp_path, faults=faults, name="hung.toml"))
    run = tmp_path / "run"
    with pytest.raises(RigError, match="light controller"):
        CaptureSession(rig, run).run()
    assert not run.exists()


def test_stop_at_the_first_frame_leaves_a_resumable_run(tmp_path: Path, reference: dict) -> None:
    faults = '[faults]\ncamera = [{ kind = "timeout", at = 1 }]\n'
    rig = load_rig(write_rig(tmp_path, faults=faults, retries=0, name="slow.toml"))
    run = tmp_path / "run"
    with pytest.raises(CameraError, match="frame 0 \\(dark frame\\).*0 of 9 frames saved"):
        CaptureSession(rig, run).run()
    assert read_manifest(run)["frames"] == []
    CaptureSession(load_rig(write_rig(tmp_path)), run, resume=True).run()
    assert frame_hashes(run) == reference


def test_folder_camera_with_serial_url_controller(tmp_path: Path) -> None:
    """A real-rig path: serial driver on a pyserial URL, frames dropped into a watched folder."""
    tether = tmp_path / "tether"
    tether.mkdir()
    rig_path = write_tethered_rig(tmp_path / "folder.toml", tether, 3, "folder-test")
    rng = np.random.default_rng(5)
    shots: list[str] = []

    def operator(message: str) -> None:
        # The operator presses the shutter: a DNG appears in the watched folder (hidden first).
        shots.append(message)
        mosaic = rng.integers(600, 4000, size=(32, 48)).astype(np.uint16)
        hidden = tether / f".shot{len(shots)}.dng"
        write_dng(hidden, mosaic, black_level=512, white_level=16383, exposure_s=0.01)
        hidden.rename(tether / f"IMG_{len(shots):04d}.dng")

    run = tmp_path / "run"
    result = CaptureSession(load_rig(rig_path), run, prompt=operator).run()
    assert result.frames_captured == 4
    assert shots[0] == "press the shutter for dark frame" and shots[-1].endswith("light 3")
    manifest = read_manifest(run)
    assert [r["file"] for r in manifest["frames"]] == [
        "frames/0000-dark.dng",
        "frames/0001-L01-r0.dng",
        "frames/0002-L02-r0.dng",
        "frames/0003-L03-r0.dng",
    ]
    assert all(r["exposure_s"] == pytest.approx(0.01) for r in manifest["frames"])
    assert not (run / "simulation").exists()
    assert not list(tether.iterdir())  # every shot was moved into the run


def test_simulator_in_another_process_via_state_file(tmp_path: Path, reference: dict) -> None:
    """`ps-lab rig serve-sim --state-file F` + a serial rig whose simulated camera reads F."""
    state_file = tmp_path / "state.json"
    text = write_rig(tmp_path).read_text()
    text = text.replace(
        'driver = "simulated"\nlights', 'driver = "serial"\nport = "{port}"\nlights', 1
    )
    text = text.replace("seed = 11", f'seed = 11\nlight_state_file = "{state_file}"')
    text = text.replace("intensity_spread = 0.1", "intensity_spread = 0.1\nnominal_error_deg = 2.0")
    with PtyServer(lights=N_LIGHTS, state_file=state_file) as server:
        rig_path = tmp_path / "serial.toml"
        rig_path.write_text(text.replace("{port}", str(server.path)))
        rig = load_rig(rig_path)
        run = tmp_path / "run"
        CaptureSession(rig, run).run()
        assert server.firmware.ended_safely()
    # The same scene, sensor and seeds as the in-process rig: the same bytes.
    assert frame_hashes(run) == reference
    nominal = np.loadtxt(run / "light_directions_nominal.txt")
    true = np.loadtxt(run / "simulation" / "light_directions_true.txt")
    angles = np.degrees(np.arccos(np.clip(np.sum(nominal * true, axis=1), -1, 1)))
    np.testing.assert_allclose(angles, 2.0, atol=1e-4)


@pytest.mark.parametrize("mishap", ["power_cycle", "watchdog"])
def test_light_lost_during_the_exposure_is_shot_again(
    tmp_path: Path, reference: dict, monkeypatch: pytest.MonkeyPatch, mishap: str
) -> None:
    """A controller that resets, or whose watchdog fires, mid-exposure must not yield a dark frame
    under a light's name: the session notices (reboot count, STATE) and shoots the frame again."""
    k = int(np.random.default_rng(len(mishap)).integers(2, N_FRAMES))
    original = cameras.SimulatedCamera._do_capture
    calls: list[int] = []

    def unlucky(self, path, frame_index, label):
        calls.append(frame_index)
        if len(calls) == k:
            firmware = self.light_state.__self__
            if mishap == "power_cycle":
                firmware.power_cycle()  # READY arrives unasked; every light is off
            else:
                time.sleep(0.9)  # longer than the rig's 600 ms watchdog
        return original(self, path, frame_index, label)

    monkeypatch.setattr(cameras.SimulatedCamera, "_do_capture", unlucky)
    text = write_rig(tmp_path).read_text().replace("watchdog_ms = 1500", "watchdog_ms = 600")
    rig_path = tmp_path / "short-watchdog.toml"
    rig_path.write_text(text)
    session = CaptureSession(load_rig(rig_path), tmp_path / "run")
    result = session.run()
    assert result.retries == 1
    assert calls[k - 1] == calls[k]  # the unlucky frame was shot again
    record = read_manifest(tmp_path / "run")["frames"][calls[k - 1]]
    assert record["attempts"] == 2
    assert frame_hashes(tmp_path / "run") == reference
