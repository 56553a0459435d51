"""Cameras: simulated sensor round trips through real DNG files, faults, folder and gphoto2."""

from __future__ import annotations

import builtins
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import rawpy
from helpers.gphoto2_double import (
    GP_EVENT_FILE_ADDED,
    GP_WIDGET_RADIO,
    GP_WIDGET_WINDOW,
    CameraFilePath,
    Widget,
)

from ps_lab import render
from ps_lab.capture.camera_devices import CameraDevice, CapturedFrame, FolderCamera
from ps_lab.capture.simulated import firmware as sim_lights
from ps_lab.capture.simulated.simulated_camera import SimulatedCamera
from ps_lab.errors import CameraError, DatasetError
from ps_lab.io.dng import write_dng
from ps_lab.io.raw import load_raw


@dataclass(frozen=True)
class State:
    lit: frozenset[int]
    level: int = 255


class Switch:
    """Stands in for the simulated controller: the test sets which lights are lit."""

    def __init__(self) -> None:
        self.state = State(frozenset())

    def set(self, *lights: int, level: int = 255) -> None:
        self.state = State(frozenset(lights), level)

    def __call__(self) -> State:
        return self.state


@dataclass(frozen=True)
class LambertScene:
    normals: np.ndarray  # (H, W, 3)
    albedo: np.ndarray  # (H, W, 3)


def lambert_render(
    scene: LambertScene, directions: np.ndarray, intensities: np.ndarray
) -> np.ndarray:
    """Local stand-in for render_scene: sum of Lambertian shading of the lit lights."""
    shading = np.clip(np.einsum("hwc,kc->khw", scene.normals, directions), 0, None)
    return np.einsum("khw,kc->hwc", shading, intensities) * scene.albedo


def make_scene(rng: np.random.Generator, shape=(16, 20)) -> LambertScene:
    normals = rng.normal(size=(*shape, 3))
    normals[..., 2] = np.abs(normals[..., 2]) + 1.0
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    albedo = rng.uniform(0.2, 1.0, size=(*shape, 3))
    return LambertScene(normals, albedo)


LIGHTS = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 0.866], [0.0, -0.5, 0.866], [-0.6, 0.3, 0.742]])
LIGHTS = LIGHTS / np.linalg.norm(LIGHTS, axis=1, keepdims=True)
INTENSITIES = np.array([[1.0, 0.9, 0.8], [1.2, 1.1, 1.0], [0.7, 0.8, 0.9], [1.0, 1.0, 1.0]])


def make_camera(scene, switch, **overrides) -> SimulatedCamera:
    args = dict(
        exposure_s=0.04,
        gain=250_000.0,
        read_noise_dn=0.0,
        shot_noise=False,
        render=lambert_render,
        timeout_s=0.05,
    )
    args.update(overrides)
    return SimulatedCamera(scene, LIGHTS, INTENSITIES, switch, **args)


def test_round_trip_equals_rendered_radiance_scaled(tmp_path, rng):
    scene, switch = make_scene(rng), Switch()
    camera = make_camera(scene, switch, gain=500_000.0)
    switch.set(2)
    frame = camera.capture(tmp_path / "f.dng", frame_index=1)
    assert isinstance(frame, CapturedFrame) and frame.exposure_s == 0.04
    assert frame.started <= frame.finished
    loaded = load_raw(frame.path)
    radiance = lambert_render(scene, LIGHTS[[1]], INTENSITIES[[1]])
    assert loaded.image.shape == radiance.shape
    assert loaded.exposure_s == pytest.approx(0.04, rel=1e-12)
    # Expected raw per channel, written out independently: mean DN, rounded, clipped.
    raw = np.clip(np.rint(radiance * 0.04 * 500_000.0 + 512), 0, 16383)
    expected_sat = (raw >= 16383).any(axis=-1)
    assert expected_sat.any() and not expected_sat.all()  # the gain makes some pixels clip
    np.testing.assert_array_equal(loaded.saturated, expected_sat)
    ok = ~expected_sat
    scale = camera.linear_scale
    assert scale == pytest.approx(0.04 * 500_000.0 / (16383 - 512))
    err = np.abs(loaded.image[ok] - radiance[ok] * scale)
    assert err.max() <= 0.5 / (16383 - 512) + 1e-6


