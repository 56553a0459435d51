"""ps-lab on a Dask cluster: the same result as in one process, batches, faults.

One module-scoped ``LocalCluster`` of 2 worker processes (one thread each) serves every test; the
captures are tiny (a few hundred pixels cut into ~10 bands), so the time goes into Dask itself.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import dask
import distributed
import numpy as np
import pytest
from helpers.captures import N_LIGHTS, budget_for, write_capture
from helpers.tolerances import (
    assert_within,
    error_summary,
    least_squares,
    light_conditioning,
    rpca_stop,
    scaled_norm,
    stored_float32,
)
from typer.testing import CliRunner

from ps_lab.cli import app
from ps_lab.errors import ClusterError
from ps_lab.io.dataset import load_dataset
from ps_lab.reconstruct import distributed as ps_distributed
from ps_lab.reconstruct._outputs import ERROR_BIN_DEG
from ps_lab.reconstruct.methods import solver
from ps_lab.reconstruct.batch import BatchRow, run_batch, summary_table
from ps_lab.reconstruct.pipeline import ReconstructOptions, reconstruct_to_folder

BUDGET = budget_for(60)  # about 10 bands of the 30 x 26 sphere
# Entries of metrics.json that describe the run, not the result (with a scheduler the bands are
# cut finer when the result allows: LS, L1 and SBL without light refinement do not depend on
# the band plan).
RUN_ENTRIES = ("timings", "solve_seconds", "out", "threads", "streaming")


@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",
        silence_logs=logging.CRITICAL,
    ) as local:
        yield local


@pytest.fixture(scope="module")
def client(cluster):
    with distributed.Client(cluster, set_as_default=False) as connected:
        yield connected


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("distributed") / "sphere"
    write_capture(folder, colour=True)  # colour, a dark frame, intensities, mask, truth
    return folder


def numbers(value, prefix=""):
    """metrics.json flattened to {path: value}, without the entries that describe the run."""
    if isinstance(value, dict):
        items = value.items()
    elif isinstance(value, list):
        items = enumerate(value)
    else:
        return {prefix: value}
    flat = {}
    for key, item in items:
        if str(key) not in RUN_ENTRIES:
            flat.update(numbers(item, f"{prefix}/{key}"))
    return flat


def normal_bound(method: str, dataset: Path) -> float:
    """How far the stored normals of a cluster run and an in-process run may differ.

    The workers run the same compiled kernels on the same bands' numbers, so L1 and SBL pixels
    (and refinement, whose sums add in the in-process band order) are bit-equal. LS solves go
    through BLAS products whose rounding may depend on the band shapes (least squares' rounding),
    and R-PCA's eigen-decompositions through BLAS with the workers' one thread: within its
    stopping rule (tolerances.rpca_stop), with the whole image's scaled observations for a band's.
    """
    if method == "ls":
        return stored_float32(least_squares(N_LIGHTS))
    if method == "rpca":
        data = load_dataset(dataset)
        data_norm = scaled_norm(data.images[:, data.mask], data.valid[:, data.mask])
        rpca = solver("rpca").defaults
        sigma_min = light_conditioning(data.light_directions)[0][0]
        return stored_float32(rpca_stop(rpca["tol"], rpca["rho"], data_norm, sigma_min))
    return 0.0


def assert_same_result(a: Path, b: Path, bound: float = 0.0) -> None:
    """The two result folders agree: normals and albedo within ``bound`` (see normal_bound)."""
    na, nb = np.load(a / "normals.npy"), np.load(b / "normals.npy")
    assert_within(nb, na, bound)
    albedo = np.load(a / "albedo.npy")
    assert_within(np.load(b / "albedo.npy"), albedo, bound * albedo, "albedo")
    for name in ("light_directions.txt", "light_intensities.txt"):
        assert (a / name).exists() == (b / name).exists()
        if (a / name).exists():  # refinement: the in-process band order, bit-equal
            np.testing.assert_array_equal(np.loadtxt(a / name), np.loadtxt(b / name))
    ma = numbers(json.loads((a / "metrics.json").read_text()))
    mb = numbers(json.loads((b / "metrics.json").read_text()))
    assert ma.keys() == mb.keys()
    summary = error_summary(ma["/pixels"], bound, ERROR_BIN_DEG)  # means: sums in band order
    for key, value in ma.items():
        if isinstance(value, float):
            assert mb[key] == pytest.approx(value, **summary), key
        else:
            assert mb[key] == value, key


CASES = [
    ("ls", 0, False),
    ("l1", 0, False),
    ("sbl", 0, False),
    ("rpca", 0, False),
    ("sbl", 2, False),
    ("l1", 1, True),
]


@pytest.mark.numerical
@pytest.mark.parametrize(("method", "refine", "fixed"), CASES)
def test_cluster_result_equals_the_in_process_run(
    capture, cluster, tmp_path, method, refine, fixed
):
    options = ReconstructOptions(
        method=method, refine_lights=refine, fixed_intensities=fixed, memory_budget=BUDGET
    )
    here = reconstruct_to_folder(capture, tmp_path / "here", options)
    there = reconstruct_to_folder(
        capture, tmp_path / "there", options.replace(scheduler=cluster.scheduler_address)
    )
    assert here.metrics["streaming"]["bands"] >= 8
    if method == "rpca" or refine:  # per-band fit or band-ordered sums: the in-process plan
        assert there.metrics["streaming"] == here.metrics["streaming"]
    assert_same_result(tmp_path / "here", tmp_path / "there", normal_bound(method, capture))
    if refine:
        assert len(there.refinement_history) == refine + 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["here", "there"]  # no staging left


@pytest.mark.numerical
def test_one_band_in_process_is_cut_for_the_workers(capture, cluster, tmp_path):
    options = ReconstructOptions(method="sbl")  # 1 GB: one band here
    here = reconstruct_to_folder(capture, tmp_path / "here", options)
    there = reconstruct_to_folder(
        capture, tmp_path / "there", options.replace(scheduler=cluster.scheduler_address)
    )
    assert here.metrics["streaming"]["bands"] == 1
    assert there.metrics["streaming"]["bands"] >= 8  # 4 per worker
    assert_same_result(tmp_path / "here", tmp_path / "there")


@pytest.mark.numerical
def test_a_worker_killed_mid_run_changes_nothing(capture, cluster, client, tmp_path):
    options = ReconstructOptions(method="sbl", refine_lights=1, memory_budget=BUDGET)
    reconstruct_to_folder(capture, tmp_path / "here", options)
    pids = client.run(os.getpid)
    killed = []

    def bars(total, description):
        def advance(n=1, description=None):
            # After the first band of the first solve pass: the other bands are queued or running.
            if n and not killed and description and "band" in description:
                victim = sorted(pids.values())[0]
                os.kill(victim, signal.SIGKILL)
                killed.append(victim)

        return _Bar(advance)

    reconstruct_to_folder(
        capture,
        tmp_path / "there",
        options.replace(scheduler=cluster.scheduler_address),
        progress_bars=bars,
    )
    assert killed
    assert_same_result(tmp_path / "here", tmp_path / "there")
    client.wait_for_workers(2, timeout=60)  # the nanny restarts it, for the next tests
    assert killed[0] not in client.run(os.getpid).values()


class _Bar:
    """A progress bar context manager for tests: yields ``advance``."""

    def __init__(self, advance):
        self.advance = advance

    def __enter__(self):
        return self.advance

    def __exit__(self, *exc):
        return False


def test_ctrl_c_cancels_the_tasks_and_leaves_nothing(capture, cluster, client, tmp_path):
    def bars(total, description):
        def advance(n=1, description=None):
            if n and description and "band" in description:
                raise KeyboardInterrupt

        return _Bar(advance)

    options = ReconstructOptions(memory_budget=BUDGET, scheduler=cluster.scheduler_address)
    with pytest.raises(KeyboardInterrupt):
        reconstruct_to_folder(capture, tmp_path / "out", options, progress_bars=bars)
    assert list(tmp_path.iterdir()) == []

    def tasks_left(dask_scheduler):
        return [key for key in dask_scheduler.tasks if "ps-lab-band" in str(key)]

    deadline = time.monotonic() + 10
    while client.run_on_scheduler(tasks_left) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert client.run_on_scheduler(tasks_left) == []


def test_a_lost_scheduler_is_one_error_and_no_output(capture, tmp_path):
    lonely = distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, dashboard_address=":0", silence_logs=logging.CRITICAL
    )

    def bars(total, description):
        def advance(n=1, description=None):
            if n and description and "band" in description and lonely.status.name == "running":
                lonely.close()

        return _Bar(advance)

    options = ReconstructOptions(memory_budget=BUDGET, scheduler=lonely.scheduler_address)
    with pytest.raises(ClusterError, match="lost the Dask scheduler"):
        reconstruct_to_folder(capture, tmp_path / "out", options, progress_bars=bars)
    assert list(tmp_path.iterdir()) == []


def test_no_scheduler_at_the_address_is_one_error_line(capture, tmp_path):
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        result = CliRunner().invoke(
            app,
            ["reconstruct", str(capture), "--out", str(tmp_path / "out"),
             "--scheduler", "tcp://127.0.0.1:9"],  # fmt: skip
        )
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "--scheduler tcp://127.0.0.1:9: no Dask scheduler" in lines[0]
    assert list(tmp_path.iterdir()) == []


def test_without_dask_scheduler_and_batch_say_how_to_install(capture, tmp_path, monkeypatch):
    monkeypatch.setattr(ps_distributed, "_dask", None)
    for args in (
        ["reconstruct", str(capture), "--out", str(tmp_path / "o"), "--scheduler", "tcp://x:1"],
        ["batch", str(capture), "--out-root", str(tmp_path / "r")],
    ):
        result = CliRunner().invoke(app, args)
        assert result.exit_code == 2
        assert result.output.strip() == (
            "error: Dask is not installed: in the ps-lab clone, run "
            ".venv/bin/pip install -e '.[distributed]'"
        )
    assert list(tmp_path.iterdir()) == []


def test_reconstruct_without_a_scheduler_does_not_import_dask(capture, tmp_path):
    script = (
        "import sys; from ps_lab.cli import main\n"
        "try:\n"
        f"    main(['reconstruct', {str(capture)!r}, '--method', 'ls', "
        f"'--out', {str(tmp_path / 'out')!r}])\n"
        "except SystemExit as exit:\n"
        "    assert not exit.code, exit.code\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed')))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]"


# --- batches ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def three(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("batch")
    folders = []
    for seed in range(3):
        write_capture(root / f"sphere{seed}", seed=seed)
        folders.append(root / f"sphere{seed}")
    return folders


def test_a_batch_of_three_datasets(three, cluster, tmp_path):
    options = ReconstructOptions(method="l1")
    rows = run_batch(three, tmp_path, options, scheduler=cluster.scheduler_address)
    assert [row.status for row in rows] == ["done"] * 3
    for folder, row in zip(three, rows, strict=True):
        assert row.out == tmp_path / folder.name
        reconstruct_to_folder(folder, tmp_path / "here" / folder.name, options)
        assert_same_result(tmp_path / "here" / folder.name, row.out)
        assert row.pixels > 0 and row.seconds > 0 and 0 < row.error_deg < 10
    again = run_batch(three, tmp_path, options, scheduler=cluster.scheduler_address)
    assert [row.status for row in again] == ["skipped"] * 3
    assert [row.error_deg for row in again] == [row.error_deg for row in rows]


def test_a_failing_dataset_does_not_stop_the_batch(three, tmp_path):
    broken = tmp_path / "data" / "broken"
    write_capture(broken, seed=7)
    (broken / "003.png").write_bytes(b"not a picture")
    datasets = [three[0], broken, three[1]]
    result = CliRunner().invoke(
        app,
        ["batch", *map(str, datasets), "--out-root", str(tmp_path / "out"), "--method", "ls",
         "--workers", "2"],  # fmt: skip  (no --scheduler: its own local cluster)
    )
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert lines[0].split() == ["dataset", "pixels", "seconds", "error", "(deg)", "status"]
    assert lines[1].endswith("done") and lines[3].endswith("done")
    assert "failed:" in lines[2] and "003.png" in lines[2]
    assert lines[-1].startswith("error: 1 of 3 datasets failed: ") and "003.png" in lines[-1]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["sphere0", "sphere1"]


def test_summary_table_lines_up():
    rows = [
        BatchRow(Path("a"), Path("o/a"), "done", 1200, 3.25, 0.5),
        BatchRow(Path("long/name"), Path("o/name"), "failed", message="boom"),
    ]
    table = summary_table(rows).splitlines()
    assert table[1].split() == ["a", "1200", "3.2", "0.50", "done"]
    assert table[2].split() == ["long/name", "-", "-", "-", "failed:", "boom"]
    end = table[0].index("pixels") + len("pixels")  # numbers right-aligned under their heading
    assert table[1].index("1200") + 4 == end and table[2].index("-") + 1 == end


def test_batch_takes_the_solver_options_of_reconstruct(three, cluster, tmp_path):
    result = CliRunner().invoke(
        app,
        ["batch", str(three[0]), "--out-root", str(tmp_path), "--scheduler",
         cluster.scheduler_address, "--max-iter", "7", "--tol", "1e-3"],  # fmt: skip
    )
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "sphere0" / "metrics.json").read_text())
    assert metrics["solver_options"]["max-iter"] == 7
    assert metrics["solver_options"]["tol"] == 1e-3
    assert metrics["iterations"]["max"] <= 7


def test_a_result_made_with_other_options_is_kept_and_named(three, cluster, tmp_path):
    # Issue 21: `--method ls` into a root of default results used to report `skipped`, silently.
    root = tmp_path / "results"
    address = ["--scheduler", cluster.scheduler_address]
    first = CliRunner().invoke(app, ["batch", str(three[0]), "--out-root", str(root), *address])
    assert first.exit_code == 0, first.output
    sbl = (root / "sphere0" / "metrics.json").read_text()
    again = CliRunner().invoke(
        app, ["batch", str(three[0]), "--out-root", str(root), "--method", "ls", *address]
    )
    assert again.exit_code == 0, again.output
    lines = again.output.strip().splitlines()
    assert lines[1].endswith("kept: made with --method auto (asked ls)"), again.output
    assert lines[-1] == (
        f"warning: {three[0]}: kept the result in {root / 'sphere0'}, made with other options: "
        "--method auto (asked ls); --overwrite replaces it (or choose another --out-root)"
    )
    assert (root / "sphere0" / "metrics.json").read_text() == sbl
    same = CliRunner().invoke(app, ["batch", str(three[0]), "--out-root", str(root), *address])
    assert same.exit_code == 0 and "warning" not in same.output
    assert same.output.strip().splitlines()[1].endswith("skipped")
    replaced = CliRunner().invoke(
        app,
        ["batch", str(three[0]), "--out-root", str(root), "--method", "ls", "--overwrite",
         *address],  # fmt: skip
    )
    assert replaced.exit_code == 0, replaced.output
    assert replaced.output.strip().splitlines()[1].endswith("done")
    assert json.loads((root / "sphere0" / "metrics.json").read_text())["method"] == "ls"


def test_option_differences_compare_what_metrics_json_records():
    from ps_lab.reconstruct.batch import option_differences

    stored = {
        "method": "sbl", "channel": "mean", "shadow_threshold": None, "light_model": "near",
        "solver_options": {"lambda": None, "sigma-x2": None, "max-iter": 7, "tol": None},
        "refinement": {"iterations": 2}, "depth": {"method": "poisson"},
    }  # fmt: skip
    same = ReconstructOptions(
        method="sbl", max_iter=7, refine_lights=2, threads=3, memory_budget="2GB"
    )
    assert option_differences(stored, same) == []
    assert option_differences(stored, same.replace(depth="poisson", lights="near")) == []
    other = ReconstructOptions(
        method="l1", channel="r", shadow_threshold=0.01, tol=1e-3, lights="directional",
        depth="bilateral",
    )  # fmt: skip
    assert option_differences(stored, other) == [
        "--method sbl (asked l1)",
        "--channel mean (asked r)",
        "--shadow-threshold default (asked 0.01)",
        "--max-iter 7 (asked default)",
        "--tol default (asked 0.001)",
        "--lights near (asked directional)",
        "--refine-lights 2 (asked 0)",
        "--depth poisson (asked bilateral)",
    ]
    assert option_differences({"method": "sbl"}, ReconstructOptions(method="sbl")) == []
    refined = {"method": "sbl", "fixed_intensities": True, "refinement": {"iterations": 2}}
    assert option_differences(refined, ReconstructOptions(method="sbl", refine_lights=2)) == [
        "--fixed-intensities on (asked off)"
    ]


def test_a_workers_warning_is_said_once_as_a_warning_line_naming_its_dataset(three, tmp_path):
    # a worker process has no terminal: its warnings came out bare (Python's last-resort
    # handler, no "warning:"); now the row carries them and the batch says them
    dark = tmp_path / "data" / "dark"
    write_capture(dark, seed=3)
    for picture in sorted(dark.glob("0*.png")):
        image = cv2.imread(str(picture), cv2.IMREAD_UNCHANGED)
        image[: image.shape[0] // 2] = 0  # the top half unlit under every light
        cv2.imwrite(str(picture), image)
    done = subprocess.run(
        [sys.executable, "-m", "ps_lab", "batch", str(three[0]), str(dark), "--out-root",
         str(tmp_path / "out"), "--method", "ls", "--workers", "2"],
        capture_output=True, text=True, env={**os.environ, "NO_COLOR": "1"},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(f"warning: {dark}") and "could not be solved" in lines[0]
