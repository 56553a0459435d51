"""Shared test configuration: opt-in hardware tests and common fixtures."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

# The shared checks (tests/helpers/) report failures as the tests' own asserts do.
pytest.register_assert_rewrite("helpers")

from helpers.bad_input import Case, Outcome, Templates, Workspace, run_cases  # noqa: E402

from ps_lab.capture.simulated.avr_firmware import (  # noqa: E402
    build_harness,
    build_sketch,
    missing_packages,
)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--rig-port", default=None, help="serial port of a real light controller")
    parser.addoption("--camera", default=None, help="run real-camera tests (gphoto2) with this port")


def _slow_selected(config: pytest.Config) -> bool:
    expression = config.getoption("-m") or ""
    return "slow" in expression and "not slow" not in expression


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # Hardware tests live in *_with_device.py and run only when a device option is given.
    has_device = config.getoption("--rig-port") or config.getoption("--camera")
    skip_device = pytest.mark.skip(reason="needs hardware: pass --rig-port or --camera")
    # Long experiments run only when asked for (`make test-slow`, i.e. `pytest -m slow`); CI runs
    # their reduced versions, which are ordinary tests.
    skip_slow = pytest.mark.skip(reason="long experiment: run with -m slow")
    run_slow = _slow_selected(config)
    for item in items:
        if item.fspath.basename.endswith("_with_device.py"):
            item.add_marker(pytest.mark.device)
            if not has_device:
                item.add_marker(skip_device)
        if "slow" in item.keywords and not run_slow:
            item.add_marker(skip_slow)


@pytest.hookimpl(trylast=True)
def pytest_collection_finish(session: pytest.Session) -> None:
    # Compile (or load) every numba kernel for this CPU target (NUMBA_CPU_NAME included) before
    # the first test, into the cache the tests' subprocesses read: with an empty cache a test
    # would otherwise pay a minute or more of compiling against its timeout.
    if session.config.option.collectonly or not session.items:
        return
    from ps_lab.reconstruct._warm_up import cache_folder, warm_all

    reporter = session.config.pluginmanager.get_plugin("terminalreporter")

    def say(line: str) -> None:
        if reporter is not None:
            reporter.write_line(line)

    started = time.perf_counter()
    compiled = warm_all(say)
    if compiled:
        say(f"compiled {len(compiled)} numba kernels in {time.perf_counter() - started:.0f} s "
            f"before the first test (cache: {cache_folder()})")


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def firmware_cache(tmp_path_factory) -> Path:
    """Build the Arduino sketch and the simavr harness once; return the cache (``PS_LAB_CACHE``).

    Skips, naming the Debian packages, where the toolchain is not installed (`.ci/run` installs
    it); nothing else skips these tests.
    """
    missing = " ".join(missing_packages())
    if missing:
        pytest.skip(
            f"the emulated firmware needs Debian packages: {missing} (apt-get install {missing})"
        )
    cache = tmp_path_factory.mktemp("ps-lab-cache")
    build_sketch(build_dir=cache / "firmware")
    build_harness(build_dir=cache / "firmware")
    return cache


# --- the bad-input tables (tests/helpers/bad_input.py) -------------------------------------------


@pytest.fixture(scope="session")
def templates(tmp_path_factory) -> Templates:
    """The small inputs the bad-input cases copy, each made once, when first asked for."""
    return Templates(tmp_path_factory.mktemp("templates"), tmp_path_factory.mktemp("home"))


@pytest.fixture
def workspace(tmp_path, templates) -> Workspace:
    home = tmp_path / "home"
    home.mkdir()
    root = tmp_path / "case"
    root.mkdir()
    return Workspace(root, home, templates)


@pytest.fixture(scope="module")
def bad_input_outcomes(request, templates, tmp_path_factory) -> dict[str, Outcome]:
    """Run every selected case of this test module's bad-input tables at once, a few commands in
    parallel.

    Each command is a separate process that mostly imports and reads; running them side by side
    keeps the tables' wall time near their CPU time divided by the cores. Per module, not per
    session: with the tests spread over processes (pytest-xdist, a file to a worker), each
    worker runs the cases of the files it was given, not every file's.
    """
    chosen = [
        value
        for item in request.session.items
        if getattr(item, "module", None) is request.module
        and hasattr(item, "callspec") and not item.get_closest_marker("skip")
        for value in item.callspec.params.values()
        if isinstance(value, Case)
    ]
    return run_cases(chosen, templates, tmp_path_factory)