def test_doubling_exposure_doubles_values(tmp_path, rng):
    scene, switch = make_scene(rng), Switch()
    switch.set(1, 3)
    short = make_camera(scene, switch, gain=50_000.0)
    long = make_camera(scene, switch, gain=50_000.0, exposure_s=0.08)
    a = load_raw(short.capture(tmp_path / "a.dng", frame_index=0).path)
    b = load_raw(long.capture(tmp_path / "b.dng", frame_index=0).path)
    assert b.exposure_s == pytest.approx(2 * a.exposure_s)
    ok = ~(a.saturated | b.saturated)
    assert ok.mean() > 0.9
    # Exact up to the rounding of each to whole DN.
    np.testing.assert_allclose(b.image[ok], 2 * a.image[ok], atol=1.5 / (16383 - 512))
    # With noise on, the mean over the image doubles within the noise.
    noisy_a = make_camera(scene, switch, gain=50_000.0, read_noise_dn=3.0, shot_noise=True)
    noisy_b = make_camera(
        scene, switch, gain=50_000.0, read_noise_dn=3.0, shot_noise=True, exposure_s=0.08
    )
    na = load_raw(noisy_a.capture(tmp_path / "na.dng", frame_index=5).path).image[ok].mean()
    nb = load_raw(noisy_b.capture(tmp_path / "nb.dng", frame_index=6).path).image[ok].mean()
    assert nb / na == pytest.approx(2.0, rel=2e-3)


def test_noise_model_statistics(tmp_path):
    shape = (40, 40)
    flat = LambertScene(np.tile([0.0, 0.0, 1.0], (*shape, 1)), np.full((*shape, 3), 0.5))
    switch = Switch()
    switch.set(1)
    camera = SimulatedCamera(
        flat,
        LIGHTS,
        None,
        switch,
        exposure_s=0.04,
        gain=200_000.0,
        read_noise_dn=4.0,
        shot_noise=True,
        dn_per_electron=0.5,
        render=lambert_render,
    )
    camera.capture(tmp_path / "flat.dng", frame_index=3)

    with rawpy.imread(str(tmp_path / "flat.dng")) as raw:
        values = raw.raw_image_visible.astype(float) - 512
    mean_dn = 0.5 * 0.04 * 200_000.0
    assert values.mean() == pytest.approx(mean_dn, rel=2e-3)
    assert values.var() == pytest.approx(mean_dn * 0.5 + 16.0, rel=0.08)


def test_reshot_frame_is_byte_identical(tmp_path, rng):
    scene, switch = make_scene(rng), Switch()
    switch.set(4)
    first = make_camera(scene, switch, read_noise_dn=2.0, shot_noise=True, seed=7)
    again = make_camera(scene, switch, read_noise_dn=2.0, shot_noise=True, seed=7)
    first.capture(tmp_path / "x.dng")  # capture count 0 -> frame 0
    a = first.capture(tmp_path / "a.dng", frame_index=9).path.read_bytes()
    b = again.capture(tmp_path / "b.dng", frame_index=9).path.read_bytes()
    c = again.capture(tmp_path / "c.dng", frame_index=10).path.read_bytes()
    other_seed = make_camera(scene, switch, read_noise_dn=2.0, shot_noise=True, seed=8)
    d = other_seed.capture(tmp_path / "d.dng", frame_index=9).path.read_bytes()
    assert a == b
    assert a != c and a != d


def test_renders_exactly_the_lit_lights_at_the_level(tmp_path, rng):
    scene, switch = make_scene(rng), Switch()
    camera = make_camera(scene, switch, gain=20_000.0)
    images = {}
    for name, lit, level in [
        ("one", (1,), 255),
        ("three", (3,), 255),
        ("both", (1, 3), 255),
        ("half", (1, 3), 128),
        ("dark", (), 255),
    ]:
        switch.set(*lit, level=level)
        images[name] = load_raw(camera.capture(tmp_path / f"{name}.dng").path).image
    tol = 2.0 / (16383 - 512)
    np.testing.assert_allclose(images["both"], images["one"] + images["three"], atol=tol)
    np.testing.assert_allclose(images["half"], images["both"] * 128 / 255, atol=tol)
    np.testing.assert_allclose(images["dark"], 0.0, atol=tol)
    assert images["one"].max() > 0.02
    switch.set(5)
    with pytest.raises(CameraError, match="light"):
        camera.capture(tmp_path / "bad.dng")


