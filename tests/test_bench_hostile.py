"""``ps-lab bench`` pointed at something that is not a benchmark's input (issue 43).

A folder the user named that is missing, a file, or holds no capture; a capture with too few
lights to hold one out; a ``--json`` path in a missing folder or onto a folder: each is refused
before any work (nothing printed on stdout, nothing written), exit 2, one ``error:`` line naming
the path or the option. Only the default shared-data folder, when absent, is skipped with a
message. ``--json`` holds strict JSON (no NaN).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from helpers.bad_input import CaseTable
from helpers.hostile import (
    assert_one_error_line,
    assert_quiet,
    run,
    snapshot,
)

from ps_lab.commands.bench import finite_json


@pytest.fixture(scope="session")
def captures(tmp_path_factory) -> Path:
    """``few`` (5 lights: none can be held out of eight folds) and ``ok`` (9 lights), 16x16."""
    root = tmp_path_factory.mktemp("bench")
    for name, lights in (("few", "5"), ("ok", "9")):
        result = run(["simulate", str(root / name), "--size", "16", "--lights", lights], root,
                     root / "home")
        assert result.code == 0, result.stderr
    return root


@dataclass(frozen=True)
class Case:
    id: str
    args: Callable[[Path, Path], list[str]]  # (case folder, captures) -> arguments
    names: Callable[[Path, Path], tuple[str, ...]]


def _file(w: Path) -> Path:
    (w / "notes.txt").write_text("not a capture\n")
    return w / "notes.txt"


def _empty(w: Path) -> Path:
    (w / "empty").mkdir()
    return w / "empty"


CASES = [
    Case("relight missing folder", lambda w, c: ["relight", str(w / "nowhere")],
         lambda w, c: (str(w / "nowhere"),)),
    Case("relight a file", lambda w, c: ["relight", str(_file(w))],
         lambda w, c: (str(w / "notes.txt"),)),
    Case("relight empty folder", lambda w, c: ["relight", str(_empty(w))],
         lambda w, c: (str(w / "empty"),)),
    Case("relight too few lights", lambda w, c: ["relight", str(c / "few")],
         lambda w, c: (str(c / "few"),)),
    Case("relight json in missing folder",
         lambda w, c: ["relight", str(c / "ok"), "--json", str(w / "no" / "out.json")],
         lambda w, c: ("--json",)),
    Case("relight json onto a folder",
         lambda w, c: ["relight", str(c / "ok"), "--json", str(_empty(w))],
         lambda w, c: ("--json",)),
    Case("real missing folder", lambda w, c: ["real", str(w / "nowhere")],
         lambda w, c: (str(w / "nowhere"),)),
    Case("real a file", lambda w, c: ["real", str(_file(w))],
         lambda w, c: (str(w / "notes.txt"),)),
    Case("real empty folder", lambda w, c: ["real", str(_empty(w))],
         lambda w, c: (str(w / "empty"),)),
    Case("real too few lights", lambda w, c: ["real", str(c), "--every", "4"],
         lambda w, c: (str(c / "few"),)),
    Case("real json onto a folder",
         lambda w, c: ["real", str(c), "--json", str(_empty(w))], lambda w, c: ("--json",)),
    Case("paper json in missing folder",
         lambda w, c: ["paper", "--quick", "--json", str(w / "no" / "out.json")],
         lambda w, c: ("--json",)),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bench_refuses_before_work(case: Case, captures: Path, tmp_path: Path) -> None:
    work = tmp_path / "case"
    work.mkdir()
    args = case.args(work, captures)
    before, inputs = snapshot(work), snapshot(captures)
    result = run(["bench", *args], work, tmp_path / "home")
    assert_one_error_line(result, case.names(work, captures))
    assert_quiet(result)
    assert result.stdout == "", "the benchmark ran before the input was refused"
    assert snapshot(work) == before and snapshot(captures) == inputs


def test_bench_relight_json_is_strict(captures: Path, tmp_path: Path) -> None:
    """A sound capture: the table, and ``--json`` that a strict parser reads."""
    out = tmp_path / "relight.json"
    result = run(["bench", "relight", str(captures / "ok"), "--json", str(out)], tmp_path,
                 tmp_path / "home")
    assert result.code == 0, result.stderr
    assert_quiet(result)

    def refuse(constant: str) -> None:
        raise AssertionError(f"{constant} in --json")

    rows = json.loads(out.read_text(), parse_constant=refuse)
    assert rows and rows[0]["capture"] == "ok"


def test_finite_json_turns_nan_and_infinity_into_null() -> None:
    value = {"a": [math.nan, 1.5, (math.inf, -math.inf)], "b": {"c": 2, "d": "x"}}
    assert finite_json(value) == {"a": [None, 1.5, [None, None]], "b": {"c": 2, "d": "x"}}


# --- bad input: ``bench paper`` options refused (the table's engine: tests/helpers/bad_input.py) -


BAD_INPUT = CaseTable()
case = BAD_INPUT.case


@case("g2-bench-unknown-table", ("--tables",))
def _(w):
    return ["bench", "paper", "--quick", "--tables", "9"]


@case("g2-bench-size-huge", ("--size",))
def _(w):
    return ["bench", "paper", "--quick", "--size", "1000000"]


@case("x-bench-seed-negative", ("--seed",))
def _(w):
    return ["bench", "paper", "--quick", "--seed", "-1"]


#: The cases CI runs; ``pytest -m slow`` runs every case of the table.
BAD_INPUT_CI = {
    "g2-bench-unknown-table",
}
test_bad_input = BAD_INPUT.test(BAD_INPUT_CI)
