"""The command line as a newcomer meets it: help, -h, a bare `ps-lab`, -v, choices (issue 21)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
import typer.main
from helpers.bad_input import CaseTable
from helpers.hostile import environment
from typer.testing import CliRunner

from ps_lab import cli
from ps_lab.cli import app

runner = CliRunner()


def leaf_commands(command=None, path=()):
    """(path, click command) for every command that runs something, e.g. ("rig", "check")."""
    command = command if command is not None else typer.main.get_command(app)
    subcommands = getattr(command, "commands", None)
    if subcommands is None:
        yield path, command
        return
    for name, sub in subcommands.items():
        yield from leaf_commands(sub, (*path, name))


COMMANDS = [path for path, _ in leaf_commands()]
GROUPS = [(), ("rig",), ("bench",)]


def help_text(*path: str, flag: str = "--help", columns: int = 80) -> str:
    result = runner.invoke(app, [*path, flag], env={"COLUMNS": str(columns)})
    assert result.exit_code == 0, result.output
    return result.output


@pytest.mark.parametrize("path", COMMANDS + GROUPS, ids=lambda p: " ".join(p) or "ps-lab")
def test_help_at_80_columns_is_whole(path):
    """Every option name in full, no stray " .", no <bool> or <str>, nothing wider than 80."""
    text = help_text(*path)
    assert "Usage: ps-lab" in text
    assert "…" not in text
    assert not re.search(r"\s\.(\s|$)", text), text
    assert "<bool>" not in text and "<str>" not in text, text
    assert max(len(line) for line in text.splitlines()) <= 80, text
    command = dict(leaf_commands()).get(path)
    for param in getattr(command, "params", []):
        for name in [*param.opts, *param.secondary_opts]:
            if name.startswith("-"):
                assert re.search(rf"(?<![\w-]){re.escape(name)}(?![\w-])", text), (name, text)


@pytest.mark.parametrize("path", COMMANDS + GROUPS, ids=lambda p: " ".join(p) or "ps-lab")
def test_dash_h_is_help(path):
    assert help_text(*path, flag="-h") == help_text(*path)


def test_lazy_entry_point_accepts_dash_h(capsys):
    # `ps-lab reconstruct -h` as the console script runs it: only that command is loaded.
    with pytest.raises(SystemExit) as exit_:
        cli.main(["reconstruct", "-h"])
    assert exit_.value.code == 0
    assert "--shadow-threshold" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_:
        cli.main([])  # bare `ps-lab`
    assert exit_.value.code == 0
    assert "Commands:" in capsys.readouterr().out


@pytest.mark.parametrize("path", GROUPS, ids=lambda p: " ".join(p) or "ps-lab")
def test_bare_group_prints_help_and_exits_0(path):
    result = runner.invoke(app, list(path))
    assert result.exit_code == 0, result.output
    assert result.output.startswith("Usage: ps-lab")
    assert "Commands:" in result.output


def test_command_list_is_wrapped_not_cut():
    text = help_text()
    assert "..." not in text.split("Commands:")[1]
    assert "Estimate surface normals and albedo; write normals.npy," in text
    assert "normal.png, albedo, metrics.json." in text


@pytest.mark.parametrize("flag", ["-v", "-vv", "--verbose"])
def test_verbose_after_the_command_says_where_it_goes(tmp_path, flag):
    result = runner.invoke(app, ["reconstruct", str(tmp_path), flag])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    assert "-v/-vv go before the command (ps-lab -v reconstruct ...)" in lines[0]
    result = runner.invoke(app, ["rig", "check", flag])
    assert "(ps-lab -v rig check ...)" in result.output


def test_verbose_before_the_command_works(tmp_path):
    result = runner.invoke(app, ["-vv", "reconstruct", str(tmp_path / "none")])
    assert result.exit_code == 2
    assert "no such dataset folder" in result.output


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    folder = tmp_path_factory.mktemp("usage") / "sphere"
    result = runner.invoke(app, ["simulate", str(folder), "--size", "24", "--lights", "12"])
    assert result.exit_code == 0, result.output
    return folder


def test_choices_are_case_insensitive(small_dataset, tmp_path):
    out = tmp_path / "out"
    result = runner.invoke(
        app,
        ["reconstruct", str(small_dataset), "--method", "SBL", "--channel", "Mean",
         "--lights", "Directional", "--depth", "POISSON", "--out", str(out)],
    )
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["method"] == "sbl" and metrics["depth"]["method"] == "poisson"
    result = runner.invoke(app, ["integrate", str(out), "--method", "Bilateral"])
    assert result.exit_code == 0, result.output
    assert json.loads((out / "metrics.json").read_text())["depth"]["method"] == "bilateral"


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["reconstruct", "DATA", "--depth", "foo"], "error: --depth: 'foo' is not one of poisson"),
        (["integrate", "DATA", "--method", "foo"], "error: --method: 'foo' is not one of poisson"),
        (["batch", "DATA", "--out-root", "R", "--depth", "x"], "error: --depth: 'x' is not one"),
        (["reconstruct", "DATA", "--method", "sbI"], "error: --method: 'sbI' is not one of auto"),
    ],
)
def test_a_bad_choice_names_its_option_first(args, line):
    result = runner.invoke(app, args)
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [result.output.strip()]
    assert result.output.startswith(line), result.output


# --- a result or a folder of datasets where a dataset belongs ------------------------------------


@pytest.fixture(scope="module")
def lab_folder(tmp_path_factory):
    """lab/a and lab/b: two datasets; lab/a/recon/sbl: a's result, with depth."""
    lab = tmp_path_factory.mktemp("lab") / "lab"
    lab.mkdir()
    for name in ("a", "b"):
        result = runner.invoke(app, ["simulate", str(lab / name), "--size", "24", "--lights", "8"])
        assert result.exit_code == 0, result.output
    result = runner.invoke(
        app, ["reconstruct", str(lab / "a"), "--method", "sbl", "--depth", "poisson"]
    )
    assert result.exit_code == 0, result.output
    return lab