def test_real_renderer_scene_round_trip(tmp_path):
    scene = render.Scene(
        width=32,
        height=24,
        objects=(
            render.SceneObject("matte", (10.0, 12.0), 8.0, (0.8, 0.6, 0.4)),
            render.SceneObject("chrome", (24.0, 12.0), 6.0),
        ),
    )
    switch = Switch()
    camera = SimulatedCamera(
        scene,
        LIGHTS,
        INTENSITIES,
        switch,
        exposure_s=0.02,
        gain=100_000.0,
        read_noise_dn=0.0,
        shot_noise=False,
    )
    switch.set(2)
    loaded = load_raw(camera.capture(tmp_path / "s.dng").path)
    radiance = render.render_scene(scene, LIGHTS[[1]], INTENSITIES[[1]])
    raw = np.clip(np.rint(radiance * 0.02 * 100_000.0 + 512), 0, 16383)
    np.testing.assert_array_equal(loaded.saturated, (raw >= 16383).any(axis=-1))
    ok = ~loaded.saturated
    assert loaded.image.shape == (24, 32, 3)
    assert loaded.image.max() > 0.05
    expected = radiance * camera.linear_scale
    np.testing.assert_allclose(loaded.image[ok], expected[ok], atol=0.5 / (16383 - 512) + 1e-6)


def test_driven_by_the_simulated_controller(tmp_path):
    scene = render.Scene(
        width=24,
        height=16,
        objects=(render.SceneObject("matte", (12.0, 8.0), 7.0, (0.9, 0.9, 0.9)),),
        background=0.01,
    )
    firmware = sim_lights.SimulatedFirmware(lights=4)
    camera = SimulatedCamera(
        scene,
        LIGHTS,
        INTENSITIES,
        firmware.state,
        exposure_s=0.02,
        gain=100_000.0,
        read_noise_dn=0.0,
        shot_noise=False,
    )
    dark = load_raw(camera.capture(tmp_path / "dark.dng").path).image
    assert firmware.handle_line("ON 3") == ["OK ON 3"]
    lit = load_raw(camera.capture(tmp_path / "lit.dng").path).image
    expected = render.render_scene(scene, LIGHTS[[2]], INTENSITIES[[2]]) * camera.linear_scale
    np.testing.assert_allclose(lit, expected, atol=1e-4)
    background = render.render_scene(scene, np.zeros((0, 3))) * camera.linear_scale
    assert background.max() > 0
    np.testing.assert_allclose(dark, background, atol=1e-4)
    assert firmware.handle_line("OFF") == ["OK OFF"]
    again = load_raw(camera.capture(tmp_path / "off.dng").path).image
    np.testing.assert_array_equal(again, dark)


def test_injected_faults(tmp_path, rng):
    scene, switch = make_scene(rng), Switch()
    switch.set(1)
    camera = make_camera(
        scene, switch, faults=[{"kind": "timeout", "at": 2}, {"kind": "truncated", "at": 3}]
    )
    camera.capture(tmp_path / "1.dng")
    with pytest.raises(CameraError, match="timed out"):
        camera.capture(tmp_path / "2.dng")
    frame = camera.capture(tmp_path / "3.dng")  # the truncated file arrives...
    assert frame.path.stat().st_size > 0
    with pytest.raises(DatasetError, match="3.dng"):  # ...and fails verification
        load_raw(frame.path)
    load_raw(camera.capture(tmp_path / "4.dng").path)  # later captures are fine
    assert camera.captures == 4


@pytest.mark.parametrize(
    "faults",
    [
        [{"kind": "explode", "at": 1}],
        [{"kind": "timeout", "at": 0}],
        [{"kind": "timeout"}],
        [{"kind": "timeout", "at": 1, "x": 2}],
    ],
)
def test_bad_fault_config(rng, faults):
    with pytest.raises(CameraError, match="fault"):
        make_camera(make_scene(rng), Switch(), faults=faults)


def test_bad_camera_parameters(rng):
    scene = make_scene(rng)
    with pytest.raises(CameraError, match="exposure"):
        make_camera(scene, Switch(), exposure_s=0.0)
    with pytest.raises(CameraError, match="black_level"):
        make_camera(scene, Switch(), black_level=20000)
    with pytest.raises(CameraError, match="light_directions"):
        SimulatedCamera(scene, np.ones((3, 2)), None, Switch(), exposure_s=0.1)


