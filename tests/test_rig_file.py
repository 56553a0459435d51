"""Rig files: schema, validation errors that name the key, overrides, the shipped rigs."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from ps_lab.capture.connect import nominal_directions
from ps_lab.capture.rig import (
    apply_overrides,
    comparable_snapshot,
    load_rig,
    parse_light_selection,
    snapshot_differences,
)
from ps_lab.capture.simulated.simulation import build_simulation
from ps_lab.errors import RigError

RIGS = Path(__file__).resolve().parents[1] / "rigs"

MINIMAL = """
name = "tiny"
[controller]
driver = "simulated"
lights = 4
[camera]
driver = "simulated"
exposure_s = 0.05
[scene]
width = 64
height = 48
[[scene.objects]]
kind = "sphere"
center = [32.0, 24.0]
radius = 20.0
"""


def write(tmp_path: Path, text: str, name: str = "rig.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize("name", ["simulated", "simulated-faulty", "arduino-gphoto2"])
def test_shipped_rigs_load_and_snapshot_is_json(name: str) -> None:
    rig = load_rig(RIGS / f"{name}.toml")
    snap = rig.snapshot()
    assert json.loads(json.dumps(snap)) == snap
    assert snap["controller"]["lights"] == rig.n_lights
    assert rig.camera.exposure_s > 0


def test_simulated_rig_meets_the_demo_requirements() -> None:
    rig = load_rig(RIGS / "simulated.toml")
    assert 24 <= rig.n_lights <= 48
    assert rig.scene is not None
    assert abs(rig.scene.width - 320) <= 80 and abs(rig.scene.height - 240) <= 60
    chrome = [o for o in rig.scene.objects if o.kind == "chrome"]
    relief = [o for o in rig.scene.objects if o.kind in ("relief", "sphere")]
    assert len(chrome) == 1 and relief
    assert 50 <= chrome[0].radius <= 60
    # The nominal circle given for calibration is where the chrome sphere really is.
    circle = rig.calibration.chrome_sphere
    assert circle is not None
    assert circle.center == chrome[0].center and circle.radius == chrome[0].radius
    snap = rig.snapshot()
    assert snap["calibration"]["chrome_sphere"] == {
        "center": list(circle.center),
        "radius": circle.radius,
    }


def test_faulty_rig_injects_every_fault_kind_it_names() -> None:
    rig = load_rig(RIGS / "simulated-faulty.toml")
    assert {f.kind for f in rig.faults.controller} >= {"drop", "garble", "delay", "reboot"}
    assert {f.kind for f in rig.faults.camera} == {"timeout", "truncated"}


@pytest.mark.parametrize(
    ("patch", "key"),
    [
        ('[controller]\ndriver = "simulated"\nlights = 4\ncolour = 3\n', "colour"),
        ('bogus = 1\n[controller]\ndriver = "simulated"\nlights = 4\n', "bogus"),
    ],
)
def test_unknown_keys_are_errors_naming_the_key_and_file(
    tmp_path: Path, patch: str, key: str
) -> None:
    text = MINIMAL.replace(
        'name = "tiny"\n[controller]\ndriver = "simulated"\nlights = 4\n', "name = 'tiny'\n" + patch
    )
    path = write(tmp_path, text)
    with pytest.raises(RigError, match=key) as info:
        load_rig(path)
    assert str(path) in str(info.value)
    assert "unknown key" in str(info.value)


def test_unknown_key_in_scene_object_and_fault(tmp_path: Path) -> None:
    path = write(tmp_path, MINIMAL + "shiny = true\n")
    with pytest.raises(RigError, match=r"scene\.objects\[0\]\] shiny: unknown key"):
        load_rig(path)
    path = write(tmp_path, MINIMAL + "[[faults.camera]]\nkind = 'timeout'\nat = 2\nwhen = 3\n")
    with pytest.raises(RigError, match="when: unknown key"):
        load_rig(path)


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("lights = 4", 'lights = "4"', r"\[controller\] lights: expected an integer, got a string"),
        ("lights = 4", "lights = 4.0", r"lights: expected an integer"),
        (
            "exposure_s = 0.05",
            "exposure_s = true",
            r"\[camera\] exposure_s: expected a number, got a boolean",
        ),
        ("exposure_s = 0.05", "exposure_s = -1.0", r"exposure_s: must be >="),
        (
            "center = [32.0, 24.0]",
            "center = [32.0, 24.0, 1.0]",
            r"center: expected a list of 2 numbers",
        ),
        (
            'driver = "simulated"\nlights',
            'driver = "usb"\nlights',
            r"\[controller\] driver: unknown value 'usb'",
        ),
        (
            'driver = "simulated"\nexposure_s',
            'driver = "webcam"\nexposure_s',
            r"\[camera\] driver: unknown value",
        ),
        ("exposure_s = 0.05", "", r"\[camera\] exposure_s: missing"),
        ('kind = "sphere"', 'kind = "cube"', r"kind: unknown value 'cube'"),
        ("radius = 20.0", "radius = 40.0", r"does not fit"),
    ],
)
def test_wrong_values_are_errors_naming_the_key(
    tmp_path: Path, old: str, new: str, message: str
) -> None:
    assert old in MINIMAL
    path = write(tmp_path, MINIMAL.replace(old, new, 1))
    with pytest.raises(RigError, match=message):
        load_rig(path)


FOUR = "[[0, 0, 1], [0, 1, 1], [1, 0, 1], [1, 1, 1]]"


@pytest.mark.parametrize(
    ("lights", "key", "message"),
    [
        ("dome_radius = 1e308", "dome_radius", "must be <="),
        ("dome_radius = nan", "dome_radius", "must be finite"),
        ("dome_radius = 300.0\nled_radius = 1e300", "led_radius", "must be <="),
        ("dome_radius = 300.0\nled_radius = 300.0", "led_radius", "smaller than dome_radius"),
        ("led_radius = -1.0", "led_radius", "must be >="),
        ("max_zenith_deg = inf", "max_zenith_deg", "must be finite"),
        ("intensity_spread = 5.0", "intensity_spread", "must be <="),
        ("intensities = [[1e308, 1, 1], [1, 1, 1], [1, 1, 1], [1, 1, 1]]", "intensities",
         "at most"),
        ("intensities = [[nan, 1, 1], [1, 1, 1], [1, 1, 1], [1, 1, 1]]", r"intensities\[0\]",
         "finite"),
        ("intensities = [[0, 1, 1], [1, 1, 1], [1, 1, 1], [1, 1, 1]]", "intensities",
         "positive"),
        ("intensities = 1.0", "intensities", "expected a list"),
        (f"directions = {FOUR.replace('[0, 0, 1]', '[0, 0, -1]')}", r"directions\[0\]",
         "below the horizon"),
        (f"directions = {FOUR.replace('[0, 0, 1]', '[1, 0, 0]')}", r"directions\[0\]",
         "below the horizon"),
        (f"directions = {FOUR.replace('[0, 0, 1]', '[inf, 0, 1]')}", r"directions\[0\]",
         "finite"),
        (f"directions = {FOUR.replace('[0, 0, 1]', '[0, 0, 0]')}", r"directions\[0\]",
         "zero vector"),
        (f"directions = {FOUR.replace('[0, 0, 1]', '[true, 0, 1]')}", r"directions\[0\]",
         "expected a list of 3 numbers"),
    ],
)
def test_led_section_values_are_errors_naming_the_key(
    tmp_path: Path, lights: str, key: str, message: str
) -> None:
    """Every field of ``[scene.lights]`` (the LEDs), NaN, infinite, huge and wrong-typed."""
    path = write(tmp_path, MINIMAL + "[scene.lights]\n" + lights.replace("\\n", "\n") + "\n")
    with pytest.raises(RigError, match=rf"rig\.toml: \[scene\.lights\] {key}: .*{message}"):
        load_rig(path)


def test_huge_direction_components_are_scaled_not_overflowed(tmp_path: Path) -> None:
    big = FOUR.replace("[0, 0, 1]", "[1e308, 0, 1e308]")
    rig = load_rig(write(tmp_path, MINIMAL + f"[scene.lights]\ndirections = {big}\n"))
    np.testing.assert_allclose(rig.scene.lights.directions[0], [0.5**0.5, 0.0, 0.5**0.5])


def test_missing_directory_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(RigError, match="does not exist"):
        load_rig(tmp_path / "nope.toml")
    with pytest.raises(RigError, match="is a directory"):
        load_rig(tmp_path)
    with pytest.raises(RigError, match="not valid TOML"):
        load_rig(write(tmp_path, "[controller\ndriver = 1\n"))
    with pytest.raises(RigError, match=r"missing table \[camera\]"):
        load_rig(write(tmp_path, '[controller]\ndriver = "simulated"\nlights = 2\n'))


def test_cross_checks(tmp_path: Path) -> None:
    serial = MINIMAL.replace('driver = "simulated"\nlights = 4', 'driver = "serial"\nlights = 4')
    with pytest.raises(RigError, match="port: missing"):
        load_rig(write(tmp_path, serial))
    with_port = serial.replace("lights = 4", 'lights = 4\nport = "/dev/ttyACM0"')
    with pytest.raises(RigError, match="light_state_file"):
        load_rig(write(tmp_path, with_port))
    faulty = with_port.replace(
        "exposure_s = 0.05", 'exposure_s = 0.05\nlight_state_file = "s.json"'
    )
    faulty += "[[faults.controller]]\nkind = 'drop'\nat = 3\n"
    with pytest.raises(RigError, match="simulated controller"):
        load_rig(write(tmp_path, faulty))
    gphoto = MINIMAL.replace('driver = "simulated"\nexposure_s', 'driver = "gphoto2"\nexposure_s')
    with pytest.raises(RigError, match=r"\[scene\] only applies"):
        load_rig(write(tmp_path, gphoto))
    wrong_key = MINIMAL.replace("exposure_s = 0.05", "exposure_s = 0.05\nfolder = '/tmp'")
    with pytest.raises(RigError, match="folder: does not apply to the 'simulated' camera"):
        load_rig(write(tmp_path, wrong_key))
    directions = MINIMAL.replace("lights = 4", "lights = 4\ndirections = [[0, 0, 1]]")
    with pytest.raises(RigError, match="expected 4 directions"):
        load_rig(write(tmp_path, directions))


def test_overrides(tmp_path: Path) -> None:
    rig = load_rig(RIGS / "arduino-gphoto2.toml")
    changed = apply_overrides(rig, port="/dev/ttyUSB3", exposure_s=0.25)
    assert changed.controller.port == "/dev/ttyUSB3" and changed.camera.exposure_s == 0.25
    assert rig.controller.port == "/dev/ttyACM0"  # frozen: the original is untouched
    # The port is a transport detail: a resumed run may use another one; the exposure is not.
    diffs = snapshot_differences(
        comparable_snapshot(rig.snapshot()), comparable_snapshot(changed.snapshot())
    )
    assert diffs == ["camera.exposure_s"]
    with pytest.raises(RigError, match="--exposure"):
        apply_overrides(rig, exposure_s=-1.0)
    simulated = load_rig(write(tmp_path, MINIMAL))
    with pytest.raises(RigError, match="--port applies to a serial controller"):
        apply_overrides(simulated, port="/dev/ttyACM0")


def test_light_selection() -> None:
    assert parse_light_selection("1-3,5", 8) == (1, 2, 3, 5)
    assert parse_light_selection(" 7 , 2-3 ", 8) == (2, 3, 7)
    assert parse_light_selection("1-8", 8) == tuple(range(1, 9))
    for bad in ("0", "9", "a", "3-1", "1,,2", "1-x"):
        with pytest.raises(RigError, match="--lights"):
            parse_light_selection(bad, 8)


def test_simulation_is_seeded_and_follows_the_layout(tmp_path: Path) -> None:
    text = MINIMAL + (
        "[scene.lights]\nseed = 5\nmax_zenith_deg = 40.0\nintensity_spread = 0.2\n"
        "nominal_error_deg = 3.0\n"
    )
    rig = load_rig(write(tmp_path, text))
    a, b = build_simulation(rig), build_simulation(rig)
    np.testing.assert_array_equal(a.light_directions, b.light_directions)
    assert a.light_directions.shape == (4, 3) and a.light_intensities.shape == (4, 3)
    np.testing.assert_allclose(np.linalg.norm(a.light_directions, axis=1), 1.0)
    zenith = np.degrees(np.arccos(a.light_directions[:, 2]))
    assert zenith.max() <= 40.0 + 1e-9
    assert np.all(np.abs(a.light_intensities - 1.0) <= 0.2 + 1e-12)
    nominal = nominal_directions(rig, a)
    assert nominal is not None
    angles = np.degrees(np.arccos(np.clip(np.sum(nominal * a.light_directions, axis=1), -1, 1)))
    np.testing.assert_allclose(angles, 3.0, atol=1e-6)
    other = load_rig(write(tmp_path, text.replace("seed = 5", "seed = 6")))
    assert not np.allclose(build_simulation(other).light_directions, a.light_directions)
    assert math.isclose(rig.scene.lights.max_zenith_deg, 40.0)


def test_scene_objects_are_plain_data_the_simulator_renders_as_given(tmp_path: Path) -> None:
    # The rig keeps [[scene.objects]] as its own plain data (no renderer import); the simulation
    # hands the renderer the same kinds and fields.
    from ps_lab.capture import rig as rig_module
    from ps_lab.render import scene as render_scene

    assert rig_module.OBJECT_KINDS == render_scene.OBJECT_KINDS
    config_fields = [f.name for f in dataclasses.fields(rig_module.SceneObjectConfig)]
    assert config_fields == [f.name for f in dataclasses.fields(render_scene.SceneObject)]
    rig = load_rig(write(tmp_path, MINIMAL))
    scene = build_simulation(rig).scene
    assert len(scene.objects) == len(rig.scene.objects) >= 1
    for given, rendered in zip(rig.scene.objects, scene.objects, strict=True):
        assert isinstance(rendered, render_scene.SceneObject)
        assert dataclasses.astuple(rendered) == dataclasses.astuple(given)


def test_fault_forms_and_gphoto2_settings(tmp_path: Path) -> None:
    text = MINIMAL + (
        "[faults]\nseed = 4\n"
        "controller = [{ kind = 'garble', probability = 0.1 }, { kind = 'silence', at = 30 }]\n"
    )
    rig = load_rig(write(tmp_path, text))
    assert [(f.kind, f.at, f.probability) for f in rig.faults.controller] == [
        ("garble", None, 0.1),
        ("silence", 30, 0.0),
    ]
    with pytest.raises(RigError, match=r"at: missing"):
        load_rig(write(tmp_path, MINIMAL + "[[faults.camera]]\nkind = 'timeout'\n"))
    with pytest.raises(RigError, match=r"probability: unknown key"):
        load_rig(
            write(
                tmp_path,
                MINIMAL + "[[faults.camera]]\nkind = 'timeout'\nat = 2\nprobability = 0.5\n",
            )
        )
    with pytest.raises(RigError, match=r"kind: unknown value 'stop'"):
        load_rig(write(tmp_path, MINIMAL + "[[faults.controller]]\nkind = 'stop'\nat = 2\n"))

    template = (RIGS / "arduino-gphoto2.toml").read_text()
    with_settings = template.replace(
        "# [camera.settings]\n# whitebalance", "[camera.settings]\nwhitebalance"
    ).replace('# imagequality = "RAW"', 'imagequality = "RAW"')
    rig = load_rig(write(tmp_path, with_settings))
    assert dict(rig.camera.settings) == {"whitebalance": "Daylight", "imagequality": "RAW"}
    assert rig.camera_settings()["settings"] == {"imagequality": "RAW", "whitebalance": "Daylight"}
    bad = with_settings.replace('imagequality = "RAW"', "imagequality = [1, 2]")
    with pytest.raises(RigError, match=r"\[camera.settings\] imagequality: expected a string"):
        load_rig(write(tmp_path, bad))


def test_explicit_light_layout(tmp_path: Path) -> None:
    directions = "[[0, 0, 1], [0.5, 0, 1], [0, 0.5, 1], [-0.5, -0.5, 1]]"
    intensities = "[[1, 1, 1], [2, 2, 2], [1, 0.5, 1], [0.8, 0.9, 1]]"
    text = MINIMAL + f"[scene.lights]\ndirections = {directions}\nintensities = {intensities}\n"
    sim = build_simulation(load_rig(write(tmp_path, text)))
    np.testing.assert_allclose(sim.light_directions[1], np.array([0.5, 0, 1]) / np.hypot(0.5, 1))
    np.testing.assert_allclose(sim.light_intensities[2], [1, 0.5, 1])
    with pytest.raises(RigError, match="expected 4 \\[r, g, b\\] rows"):
        load_rig(write(tmp_path, MINIMAL + "[scene.lights]\nintensities = [[1, 1, 1]]\n"))
