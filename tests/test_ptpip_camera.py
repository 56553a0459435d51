"""The camera path through the real libgphoto2: the PTP/IP camera simulator on 127.0.0.1.

Three clients talk to ``capture/simulated/ptpip_camera.py``: a minimal PTP/IP initiator written
here from CIPA DC-005 (the protocol's refusals and response codes), python-gphoto2's libgphoto2
(``Gphoto2Camera`` and whole ``ps-lab capture`` runs, faults included) and Debian's ``gphoto2``
command-line tool (a different libgphoto2 build). The simulator runs in its own process, as
``ps-lab rig serve-camera`` or started by the rig, except for the raw-protocol test.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import socket
import struct
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from helpers.rigs import SMALL_SCENE
from typer.testing import CliRunner

from ps_lab.capture import session as capture_session
from ps_lab.capture.faults import Fault
from ps_lab.capture.simulated import ptp
from ps_lab.capture.simulated.ptpip_camera import PtpIpCamera
from ps_lab.cli import app
from ps_lab.reconstruct.metrics import angular_errors_deg

ROOT = Path(__file__).resolve().parents[1]

RIG = """
name = "ptpip-small"

[controller]
driver = "simulated"
lights = {lights}
watchdog_ms = 5000
timeout_s = 0.5

[camera]
driver = "{driver}"
{port}
exposure_s = 0.05
timeout_s = {timeout}
retries = {retries}
seed = 11