class ScriptedCamera(CameraDevice):
    driver = "scripted"

    def __init__(self, action):
        super().__init__(timeout_s=1.0)
        self.action = action
        self.closed_calls = 0

    def _do_capture(self, path: Path, frame_index: int, label: str):
        return self.action(path)

    def _do_close(self) -> None:
        self.closed_calls += 1


def test_base_class_template_checks(tmp_path):
    def writes(path):
        path.write_bytes(b"data")
        return 0.25

    camera = ScriptedCamera(writes)
    frame = camera.capture(tmp_path / "ok.raw")
    assert frame.exposure_s == 0.25 and frame.path.read_bytes() == b"data"
    with pytest.raises(CameraError, match="does not exist"):
        camera.capture(tmp_path / "missing" / "x.dng")
    with pytest.raises(CameraError, match="folder"):
        camera.capture(tmp_path)
    with pytest.raises(CameraError, match="no file"):
        ScriptedCamera(lambda p: 1.0).capture(tmp_path / "none.dng")
    with pytest.raises(CameraError, match="empty"):
        ScriptedCamera(lambda p: p.write_bytes(b"") and 1.0).capture(tmp_path / "empty.dng")

    def fails(path):
        raise OSError("disk full")

    with pytest.raises(CameraError, match="disk full"):
        ScriptedCamera(fails).capture(tmp_path / "f.dng")
    with camera:
        pass
    assert camera.closed_calls == 1
    camera.close()
    assert camera.closed_calls == 1
    with pytest.raises(CameraError, match="closed"):
        camera.capture(tmp_path / "after.raw")


