"""``ps-lab rig serve-sim`` and ``serve-firmware`` run as a user runs them: the path they print."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

from ps_lab.capture.light_controllers import LightState, SerialLightController
from ps_lab.capture.simulated.pty_server import state_file_reader


def switch_through_served_device(
    args: list[str], state_file: Path, lights: int, driver: dict, *, wait_s: float,
    env: dict[str, str] | None = None,
) -> Callable[[], LightState]:  # fmt: skip
    """Run ``python -m ps_lab rig ARGS --state-file STATE_FILE``, light 2 through the device path it
    prints (the state file follows), stop it with SIGTERM: exit 0 and the state file removed.

    Returns the state file's reader (which now raises: the server is gone).
    """
    process = subprocess.Popen(
        [sys.executable, "-m", "ps_lab", "rig", *args, "--state-file", str(state_file)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        ready, _, _ = select.select([process.stdout], [], [], wait_s)
        assert ready, f"{args[0]} printed no device path"
        path = process.stdout.readline().strip()
        assert path.startswith("/dev/") and os.path.exists(path)
        read_state = state_file_reader(state_file)
        with SerialLightController(path, lights, **driver) as controller:
            controller.switch(2)
            assert read_state() == LightState(frozenset({2}), 255)
        assert read_state().lit == frozenset()
    finally:
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=30)
    assert process.returncode == 0, err
    assert not state_file.exists()
    return read_state
