"""``ps-lab calibrate`` given what it cannot use, and stopped by a signal.

Spheres, ROIs and lens numbers that are negative, NaN or off the image; runs without a chrome
sphere, with a missing frame or a manifest that is not JSON; a near rig's absent second sphere;
``--outline-frame`` black, noisy, the wrong size or unreadable. Exit 2 (130 for a signal), one
``error:`` line naming the file or option, nothing created or changed.
"""

from __future__ import annotations

import os
import shutil
import signal
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers.bad_input import (
    NOT_UTF8,
    CaseTable,
    ds_name,
    finish,
    has,
    lacks,
    named,
    succeeded,
)
from helpers.hostile import _alive, assert_one_error_line, snapshot, start


CASES = CaseTable()
case = CASES.case
option_case = CASES.option_case


# Group 2: numbers that reach the maths unchecked ----------------------------------------------


def calibrate_case(id: str, option: str, value: str, extra: tuple[str, ...] = ()):
    @case(id, (option,))
    def _(w):
        return ["calibrate", str(w.copy("run")), option, value, *extra]


calibrate_case("g2-sphere-negative-radius", "--sphere", "100,100,-5")
calibrate_case("g2-sphere-zero-radius", "--sphere", "40,40,0")
calibrate_case("g2-sphere-nan", "--sphere", "nan,40,30")
calibrate_case("g2-sphere-inf-radius", "--sphere", "40,40,inf")
calibrate_case("g2-sphere-outside-image", "--sphere", "1e9,1e9,30")
calibrate_case("g2-sphere-two-numbers", "--sphere", "40,40")
calibrate_case("g2-roi-negative-width", "--roi", "0,0,-10,50")
calibrate_case("g2-roi-zero", "--roi", "0,0,0,0")
calibrate_case("g2-roi-nan", "--roi", "nan,0,50,50")
calibrate_case("g2-roi-outside-image", "--roi", "5000,5000,50,50")
calibrate_case("g2-matte-negative-radius", "--matte", "40,90,-3")
calibrate_case("g2-focal-length-zero", "--focal-length", "0", ("--pixel-pitch", "4"))
calibrate_case("g2-pixel-pitch-zero", "--pixel-pitch", "0", ("--focal-length", "50"))
calibrate_case("g2-focal-length-negative", "--focal-length", "-50", ("--pixel-pitch", "4"))
calibrate_case("g2-focal-length-nan", "--focal-length", "nan", ("--pixel-pitch", "4"))
calibrate_case("g2-safe-radius-nan", "--safe-radius", "nan")


@case("g4-no-chrome-sphere", ds_name)
def _(w):
    return ["calibrate", str(w.png())]


option_case("g5-safe-radius-above-max", ["calibrate"], "--safe-radius", "2", where="run")


@case("g6-calibrate-fails-after-progress-bar", lambda w: (str(w.root / "png"),))
def _(w):
    ds = w.png()
    return ["calibrate", str(ds), "--roi", "0,0,16,16"]


@case("x-manifest-not-json", ("manifest.json",))
def _(w):
    run_dir = w.copy("run")
    (run_dir / "manifest.json").write_text("{ not json")
    return ["calibrate", str(run_dir)]


@case("x-run-frame-missing", ("frames",))
def _(w):
    run_dir = w.copy("run")
    frame = sorted((run_dir / "frames").iterdir())[-1]
    frame.unlink()
    return ["calibrate", str(run_dir)]


@case("x-calibrate-one-image", ("light", "image", "frame"))
def _(w):
    ds = w.root / "one"
    ds.mkdir()
    shutil.copy(w.templates["png"] / "001.png", ds / "001.png")
    return ["calibrate", str(ds)]