""" + SMALL_SCENE


def _rig(
    folder: Path,
    *,
    driver: str = "gphoto2",
    lights: int = 16,
    retries: int = 1,
    timeout: float = 5.0,
    faults: str = "",
    name: str = "rig.toml",
) -> Path:
    port = 'port = "ptpip:127.0.0.1:0"' if driver == "gphoto2" else ""
    text = RIG.format(driver=driver, port=port, lights=lights, retries=retries, timeout=timeout)
    if faults:
        text += f"\n[faults]\ncamera = [{faults}]\n"
    path = folder / name
    path.write_text(text)
    return path


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def gphoto2_home(tmp_path, monkeypatch):
    """libgphoto2 keeps its PTP/IP GUID in ~/.gphoto/settings: a private HOME per test."""
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    return home


def _need_python_gphoto2():
    return pytest.importorskip("gphoto2", reason="python-gphoto2 not installed: ps-lab[gphoto2]")


# -- a minimal PTP/IP initiator (CIPA DC-005) --------------------------------------------------


class Initiator:
    """Command and event connections to a PTP/IP responder, one transaction at a time."""

    def __init__(self, port: int) -> None:
        self.command = self.event = None
        try:
            self._introduce(port)
        except BaseException:
            for sock in (self.command, self.event):
                if sock is not None:
                    sock.close()
            raise

    def _introduce(self, port: int) -> None:
        self.command = socket.create_connection(("127.0.0.1", port), timeout=5)
        name = "test".encode("utf-16-le") + b"\0\0"
        self._send(self.command, ptp.INIT_COMMAND_REQUEST, bytes(16) + name + ptp.u32(0x10000))
        kind, payload = self._read(self.command)
        assert kind == ptp.INIT_COMMAND_ACK, kind
        self.connection = struct.unpack_from("<I", payload)[0]
        self.responder = ptp.utf16_name(payload[20:])
        self.event = socket.create_connection(("127.0.0.1", port), timeout=5)
        self._send(self.event, ptp.INIT_EVENT_REQUEST, ptp.u32(self.connection))
        assert self._read(self.event)[0] == ptp.INIT_EVENT_ACK
        self.transaction = 0

    @staticmethod
    def _send(sock: socket.socket, kind: int, payload: bytes) -> None:
        sock.sendall(ptp.packet(kind, payload))

    @staticmethod
    def _read(sock: socket.socket) -> tuple[int, bytes]:
        header = b""
        while len(header) < 8:
            chunk = sock.recv(8 - len(header))
            assert chunk, "connection closed"
            header += chunk
        length, kind = struct.unpack("<II", header)
        body = b""
        while len(body) < length - 8:
            chunk = sock.recv(length - 8 - len(body))
            assert chunk, "connection closed"
            body += chunk
        return kind, body

    def op(self, code: int, *params: int, data_out: bytes | None = None):
        """Run one operation: (response code, response params, data in or None)."""
        self.transaction += 1
        t = self.transaction
        phase = 2 if data_out is not None else 1
        payload = ptp.u32(phase) + ptp.u16(code) + ptp.u32(t) + b"".join(map(ptp.u32, params))
        self._send(self.command, ptp.OPERATION_REQUEST, payload)
        if data_out is not None:
            self._send(self.command, ptp.START_DATA, ptp.u32(t) + ptp.u64(len(data_out)))
            self._send(self.command, ptp.END_DATA, ptp.u32(t) + data_out)
        data = None
        while True:
            kind, body = self._read(self.command)
            if kind == ptp.START_DATA:
                data = b""
            elif kind in (ptp.DATA, ptp.END_DATA):
                data += body[4:]
            else:
                assert kind == ptp.OPERATION_RESPONSE, kind
                code, tid = struct.unpack_from("<HI", body)
                assert tid == t
                count = (len(body) - 6) // 4
                return code, struct.unpack_from(f"<{count}I", body, 6), data

    def next_event(self) -> tuple[int, tuple[int, ...]]:
        kind, body = self._read(self.event)
        assert kind == ptp.EVENT
        code = struct.unpack_from("<H", body)[0]
        count = (len(body) - 6) // 4
        return code, struct.unpack_from(f"<{count}I", body, 6)

    def close(self) -> None:
        self.command.close()
        self.event.close()


def test_protocol_operations_and_refusals():
    """Every supported operation answers OK with its data set; the rest the right refusal."""
    shots = []

    def shoot(index: int, exposure_s: float, gain_scale: float) -> bytes:
        shots.append((index, exposure_s, gain_scale))
        time.sleep(0.3)  # a capture in progress, for the DeviceBusy checks
        return bytes([index]) * 300_000

    with PtpIpCamera(shoot, port=0, faults=[Fault("busy", at=2)]) as camera:
        cam = Initiator(camera.port)
        assert cam.responder == "ps-lab simulated camera"
        assert PtpIpCamera.address_of("127.0.0.1", 15740) == "ptpip:127.0.0.1"
        assert camera.address == f"ptpip:127.0.0.1:{camera.port}:{camera.port}"
        # A second initiator is refused while the first one is connected.
        other = socket.create_connection(("127.0.0.1", camera.port), timeout=5)
        Initiator._send(other, ptp.INIT_COMMAND_REQUEST, bytes(16) + b"\0\0" + ptp.u32(0x10000))
        kind, payload = Initiator._read(other)
        assert (kind, payload) == (ptp.INIT_FAIL, ptp.u32(ptp.FAIL_BUSY))
        other.close()

        code, _, info = cam.op(ptp.GET_DEVICE_INFO)  # allowed outside a session
        assert code == ptp.OK and struct.unpack_from("<HIH", info) == (100, 0, 0)
        assert "ps-lab simulated camera".encode("utf-16-le") in info
        assert cam.op(ptp.GET_STORAGE_IDS)[0] == ptp.SESSION_NOT_OPEN
        assert cam.op(ptp.OPEN_SESSION, 0)[0] == ptp.INVALID_PARAMETER
        assert cam.op(ptp.OPEN_SESSION, 7)[0] == ptp.OK
        assert cam.op(ptp.OPEN_SESSION, 8)[:2] == (ptp.SESSION_ALREADY_OPEN, (7,))
        code, _, ids = cam.op(ptp.GET_STORAGE_IDS)
        assert ids == ptp.u32_array([0x00010001])
        assert cam.op(ptp.GET_STORAGE_INFO, 0x00020001)[0] == ptp.INVALID_STORAGE_ID
        code, _, storage = cam.op(ptp.GET_STORAGE_INFO, 0x00010001)
        assert code == ptp.OK and struct.unpack_from("<HHH", storage) == (3, 1, 2)
        assert cam.op(ptp.GET_NUM_OBJECTS, 0xFFFFFFFF)[:2] == (ptp.OK, (0,))

        # Properties: the enumerations, values, and what is refused.
        code, _, desc = cam.op(ptp.GET_DEVICE_PROP_DESC, ptp.PROP_EXPOSURE_TIME)
        assert code == ptp.OK
        assert struct.unpack_from("<HHBIIB", desc) == (0x500D, ptp.UINT32, 1, 500, 500, 2)
        assert cam.op(ptp.GET_DEVICE_PROP_DESC, 0x5001)[0] == ptp.DEVICE_PROP_NOT_SUPPORTED
        assert cam.op(ptp.GET_DEVICE_PROP_VALUE, 0x5001)[0] == ptp.DEVICE_PROP_NOT_SUPPORTED
        bad = cam.op(ptp.SET_DEVICE_PROP_VALUE, 0x500D, data_out=ptp.u32(123))
        assert bad[0] == ptp.INVALID_DEVICE_PROP_VALUE
        wrong_size = cam.op(ptp.SET_DEVICE_PROP_VALUE, 0x500F, data_out=ptp.u32(200))
        assert wrong_size[0] == ptp.INVALID_DEVICE_PROP_FORMAT
        assert cam.op(ptp.SET_DEVICE_PROP_VALUE, 0x500D, data_out=ptp.u32(1000))[0] == ptp.OK
        assert cam.op(ptp.SET_DEVICE_PROP_VALUE, 0x500F, data_out=ptp.u16(400))[0] == ptp.OK
        assert cam.op(ptp.SET_DEVICE_PROP_VALUE, 0x5007, data_out=ptp.u16(400))[0] == ptp.OK
        assert cam.op(ptp.GET_DEVICE_PROP_VALUE, 0x500F)[2] == ptp.u16(400)
        assert cam.op(0x100A, 1)[0] == ptp.OPERATION_NOT_SUPPORTED  # GetThumb
        assert cam.op(0x9999)[0] == ptp.OPERATION_NOT_SUPPORTED

        # A capture: OK, then ObjectAdded and CaptureComplete on the event connection; while it
        # runs, another capture or a property change is DeviceBusy.
        code, _, _ = cam.op(ptp.INITIATE_CAPTURE, 0, 0)
        capture_transaction = cam.transaction
        assert code == ptp.OK
        assert cam.op(ptp.INITIATE_CAPTURE, 0, 0)[0] == ptp.DEVICE_BUSY  # in progress (and #2)
        busy = cam.op(ptp.SET_DEVICE_PROP_VALUE, 0x500D, data_out=ptp.u32(500))
        assert busy[0] == ptp.DEVICE_BUSY
        assert cam.next_event() == (ptp.OBJECT_ADDED, (1,))
        assert cam.next_event() == (ptp.CAPTURE_COMPLETE, (capture_transaction,))
        # exposure 0.1 s; gain (400 / 100) * (8 / 4)^2 = 16
        assert shots == [(0, 0.1, 16.0)]
        assert cam.op(ptp.INITIATE_CAPTURE, 0x00020001, 0)[0] == ptp.INVALID_STORAGE_ID
        assert cam.op(ptp.INITIATE_CAPTURE, 0, 0x3801)[0] == ptp.INVALID_OBJECT_FORMAT_CODE

        code, _, handles = cam.op(ptp.GET_OBJECT_HANDLES, 0xFFFFFFFF, 0, 0xFFFFFFFF)
        assert handles == ptp.u32_array([1])
        assert cam.op(ptp.GET_OBJECT_HANDLES, 0xFFFFFFFF, 0, 99)[0] == ptp.INVALID_PARENT_OBJECT
        code, _, info = cam.op(ptp.GET_OBJECT_INFO, 1)
        assert struct.unpack_from("<IHHI", info) == (0x00010001, ptp.FORMAT_TIFF, 0, 300_000)
        assert "IMG_0001.DNG".encode("utf-16-le") in info
        code, _, data = cam.op(ptp.GET_OBJECT, 1)  # Start Data, Data, End Data
        assert code == ptp.OK and data == bytes([0]) * 300_000
        assert camera.frames[0].sha256 == hashlib.sha256(data).hexdigest()
        assert cam.op(ptp.GET_OBJECT, 2)[0] == ptp.INVALID_OBJECT_HANDLE
        assert cam.op(ptp.DELETE_OBJECT, 1)[0] == ptp.OK
        assert cam.op(ptp.DELETE_OBJECT, 1)[0] == ptp.INVALID_OBJECT_HANDLE
        assert cam.op(ptp.GET_NUM_OBJECTS, 0xFFFFFFFF)[:2] == (ptp.OK, (0,))
        assert cam.op(ptp.CLOSE_SESSION)[0] == ptp.OK
        assert cam.op(ptp.GET_STORAGE_IDS)[0] == ptp.SESSION_NOT_OPEN
        cam.close()
        assert camera.captures == 2


# -- through python-gphoto2's libgphoto2 -------------------------------------------------------


class ServeCamera:
    """``ps-lab rig serve-camera`` in its own process; the port comes from its first line."""

    def __init__(self, rig: Path, *args: str) -> None:
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "ps_lab",
                "rig",
                "serve-camera",
                "--rig",
                str(rig),
                "--port",
                "0",
                *args,
            ],  # fmt: skip
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
        line = self.process.stdout.readline().strip()
        if not line.startswith("ptpip:"):
            self.process.kill()
            _, err = self.process.communicate()
            raise AssertionError(f"serve-camera printed {line!r}: {err}")
        self.address = line

    def stop(self) -> None:
        self.process.terminate()  # SIGTERM: serve-camera stops cleanly, exit status 0
        _, err = self.process.communicate(timeout=20)
        assert self.process.returncode == 0, err


def test_driver_sets_the_properties_and_downloads_the_frame(tmp_path, gphoto2_home):
    """Gphoto2Camera through the real libgphoto2: widgets, capture, download, delete."""
    _need_python_gphoto2()
    from ps_lab.capture.gphoto2_camera import Gphoto2Camera
    from ps_lab.io.raw import load_raw

    keep = tmp_path / "served"
    server = ServeCamera(_rig(tmp_path), "--lit", "1-16", "--keep", str(keep))
    try:
        # libgphoto2's widgets of the standard properties: shutterspeed (ExposureTime), iso
        # (ExposureIndex), f-number (FNumber; the driver's alias of aperture).
        camera = Gphoto2Camera(server.address, exposure_s=0.1, iso=200, aperture=4, timeout_s=5)
        with camera:
            first = camera.capture(tmp_path / "a.dng", label="light 1")
            camera.capture(tmp_path / "b.dng", label="light 2")
            assert camera.model == "PTP/IP Camera"
    finally:
        server.stop()
    assert first.exposure_s == pytest.approx(0.1)
    served = sorted(keep.iterdir())
    assert [p.name for p in served] == ["IMG_0001.DNG", "IMG_0002.DNG"]
    assert (tmp_path / "a.dng").read_bytes() == served[0].read_bytes()
    assert (tmp_path / "b.dng").read_bytes() == served[1].read_bytes()
    loaded = load_raw(tmp_path / "a.dng")
    assert loaded.exposure_s == pytest.approx(0.1)  # the shutterspeed reached the camera
    # ISO 200 at f/4: 2 * 4 = 8 times the rig's gain; the lit scene saturates more than half.
    assert loaded.image.shape == (120, 192, 3)
    assert np.mean(loaded.saturated) > 0.5


def _capture_recording(monkeypatch, args: list[str]):
    """Run ``ps-lab capture`` and return (exit code, output, the OpenRigs it opened)."""
    opened = []
    real = capture_session.open_rig

    def recording(*a, **k):
        rig = real(*a, **k)
        opened.append(rig)
        return rig

    monkeypatch.setattr(capture_session, "open_rig", recording)
    result = CliRunner().invoke(app, ["capture", *args, "--quiet"])
    return result.exit_code, result.output, opened


def _frames(run: Path) -> list[Path]:
    manifest = json.loads((run / "manifest.json").read_text())
    return [run / f["file"] for f in manifest["frames"]]


def test_capture_calibrate_reconstruct_through_libgphoto2(tmp_path, gphoto2_home, monkeypatch):
    """A whole run through libgphoto2 equals the simulated rig's, frame for frame."""
    _need_python_gphoto2()
    run = tmp_path / "run"
    code, output, opened = _capture_recording(
        monkeypatch, ["--rig", str(_rig(tmp_path)), "--out", str(run)]
    )
    assert code == 0, output
    frames = _frames(run)
    assert len(frames) == 17
    # byte-identical to the files the simulator shot, in order
    served = opened[0].served_frames
    assert [f.sha256 for f in served] == [_sha(p) for p in frames]
    # ... and to the simulated camera's (same scene, sensor, seed; frame k's noise is [seed, k])
    reference = tmp_path / "reference"
    simulated = _rig(tmp_path, driver="simulated", name="simulated.toml")
    args = ["--rig", str(simulated), "--out", str(reference)]
    code, output, _ = _capture_recording(monkeypatch, args)
    assert code == 0, output
    assert [_sha(p) for p in _frames(reference)] == [_sha(p) for p in frames]

    runner = CliRunner()
    result = runner.invoke(app, ["calibrate", str(run)])
    assert result.exit_code == 0, result.output
    estimated = np.loadtxt(run / "light_directions.txt")
    truth = np.loadtxt(run / "simulation" / "light_directions_true.txt")
    assert angular_errors_deg(estimated, truth).mean() < 0.5  # tests/test_end_to_end.py's bound
    out = run / "recon"
    result = runner.invoke(
        app, ["reconstruct", str(run), "--method", "sbl", "--refine-lights", "1", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["angular_error_deg"]["mean"] < 2.0


# kind: (re-shoots by the session, InitiateCapture requests, frames the camera shot)
FAULTS = {
    # busy: the driver triggers again (0.25 s later) until the camera accepts
    "busy": (0, 6, 5),
    # the capture is never reported: no RAW within timeout_s; the session re-shoots the frame
    "timeout": (1, 6, 5),
    # both connections dropped halfway through the download: the driver reconnects, re-shoot
    "disconnect": (1, 6, 6),
    # the download takes 2 s (slow_s): nothing times out
    "slow": (0, 5, 5),
}


@pytest.mark.parametrize("kind", sorted(FAULTS), ids=lambda kind: f"{kind}-fault")
def test_each_fault_recovers_losing_no_frame(kind, tmp_path, gphoto2_home, monkeypatch):
    _need_python_gphoto2()
    reshoots, requests, shot = FAULTS[kind]
    rig = _rig(tmp_path, lights=4, timeout=1.0, faults=f'{{ kind = "{kind}", at = 3 }}')
    run = tmp_path / "run"
    code, output, opened = _capture_recording(monkeypatch, ["--rig", str(rig), "--out", str(run)])
    assert code == 0, output
    frames = _frames(run)
    assert len(frames) == 5
    manifest = json.loads((run / "manifest.json").read_text())
    assert sum(f.get("attempts", 1) - 1 for f in manifest["frames"]) == reshoots, manifest["frames"]
    served = {f.sha256 for f in opened[0].served_frames}
    assert {_sha(p) for p in frames} <= served  # every frame is one the camera shot, whole
    assert (opened[0].served_captures, len(opened[0].served_frames)) == (requests, shot)
    third = manifest["frames"][2]
    seconds = datetime.fromisoformat(third["finished"]) - datetime.fromisoformat(third["started"])
    assert (seconds.total_seconds() > 1.9) == (kind == "slow")


def test_fault_without_retries_stops_with_one_line_and_resumes(tmp_path, gphoto2_home, monkeypatch):
    _need_python_gphoto2()
    # capture 4 of a session drops the connection; a resumed session's new camera counts afresh
    rig = _rig(tmp_path, lights=4, retries=0, faults='{ kind = "disconnect", at = 4 }')
    run = tmp_path / "run"
    code, output, _ = _capture_recording(monkeypatch, ["--rig", str(rig), "--out", str(run)])
    assert code == 2
    lines = [line for line in output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: capture stopped at frame 3"), output
    assert "gphoto2 lost the camera while capturing" in lines[0]
    assert len(json.loads((run / "manifest.json").read_text())["frames"]) == 3
    code, output, opened = _capture_recording(
        monkeypatch, ["--rig", str(rig), "--out", str(run), "--resume"]
    )
    assert code == 0, output
    frames = _frames(run)
    assert len(frames) == 5
    assert [f.sha256 for f in opened[0].served_frames] == [_sha(p) for p in frames[3:]]


# -- rig files and bad input ------------------------------------------------------------------


def test_rig_file_scene_needs_a_local_ptpip_port(tmp_path):
    from ps_lab.capture.rig import load_rig
    from ps_lab.errors import RigError

    path = _rig(tmp_path)
    assert load_rig(path).camera.driver == "gphoto2"
    path.write_text(path.read_text().replace("ptpip:127.0.0.1:0", "usb:001,004"))
    with pytest.raises(
        RigError, match=re.escape('a gphoto2 camera on port = "ptpip:127.0.0.1[:N]"')
    ):
        load_rig(path)


def test_rig_file_faults_and_sensor_keys(tmp_path):
    from ps_lab.capture.rig import load_rig, local_ptpip_port
    from ps_lab.errors import RigError

    with pytest.raises(RigError, match="'truncated' is not a fault of this camera"):
        load_rig(_rig(tmp_path, faults='{ kind = "truncated", at = 2 }'))
    with pytest.raises(RigError, match="'busy' is not a fault of this camera"):
        load_rig(_rig(tmp_path, driver="simulated", faults='{ kind = "busy", at = 2 }'))
    no_scene = tmp_path / "no-scene.toml"
    no_scene.write_text(
        '[controller]\ndriver = "simulated"\nlights = 4\n'
        '[camera]\ndriver = "gphoto2"\nexposure_s = 0.05\ngain = 5.0\n'
    )
    with pytest.raises(RigError, match="gain: applies to a gphoto2 camera only on a"):
        load_rig(no_scene)
    assert load_rig(ROOT / "rigs" / "simulated-ptpip.toml").camera.port == "ptpip:127.0.0.1:15740"
    assert [local_ptpip_port(p) for p in ("ptpip:127.0.0.1", "ptpip:localhost:99:99")] == [
        15740,
        99,
    ]
    assert local_ptpip_port("ptpip:192.168.1.5") is None


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--lit", "99"], "--lit '99': the rig has lights 1-16"),
        (["--fault", "garble@2"], "camera fault garble@2: write KIND@N with KIND one of busy"),
        (["--fault", "busy@p0.5"], "camera fault busy@p0.5: write KIND@N"),
    ],
)
def test_serve_camera_bad_input(tmp_path, args, message):
    rig = _rig(tmp_path)
    result = CliRunner().invoke(app, ["rig", "serve-camera", "--rig", str(rig), *args])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {message}"), result.output


def test_serve_camera_port_in_use_and_rig_without_scene(tmp_path):
    rig = _rig(tmp_path)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        result = CliRunner().invoke(
            app, ["rig", "serve-camera", "--rig", str(rig), "--port", str(port)]
        )
    assert result.exit_code == 2
    assert f"error: cannot listen on 127.0.0.1:{port}" in result.output
    plain = tmp_path / "plain.toml"
    plain.write_text(
        '[controller]\ndriver = "simulated"\nlights = 4\n'
        '[camera]\ndriver = "folder"\nfolder = "x"\nexposure_s = 0.05\n'
    )
    result = CliRunner().invoke(app, ["rig", "serve-camera", "--rig", str(plain)])
    assert result.exit_code == 2
    assert "has no [scene] for the camera to see" in result.output


# -- from outside: Debian's gphoto2 command-line tool ------------------------------------------


def _port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def test_gphoto2_command_line_tool(tmp_path, gphoto2_home):
    """`gphoto2 --summary` and `--capture-image-and-download` against serve-camera."""
    tool = shutil.which("gphoto2")
    if tool is None:
        pytest.skip("Debian's gphoto2 command-line tool is not installed (apt-get install gphoto2)")
    import rawpy

    default_port_free = _port_free(15740)  # the short ptpip:HOST:N form needs it
    keep = tmp_path / "served"
    server = ServeCamera(_rig(tmp_path), "--lit", "2,5", "--keep", str(keep))
    env = {**os.environ, "HOME": str(gphoto2_home), "LANG": "C"}
    try:
        summary = subprocess.run(
            [tool, "--port", server.address, "--summary"],
            capture_output=True,
            text=True,
            timeout=60,
            env=env,  # fmt: skip
        )
        assert summary.returncode == 0, summary.stdout + summary.stderr
        assert "Model: ps-lab simulated camera" in summary.stdout
        assert "500d" in summary.stdout.lower()  # ExposureTime in the property summary
        # The short form ptpip:HOST:N opens its event connection on 15740: serve-camera listens
        # there too while that port is free.
        if default_port_free:
            host, port = server.address.split(":")[1:3]
            assert not _port_free(15740), "serve-camera did not take 15740 for event connections"
            short = subprocess.run(
                [tool, "--port", f"ptpip:{host}:{port}", "--summary"],
                capture_output=True,
                text=True,
                timeout=60,
                env=env,  # fmt: skip
            )
            assert short.returncode == 0, short.stdout + short.stderr
        shot = subprocess.run(
            [
                tool,
                "--port",
                server.address,
                "--capture-image-and-download",
                "--filename",
                str(tmp_path / "cli.dng"),
            ],  # fmt: skip
            capture_output=True,
            text=True,
            timeout=60,
            env=env,  # fmt: skip
        )
        assert shot.returncode == 0, shot.stdout + shot.stderr
    finally:
        server.stop()
    downloaded = (tmp_path / "cli.dng").read_bytes()
    assert downloaded == (keep / "IMG_0001.DNG").read_bytes()
    with rawpy.imread(str(tmp_path / "cli.dng")) as raw:
        assert raw.raw_image_visible.shape == (240, 384)
        assert raw.raw_image_visible.mean() > 600  # lights 2 and 5 lit, above the black level


# -- hostile initiators: no sequence leaves the camera busy ------------------------------------

_HELLO = bytes(16) + "hostile".encode("utf-16-le") + b"\0\0" + ptp.u32(0x10000)


def _reset(sock: socket.socket) -> None:
    """Close with a TCP reset (SO_LINGER 0), as a crashed or killed initiator does."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()


def _connect(port: int) -> socket.socket:
    return socket.create_connection(("127.0.0.1", port), timeout=5)


def _init_command(port: int, *, read_ack: bool = True) -> tuple[socket.socket, int]:
    sock = _connect(port)
    Initiator._send(sock, ptp.INIT_COMMAND_REQUEST, _HELLO)
    if not read_ack:
        return sock, 0
    kind, payload = Initiator._read(sock)
    assert kind == ptp.INIT_COMMAND_ACK, kind
    return sock, struct.unpack_from("<I", payload)[0]


def _both(port: int) -> tuple[socket.socket, socket.socket]:
    command, number = _init_command(port)
    event = _connect(port)
    Initiator._send(event, ptp.INIT_EVENT_REQUEST, ptp.u32(number))
    assert Initiator._read(event)[0] == ptp.INIT_EVENT_ACK
    return command, event


def _reset_after_request(port):
    for _ in range(3):  # the reported case: three initiators in a row
        sock, _ = _init_command(port, read_ack=False)
        _reset(sock)


def _close_after_request(port):
    sock, _ = _init_command(port, read_ack=False)
    sock.close()


def _reset_after_ack(port):
    _reset(_init_command(port)[0])


def _reset_before_event_ack(port):
    command, number = _init_command(port)
    event = _connect(port)
    Initiator._send(event, ptp.INIT_EVENT_REQUEST, ptp.u32(number))
    _reset(event)
    _reset(command)


def _reset_event_only(port):
    command, event = _both(port)
    _reset(event)
    return command  # still open: its place is released all the same


def _reset_command_only(port):
    command, event = _both(port)
    _reset(command)
    return event


def _reset_in_a_session(port):
    command, event = _both(port)
    payload = ptp.u32(1) + ptp.u16(ptp.OPEN_SESSION) + ptp.u32(1) + ptp.u32(1)
    Initiator._send(command, ptp.OPERATION_REQUEST, payload)
    assert Initiator._read(command)[0] == ptp.OPERATION_RESPONSE
    _reset(command)
    _reset(event)


def _start_data_phase(command, size: int) -> None:
    """A SetDevicePropValue request for property 0x500D and the start of its ``size``-byte data."""
    payload = ptp.u32(2) + ptp.u16(ptp.SET_DEVICE_PROP_VALUE) + ptp.u32(1) + ptp.u32(0x500D)
    Initiator._send(command, ptp.OPERATION_REQUEST, payload)
    Initiator._send(command, ptp.START_DATA, ptp.u32(1) + ptp.u64(size))


def _reset_in_a_data_phase(port):
    command, event = _both(port)
    _start_data_phase(command, 4)
    _reset(command)
    return event


def _oversized_data_phase(port):
    command, event = _both(port)
    _start_data_phase(command, 1 << 30)
    chunk = ptp.u32(1) + bytes(8 << 20)
    try:
        for _ in range(3):  # 24 MiB for a property of 4 bytes: the camera hangs up
            Initiator._send(command, ptp.DATA, chunk)
    except OSError:
        pass
    return command, event


def _no_event_connection(port):
    return _init_command(port)[0]  # open, silent, never asks for its event connection


def _stalled_mid_packet(port):
    command, event = _both(port)
    command.sendall(ptp.u32(30) + ptp.u32(ptp.OPERATION_REQUEST))  # a header, then nothing
    return command, event


def _silent_after_handshake(port):
    return _both(port)  # alive and connected, says nothing: yields after YIELD_S


def _many_silent_connections(port):
    return [_connect(port) for _ in range(40)]  # never introduce themselves


HOSTILE = {
    "reset-after-init-command-request": _reset_after_request,
    "close-after-init-command-request": _close_after_request,
    "reset-after-init-command-ack": _reset_after_ack,
    "reset-before-init-event-ack": _reset_before_event_ack,
    "reset-event-connection-only": _reset_event_only,
    "reset-command-connection-only": _reset_command_only,
    "reset-in-a-session": _reset_in_a_session,
    "reset-in-a-data-phase": _reset_in_a_data_phase,
    "oversized-data-phase": _oversized_data_phase,
    "no-event-connection": _no_event_connection,
    "stalled-mid-packet": _stalled_mid_packet,
    "silent-after-handshake": _silent_after_handshake,
    "many-silent-connections": _many_silent_connections,
}


@pytest.fixture
def short_timeouts(monkeypatch):
    """The camera's patience in seconds, shortened so that the half-open cases run fast."""
    from ps_lab.capture.simulated import ptpip_camera

    for name, value in (("STALL_S", 0.5), ("EVENT_WAIT_S", 0.5), ("YIELD_S", 0.5)):
        monkeypatch.setattr(ptpip_camera, name, value)
    monkeypatch.setattr(ptpip_camera, "CONTENDED_S", 0.3)


def _served_within(port: int, seconds: float) -> Initiator:
    """The next initiator, tried until the camera frees its place (Init Fail busy until then)."""
    deadline = time.monotonic() + seconds
    while True:
        try:
            return Initiator(port)
        except AssertionError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


@pytest.mark.parametrize("sequence", sorted(HOSTILE))
def test_hostile_initiator_never_leaves_the_camera_busy(sequence, short_timeouts, caplog):
    """After each sequence a well-behaved initiator is served (at once where the peer is gone)."""
    with PtpIpCamera(lambda *_: b"dng", port=0) as camera:
        held = HOSTILE[sequence](camera.port)
        held = list(held) if isinstance(held, (list, tuple)) else [held] if held else []
        try:
            # a dead holder is noticed as soon as the newcomer arrives: well inside the 5 s a
            # half-open one is given (2 s leaves room for a loaded machine's scheduling)
            dead = sequence.startswith(("reset", "close"))
            cam = _served_within(camera.port, 2.0 if dead else 10.0)
            assert cam.op(ptp.OPEN_SESSION, 1)[0] == ptp.OK
            assert cam.op(ptp.GET_STORAGE_IDS)[0] == ptp.OK
            cam.close()
        finally:
            for sock in held:
                sock.close()
        # ... and the place is free again for the next one
        _served_within(camera.port, 5.0).close()


def test_half_open_initiator_released_without_a_newcomer(short_timeouts):
    """No event connection within EVENT_WAIT_S: the camera releases the place by itself."""
    with PtpIpCamera(lambda *_: b"dng", port=0) as camera:
        sock = _no_event_connection(camera.port)
        deadline = time.monotonic() + 10.0
        while camera._command is not None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert camera._command is None
        assert sock.recv(1) == b""  # the camera hung up on it
        sock.close()


def test_connected_initiator_keeps_its_place_while_active():
    """A live initiator that has just spoken keeps the camera: a newcomer gets Init Fail busy."""
    with PtpIpCamera(lambda *_: b"dng", port=0) as camera:
        cam = Initiator(camera.port)
        assert cam.op(ptp.OPEN_SESSION, 1)[0] == ptp.OK
        other, _ = _init_command(camera.port, read_ack=False)
        assert Initiator._read(other) == (ptp.INIT_FAIL, ptp.u32(ptp.FAIL_BUSY))
        other.close()
        assert cam.op(ptp.GET_STORAGE_IDS)[0] == ptp.OK
        cam.close()


def test_gphoto2_summary_after_hostile_initiators(tmp_path, gphoto2_home):
    """Debian's gphoto2 --summary works after initiators reset in every phase of the handshake."""
    tool = shutil.which("gphoto2")
    if tool is None:
        pytest.skip("Debian's gphoto2 command-line tool is not installed (apt-get install gphoto2)")
    env = {**os.environ, "HOME": str(gphoto2_home), "LANG": "C"}
    with PtpIpCamera(lambda *_: b"dng", port=0) as camera:
        for sequence in ("reset-after-init-command-request", "reset-after-init-command-ack",
                         "reset-before-init-event-ack", "reset-in-a-session"):  # fmt: skip
            HOSTILE[sequence](camera.port)
        summary = subprocess.run(
            [tool, "--port", camera.address, "--summary"],
            capture_output=True, text=True, timeout=60, env=env,  # fmt: skip
        )
    assert summary.returncode == 0, summary.stdout + summary.stderr
    assert "Model: ps-lab simulated camera" in summary.stdout
