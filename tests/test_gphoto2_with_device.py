"""Real-camera checks (opt-in): `pytest tests/test_gphoto2_with_device.py --camera usb:001,004`.

Pass ``--camera auto`` to use the first camera gphoto2 detects. The camera must be set to shoot
RAW (or RAW+JPEG); the test takes two frames and loads them linearly. conftest skips this file
unless ``--camera`` (or ``--rig-port``) is given.
"""

from __future__ import annotations

import numpy as np
import pytest

from ps_lab.capture.gphoto2_camera import Gphoto2Camera
from ps_lab.io.raw import load_raw


@pytest.fixture
def camera(request):
    port = request.config.getoption("--camera")
    if port is None:
        pytest.skip("no --camera given")
    pytest.importorskip("gphoto2")
    with Gphoto2Camera(None if port == "auto" else port, settings={}, timeout_s=30.0) as cam:
        yield cam


def test_two_frames_arrive_and_load_linearly(camera, tmp_path):
    # LibRaw identifies the format by content, so a CR2/NEF saved under a .dng name still loads.
    frames = [camera.capture(tmp_path / f"frame{i}.dng", label=f"test frame {i}") for i in range(2)]
    for frame in frames:
        assert frame.path.stat().st_size > 100_000
        assert frame.finished >= frame.started
        image = load_raw(frame.path)
        assert image.image.ndim == 3 and image.image.shape[2] == 3
        assert np.isfinite(image.image).all()
        assert image.white_level > image.black_level.max()
    assert frames[1].started >= frames[0].finished
