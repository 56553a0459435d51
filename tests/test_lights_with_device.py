"""Opt-in tests on a real light controller.

Run ``pytest tests/test_lights_with_device.py --rig-port /dev/ttyACM0``.

Set ``PS_LAB_RIG_LIGHTS`` when the board has other than 12 lights (the sketch's default pin table).
"""

from __future__ import annotations

import os

import pytest

from ps_lab.capture.light_controllers import LightState, SerialLightController, walk_lights
from ps_lab.errors import RigError


@pytest.fixture
def controller(request):
    port = request.config.getoption("--rig-port")
    if not port:
        pytest.skip("needs --rig-port")
    lights = int(os.environ.get("PS_LAB_RIG_LIGHTS", "12"))
    with SerialLightController(port, lights, reply_timeout=0.5) as controller:
        yield controller


def test_every_light_alone(controller):
    walk_lights(controller, dwell_s=0.2)
    assert controller.state() == LightState(frozenset(), 255)


def test_sets_and_levels(controller):
    controller.set_level(30)
    controller.switch({1, controller.count})
    assert controller.state() == LightState(frozenset({1, controller.count}), 30)
    controller.set_level(255)
    controller.all_off()
    assert controller.state().lit == frozenset()


def test_out_of_range_is_refused_before_sending(controller):
    with pytest.raises(RigError, match="out of range"):
        controller.switch(controller.count + 1)


def test_reopen_after_close(controller, request):
    controller.close()
    with SerialLightController(request.config.getoption("--rig-port"), controller.count) as again:
        again.switch(1)
        assert again.state().lit == {1}