@pytest.mark.parametrize(
    "sig",
    [signal.SIGTERM, pytest.param(signal.SIGHUP, marks=pytest.mark.slow)],
    ids=lambda s: s.name,
)
def test_signal_during_calibrate(sig, workspace) -> None:
    # The small run's frames can all be read between two 5 ms polls; a calibration that ends
    # (successfully) before the signal is sent is run again on a fresh copy, up to 5 times.
    for attempt in range(5):
        run_dir = workspace.copy("run", f"run{attempt}")
        before = snapshot(workspace.root)
        proc, out, err = start(["calibrate", str(run_dir)], workspace.root, workspace.home)

        def reading_frames(proc=proc, run_dir=run_dir) -> bool:
            try:
                return any(
                    str(run_dir) in os.readlink(fd)
                    for fd in Path(f"/proc/{proc.pid}/fd").iterdir()
                )
            except OSError:
                return False

        deadline = time.monotonic() + 90
        while not reading_frames() and _alive(proc.pid):
            assert time.monotonic() < deadline, "timed out waiting for the command to get going"
            time.sleep(0.005)
        if not _alive(proc.pid):
            done = finish(proc, out, err, timeout=60)
            assert done.code == 0, done.stderr  # ended before the signal: only by finishing
            continue
        proc.send_signal(sig)
        result = finish(proc, out, err, timeout=60)
        assert_one_error_line(result, ("interrupted",), code=130)
        assert snapshot(workspace.root) == before
        return
    pytest.fail("calibrate finished before the signal could be sent, 5 times")


@case("s3-calibrate-run-not-utf8", (), code=0, check=succeeded)
def _(w):
    return ["calibrate", str(w.copy("run", NOT_UTF8))]


@case("s6-calibrate-near-rig-second-sphere-absent", ("manifest.json",),
      check=lambda w, r, line: has(r.lines[0], "sphere 2"))
def _(w):
    return ["calibrate", str(w.copy("near"))]


@case("s6-calibrate-sphere-on-bare-table", ("--sphere",),
      check=lambda w, r, line: lacks(r.lines[0], "light 2"))
def _(w):
    return ["calibrate", str(w.copy("run")), "--sphere", "20,100,15"]


# o: calibrate --outline-frame


def _outline_case(id: str, write: Callable[[Path], None]):
    @case(id, named("outline.png"), timeout=180, quiet_stdout=True)
    def _(w):
        run_folder = w.copy("run")
        write(w.root / "outline.png")
        return ["calibrate", str(run_folder), "--outline-frame", str(w.root / "outline.png"),
                "--out", str(w.root / "out")]  # fmt: skip


_outline_case("o-outline-frame-black", lambda p: cv2.imwrite(str(p), np.zeros((120, 160), np.uint8)))
_outline_case("o-outline-frame-dark-noise", lambda p: cv2.imwrite(
    str(p), np.random.default_rng(1).integers(0, 3, (120, 160)).astype(np.uint8)))
_outline_case("o-outline-frame-wrong-size", lambda p: cv2.imwrite(
    str(p), np.full((60, 80), 128, np.uint8)))
_outline_case("o-outline-frame-unreadable", lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(9)))


# --- the outline frame, in one process -----------------------------------------------------------


def test_outline_frame_is_used_when_sound_and_named_when_not(rng):
    from ps_lab.calibration import calibrate, summary_image
    from ps_lab.errors import CalibrationError
    from ps_lab.render import random_light_directions, render_chrome_sphere

    shape, centre, radius = (120, 160), (60.3, 58.1), 40.0
    lights = random_light_directions(8, rng, max_zenith_deg=40.0)
    frames = render_chrome_sphere(shape, centre, radius, lights, ambient=1.0)
    sound = calibrate(frames, outline=summary_image(frames), outline_name="ref.png")
    assert sound.outline_source == "outline frame"
    assert np.hypot(sound.circle.x - centre[0], sound.circle.y - centre[1]) < 0.5
    for frame, reason in ((np.zeros(shape), " is black"), (np.full(shape, 0.3), " is blank"),
                          (rng.uniform(0, 0.01, shape), ": ")):  # fmt: skip
        with pytest.raises(CalibrationError) as refused:
            calibrate(frames, outline=frame, outline_name="ref.png")
        assert str(refused.value).startswith(f"ref.png{reason}"), str(refused.value)


#: The cases CI runs; ``pytest -m slow`` runs every case of the table.
CI_CASES = {
    "g2-focal-length-zero",
    "g2-roi-nan",
    "g2-sphere-nan",
    "g2-sphere-negative-radius",
    "g4-no-chrome-sphere",
    "g6-calibrate-fails-after-progress-bar",
    "o-outline-frame-black",
    "s3-calibrate-run-not-utf8",
    "s6-calibrate-near-rig-second-sphere-absent",
    "s6-calibrate-sphere-on-bare-table",
}
test_bad_input = CASES.test(CI_CASES)