def one_error_line(result) -> str:
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    return lines[0]


def files(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


@pytest.mark.parametrize("command", ["calibrate", "reconstruct"])
def test_a_result_folder_is_not_taken_for_a_dataset(lab_folder, command):
    result_folder = lab_folder / "a" / "recon" / "sbl"
    before = files(lab_folder)
    line = one_error_line(runner.invoke(app, [command, str(result_folder)]))
    assert f"{result_folder}: a ps-lab reconstruct result (its metrics.json), not a dataset" in line
    assert f"made from: {lab_folder / 'a'}" in line
    assert "colour image" not in line and "light_directions" not in line
    assert files(lab_folder) == before


def test_reconstruct_on_a_folder_of_datasets_points_to_batch(lab_folder):
    line = one_error_line(runner.invoke(app, ["reconstruct", str(lab_folder)]))
    assert f"{lab_folder}: a folder of datasets, not a dataset" in line
    assert "2 subfolders hold datasets: a, b" in line
    assert f"ps-lab batch {lab_folder}/* --out-root RESULTS" in line


def test_calibrate_on_a_folder_of_datasets_asks_for_one(lab_folder):
    line = one_error_line(runner.invoke(app, ["calibrate", str(lab_folder)]))
    assert f"{lab_folder}: a folder of datasets, not a dataset" in line
    assert f"give one of them, e.g. {lab_folder / 'a'}" in line
    assert "batch" not in line


def test_a_folder_of_results_is_named_as_such(lab_folder):
    line = one_error_line(runner.invoke(app, ["reconstruct", str(lab_folder / "a" / "recon")]))
    assert "its subfolders are ps-lab reconstruct results (sbl)" in line


# --- bad input through the ps-lab process: typer's rejections, a bug (helpers/bad_input.py) ---


BAD_INPUT = CaseTable()
case = BAD_INPUT.case


@case("g5-unknown-option", ("--frobnicate",))
def _(w):
    return ["reconstruct", str(w.png()), "--frobnicate"]


@case("g5-extra-argument", ("surplus",))
def _(w):
    return ["reconstruct", str(w.png()), "surplus"]


@case("g5-missing-dataset-argument", ("DATASET", "dataset"))
def _(w):
    return ["reconstruct"]


@case("g5-unknown-command", ("recontruct",))
def _(w):
    return ["recontruct", "x"]


BUG = (
    "import sys\n"
    "import ps_lab.render.simulate as simulate\n"
    "def broken(*args, **kwargs):\n"
    "    raise ZeroDivisionError('injected bug')\n"
    "simulate.write_simulated_dataset = broken\n"
    "import ps_lab.commands.simulate as command\n"
    "command.write_simulated_dataset = broken\n"
    "from ps_lab.cli import main\n"
    "sys.argv[0] = 'ps-lab'\n"
    "main()\n"
)


@pytest.mark.parametrize("verbose", [[], ["-vv"]], ids=["quiet", "vv"])
def test_a_bug_is_one_line_naming_the_log(verbose, workspace) -> None:
    """An exception that is not a PsLabError: one line saying it is a bug and where the log is."""
    out = workspace.root / "new"
    result = subprocess.run(
        [sys.executable, "-c", BUG, *verbose, "simulate", str(out), "--size", "16"],
        cwd=workspace.root,
        capture_output=True,
        text=True,
        env=environment(workspace.home),
        timeout=120,
    )
    assert result.returncode == 2, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    line = lines[-1]
    assert line.startswith("error: internal error (a bug in ps-lab"), result.stderr
    assert "ZeroDivisionError: injected bug" in line
    log_file = Path(line.split("traceback in ", 1)[1].split(";", 1)[0])
    assert log_file.is_file() and "Traceback" in log_file.read_text()
    assert log_file.is_relative_to(workspace.home)
    if verbose:
        assert "Traceback" in result.stderr
    else:
        assert len(lines) == 1 and "Traceback" not in result.stderr
    assert not out.exists()


#: The cases CI runs; ``pytest -m slow`` runs every case of the table.
BAD_INPUT_CI = {
    "g5-missing-dataset-argument",
    "g5-unknown-command",
    "g5-unknown-option",
}
test_bad_input = BAD_INPUT.test(BAD_INPUT_CI)
