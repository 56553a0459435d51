"""``ps-lab batch`` with schedulers that are not, a bad ``--out-root`` and a failing dataset.

Refused within seconds in one ``error:`` line naming the option or the failing dataset; SIGTERM
counts the finished datasets.
"""

from __future__ import annotations

import shutil
import signal
import socket
import time
from collections.abc import Callable

from helpers.bad_input import NOT_UTF8, CaseTable, Workspace, finish, has, run, succeeded
from helpers.hostile import Result, assert_one_error_line, start, temporary_leftovers, wait_until


CASES = CaseTable()
case = CASES.case


@case("s3-batch-not-utf8", (), code=0, check=succeeded)
def _(w):
    return ["batch", str(w.copy("png", NOT_UTF8)), "--out-root", str(w.root / NOT_UTF8 / "x"),
            "--workers", "1"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _quick(seconds: float) -> Callable[[Workspace, Result], None]:
    def check(w: Workspace, result: Result, line: str | None) -> None:
        assert w.notes["seconds"] < seconds, f"took {w.notes['seconds']:.1f} s"

    return check


@case("s6-batch-scheduler-port-not-a-number", ("--scheduler",), check=_quick(15), timeout=60)
def _(w):
    return ["batch", str(w.copy("png")), "--out-root", str(w.root / "results"),
            "--scheduler", "tcp://127.0.0.1:notaport"]


@case("s6-batch-scheduler-unreachable", ("--scheduler",), check=_quick(15), timeout=60)
def _(w):
    return ["batch", str(w.copy("png")), "--out-root", str(w.root / "results"),
            "--scheduler", f"tcp://127.0.0.1:{_free_port()}"]


@case("s6-batch-out-root-is-a-file", lambda w: ("--out-root",),
      check=lambda w, r, line: has(r.lines[0], str(w.root / "taken")))
def _(w):
    (w.root / "taken").write_text("mine")
    return ["batch", str(w.copy("png")), "--out-root", str(w.root / "taken"), "--workers", "1"]


def _failed_dataset_named(w: Workspace, result: Result, line: str | None) -> None:
    has(result.lines[0], str(w.root / "broken" / "003.png"))
    results = w.root / "results"
    assert sorted(p.name for p in results.iterdir()) == ["png"]  # nothing of "broken"
    assert (results / "png" / "metrics.json").is_file()
    shutil.rmtree(results)  # the good dataset's result is expected: not part of the snapshot


@case("s6-batch-names-the-failing-dataset", ("broken",), check=_failed_dataset_named)
def _(w):
    broken = w.copy("png", "broken")
    (broken / "003.png").write_bytes(b"not a png")
    return ["batch", str(w.copy("png")), str(broken), "--out-root", str(w.root / "results"),
            "--workers", "1"]


def test_sigterm_during_batch_counts_the_finished_datasets(templates, tmp_path) -> None:
    home, root = tmp_path / "home", tmp_path / "case"
    home.mkdir()
    root.mkdir()
    datasets = []
    for k in range(4):
        shutil.copytree(templates["png"], root / f"ds{k}")
        datasets.append(str(root / f"ds{k}"))
    results = root / "results"
    proc, out, err = start(["batch", *datasets, "--out-root", str(results), "--workers", "1",
                            "--method", "sbl", "--refine-lights", "30"], root, home)
    wait_until(lambda: (results / "ds0" / "metrics.json").exists(), proc, timeout=120)
    proc.send_signal(signal.SIGTERM)
    result = finish(proc, out, err, timeout=120)
    line = assert_one_error_line(result, ("interrupted",), code=130)
    finished = [p.name for p in results.iterdir() if (p / "metrics.json").is_file()]
    assert f"{len(finished)} of 4 datasets finished" in line, (line, finished)
    hidden = [p.name for p in results.iterdir() if p.name.startswith(".")]
    assert not hidden, hidden  # the stopped worker's staging removed by the cluster's shutdown


def test_a_service_that_is_not_a_scheduler_is_one_line_within_seconds(templates, tmp_path) -> None:
    """A TCP port that accepts but never speaks Dask (Dask's client alone would wait forever)."""
    home, root = tmp_path / "home", tmp_path / "case"
    home.mkdir()
    root.mkdir()
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(4)  # the kernel accepts; nobody ever sends a byte
        address = f"tcp://127.0.0.1:{silent.getsockname()[1]}"
        started = time.monotonic()
        result = run(["batch", str(templates["png"]), "--out-root", str(root / "results"),
                      "--scheduler", address], root, home, timeout=90)
        seconds = time.monotonic() - started
    line = assert_one_error_line(result, ("--scheduler",))
    assert "not a Dask scheduler" in line, line
    assert seconds < 20, f"took {seconds:.1f} s"
    assert not any(root.iterdir()) and not temporary_leftovers(home)


#: The cases CI runs; ``pytest -m slow`` runs every case of the table.
CI_CASES = {
    "s6-batch-out-root-is-a-file",
    "s6-batch-scheduler-port-not-a-number",
    "s6-batch-scheduler-unreachable",
}
test_bad_input = CASES.test(CI_CASES)