def _drop_later(path: Path, data: bytes, delay: float, chunks: int = 3) -> threading.Thread:
    def run():
        time.sleep(delay)
        with open(path, "wb") as handle:
            for i in range(chunks):  # a slowly growing file, as tethering software writes it
                handle.write(data[i * len(data) // chunks : (i + 1) * len(data) // chunks])
                handle.flush()
                time.sleep(0.03)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_folder_camera_takes_the_next_new_stable_file(tmp_path, rng):
    watched, out = tmp_path / "watched", tmp_path / "run"
    watched.mkdir()
    out.mkdir()
    (watched / "old.dng").write_bytes(b"old frame")
    data = rng.bytes(30000)
    prompts = []
    camera = FolderCamera(
        watched, timeout_s=5.0, pattern="*.dng", prompt=prompts.append, poll_s=0.02, exposure_s=0.1
    )
    (watched / "sibling.jpg").write_bytes(b"jpeg")
    thread = _drop_later(watched / "IMG_0001.DNG", data, 0.1)
    frame = camera.capture(out / "0001.dng", label="light 3")
    thread.join()
    assert prompts == ["press the shutter for light 3"]
    assert frame.path.read_bytes() == data
    assert not (watched / "IMG_0001.DNG").exists()  # moved
    assert frame.exposure_s == 0.1  # not a readable RAW: the nominal exposure
    with pytest.raises(CameraError, match="no new file"):
        FolderCamera(watched, timeout_s=0.1, pattern="*.dng", poll_s=0.02).capture(out / "x.dng")


def test_folder_camera_copy_mode_and_raw_exposure(tmp_path, rng):
    watched = tmp_path / "watched"
    watched.mkdir()
    camera = FolderCamera(watched, timeout_s=5.0, poll_s=0.02, copy=True)
    source = tmp_path / "src.dng"
    write_dng(
        source,
        rng.integers(0, 4000, (32, 32)).astype(np.uint16),
        black_level=100,
        white_level=4095,
        exposure_s=1 / 125,
    )
    thread = _drop_later(watched / "shot.dng", source.read_bytes(), 0.05)
    frame = camera.capture(tmp_path / "frame.dng")
    thread.join()
    assert (watched / "shot.dng").exists()  # copied, original kept and not taken twice
    assert frame.exposure_s == pytest.approx(1 / 125)
    with pytest.raises(CameraError, match="no new file"):
        FolderCamera(watched, timeout_s=0.1, poll_s=0.02).capture(tmp_path / "again.dng")
    with pytest.raises(CameraError, match="does not exist"):
        FolderCamera(tmp_path / "nope")


# --------------------------------------------------------------------------------------------
# Gphoto2Camera against the API double
# --------------------------------------------------------------------------------------------

from helpers.gphoto2_double import GP_ERROR_IO_USB_CLAIM, Shot, make_gphoto2_double  # noqa: E402

from ps_lab.capture.gphoto2_camera import Gphoto2Camera, parse_shutter_speed  # noqa: E402

RIG_SETTINGS = {"imageformat": "RAW", "shutterspeed": "1/20", "iso": "100", "aperture": "8"}


def test_gphoto2_applies_settings_and_downloads_the_raw(tmp_path, rng):
    gp = make_gphoto2_double()
    raw_bytes, jpeg_bytes = rng.bytes(5000), rng.bytes(800)
    gp.rig.shots.append(
        Shot({"IMG_0001.JPG": jpeg_bytes, "IMG_0001.CR2": raw_bytes}, delay_events=2)
    )
    gp.rig.shots.append(Shot({"IMG_0002.CR2": raw_bytes[::-1]}))
    with Gphoto2Camera(settings=RIG_SETTINGS, timeout_s=2.0, gp_module=gp) as camera:
        config = gp.rig.config
        assert config.get_child_by_name("imageformat").value == "RAW"
        assert config.get_child_by_name("shutterspeed").value == "1/20"
        assert config.get_child_by_name("iso").value == "100"
        assert config.get_child_by_name("aperture").value == "8"
        assert config.get_child_by_name("capturetarget").value == "Internal RAM"  # default
        assert ("set_port_info", "usb:001,004") in gp.rig.calls
        first = camera.capture(tmp_path / "0001.cr2", label="light 1")
        second = camera.capture(tmp_path / "0002.cr2")
    assert first.path.read_bytes() == raw_bytes  # the RAW, not the JPEG sibling
    assert second.path.read_bytes() == raw_bytes[::-1]
    assert first.exposure_s == pytest.approx(0.05)
    assert first.started <= first.finished <= second.started
    downloaded = [c[2] for c in gp.rig.calls if c[0] == "file_get"]
    assert downloaded == ["IMG_0001.CR2", "IMG_0002.CR2"]
    assert gp.rig.storage == {}  # RAW and JPEG deleted from the camera's RAM
    assert gp.rig.calls[-1] == ("exit",)


def test_gphoto2_explicit_port_and_keep_on_camera(tmp_path, rng):
    gp = make_gphoto2_double()
    gp.rig.shots.append(Shot({"DSC_0001.NEF": rng.bytes(100)}))
    camera = Gphoto2Camera(
        "usb:001,004",
        settings={"capturetarget": "Memory card"},
        keep_on_camera=True,
        gp_module=gp,
        timeout_s=1.0,
    )
    camera.capture(tmp_path / "a.nef")
    camera.close()
    assert len(gp.rig.storage) == 1
    assert camera.settings["port"] == "usb:001,004"


def test_gphoto2_timeout_when_no_raw_arrives(tmp_path):
    gp = make_gphoto2_double()
    gp.rig.shots.append(Shot({"IMG_0001.JPG": b"jpeg only"}))
    camera = Gphoto2Camera(settings={}, timeout_s=0.05, gp_module=gp)
    with pytest.raises(CameraError, match="no RAW file within"):
        camera.capture(tmp_path / "x.cr2")
    with pytest.raises(CameraError, match="no RAW file within"):  # nothing at all arrives
        camera.capture(tmp_path / "y.cr2")
    assert not (tmp_path / "x.cr2").exists()


def test_gphoto2_ignores_leftover_files_from_an_earlier_shot(tmp_path, rng):
    gp = make_gphoto2_double()

    gp.rig.storage[("/", "OLD.CR2")] = b"stale"
    gp.rig.leftover_events = [(GP_EVENT_FILE_ADDED, CameraFilePath("/", "OLD.CR2"))]
    fresh = rng.bytes(300)
    gp.rig.shots.append(Shot({"NEW.CR2": fresh}))
    camera = Gphoto2Camera(settings={}, timeout_s=1.0, gp_module=gp)
    assert camera.capture(tmp_path / "f.cr2").path.read_bytes() == fresh


def test_gphoto2_clear_errors(tmp_path):
    gp = make_gphoto2_double()
    gp.rig.cameras = []
    with pytest.raises(CameraError, match="no camera detected"):
        Gphoto2Camera(settings={}, gp_module=gp)
    gp = make_gphoto2_double()
    with pytest.raises(CameraError, match="no port"):
        Gphoto2Camera("usb:009,009", settings={}, gp_module=gp)
    gp = make_gphoto2_double()
    with pytest.raises(CameraError, match="no camera found"):
        Gphoto2Camera("serial:/dev/ttyS0", settings={}, gp_module=gp)
    gp = make_gphoto2_double()
    gp.rig.init_error = GP_ERROR_IO_USB_CLAIM
    with pytest.raises(CameraError, match="busy"):
        Gphoto2Camera(settings={}, gp_module=gp)
    gp = make_gphoto2_double()
    with pytest.raises(CameraError, match="no setting 'whitebalance'"):
        Gphoto2Camera(settings={"whitebalance": "Daylight"}, gp_module=gp)
    assert gp.rig.calls[-1] == ("exit",)  # closed again after the failed configuration
    gp = make_gphoto2_double()
    with pytest.raises(CameraError, match="iso='64' is not one of"):
        Gphoto2Camera(settings={"iso": "64"}, gp_module=gp)
    gp = make_gphoto2_double()
    # case-insensitive
    camera = Gphoto2Camera(settings={"imageformat": "raw"}, timeout_s=0.6, gp_module=gp)
    assert gp.rig.config.get_child_by_name("imageformat").value == "RAW"
    gp.rig.trigger_error = -110  # GP_ERROR_CAMERA_BUSY: triggered again until timeout_s
    with pytest.raises(CameraError, match="camera stayed busy for 0.6 s when triggering frame 0"):
        camera.capture(tmp_path / "z.cr2")
    assert gp.rig.calls.count(("trigger_capture",)) >= 2


def test_gphoto2_missing_library_message(monkeypatch):
    real_import = builtins.__import__

    def no_gphoto2(name, *args, **kwargs):
        if name == "gphoto2":
            raise ImportError("No module named 'gphoto2'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_gphoto2)
    hint = r"in the ps-lab clone, run \.venv/bin/pip install -e '\.\[gphoto2\]'"
    with pytest.raises(CameraError, match=hint):
        Gphoto2Camera(settings={})


@pytest.mark.parametrize(
    "text, seconds",
    [
        ("1/125", 1 / 125),
        ("0.5", 0.5),
        ("2", 2.0),
        ("30s", 30.0),
        ("1/20s", 0.05),
        ('2"', 2.0),
        (0.1, 0.1),
        ("bulb", None),
        ("", None),
        ("0", None),
    ],
)
def test_parse_shutter_speed(text, seconds):
    assert parse_shutter_speed(text) == (pytest.approx(seconds) if seconds else None)


def test_gphoto2_numeric_shortcuts_and_nikon_names(tmp_path, rng):
    gp = make_gphoto2_double()
    Gphoto2Camera(exposure_s=0.05, iso=200, aperture=11, gp_module=gp).close()
    config = gp.rig.config
    assert config.get_child_by_name("shutterspeed").value == "1/20"
    assert config.get_child_by_name("iso").value == "200"
    assert config.get_child_by_name("aperture").value == "11"
    assert config.get_child_by_name("imageformat").value == "RAW"  # default: RAW only

    gp = make_gphoto2_double()
    gp.rig.config = Widget(
        "main",
        GP_WIDGET_WINDOW,
        children={
            "f-number": Widget("f-number", GP_WIDGET_RADIO, "f/4", ["f/4", "f/5.6", "f/8"]),
            "imagequality": Widget(
                "imagequality", GP_WIDGET_RADIO, "JPEG Fine", ["JPEG Fine", "NEF+Fine", "NEF (Raw)"]
            ),
            "shutterspeed": Widget(
                "shutterspeed", GP_WIDGET_RADIO, "1/60", ["1/60", "1/30", "0.5", "1"]
            ),
        },
    )
    camera = Gphoto2Camera(settings={"shutterspeed": "1/2"}, aperture=8.0, gp_module=gp)
    assert gp.rig.config.get_child_by_name("f-number").value == "f/8"
    assert gp.rig.config.get_child_by_name("imagequality").value == "NEF (Raw)"
    assert gp.rig.config.get_child_by_name("shutterspeed").value == "0.5"
    assert camera.exposure_s == 0.5
    camera.close()
    with pytest.raises(CameraError, match="shutterspeed='0.000125' is not one of"):
        Gphoto2Camera(exposure_s=1 / 8000, gp_module=make_gphoto2_double())
