"""Shared test configuration: opt-in hardware tests and common fixtures."""

from __future__ import annotations

import numpy as np
import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--rig-port", default=None, help="serial port of a real light controller")
    parser.addoption("--camera", default=None, help="run real-camera tests (gphoto2) with this port")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # Hardware tests live in *_with_device.py and run only when a device option is given.
    has_device = config.getoption("--rig-port") or config.getoption("--camera")
    skip = pytest.mark.skip(reason="needs hardware: pass --rig-port or --camera")
    for item in items:
        if item.fspath.basename.endswith("_with_device.py"):
            item.add_marker(pytest.mark.device)
            if not has_device:
                item.add_marker(skip)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
