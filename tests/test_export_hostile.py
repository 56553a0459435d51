"""``ps-lab view --export DIR --format relight`` and RelightLab folders read back, as a hostile
user tries them (issue 43): the README's failure promise (one ``error:`` line naming the user's
file or option, exit 2, nothing written or changed) and a user's files never replaced.

Every case runs the real command in a subprocess (tests/helpers/hostile.py).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from ps_lab.cli import app
from tests.helpers.hostile import (
    IS_ROOT,
    assert_one_error_line,
    assert_quiet,
    refused,
    run,
    run_on_tmpfs,
    tmpfs_prefix,
)

runner = CliRunner()


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> dict[str, Path]:
    """A default result (ps fit) of a 32 px relief, its dataset, and its relight export."""
    root = tmp_path_factory.mktemp("export-hostile")
    data, result, export = root / "data", root / "result", root / "export"
    for args in (["simulate", str(data), "--scene", "relief", "--size", "32", "--lights", "12"],
                 ["reconstruct", str(data), "--method", "ls", "--out", str(result)],
                 ["view", str(result), "--export", str(export), "--format", "relight"]):
        done = runner.invoke(app, args)
        assert done.exit_code == 0, done.output
    return {"data": data, "result": result, "export": export}


def _case(tmp_path: Path) -> tuple[Path, Path]:
    case, home = tmp_path / "case", tmp_path / "home"
    case.mkdir()
    home.mkdir()
    return case, home


def _export(result: Path, out: Path) -> list[str]:
    return ["view", str(result), "--export", str(out), "--format", "relight"]


# ---- the output folder -------------------------------------------------------------------------


@pytest.mark.parametrize("content", ["info-and-notes", "info-only", "notes-only", "planes-only"])
def test_a_folder_with_the_users_files_is_refused_and_kept(made, tmp_path, content):
    case, home = _case(tmp_path)
    out = case / "mine"
    out.mkdir()
    if content in ("info-and-notes", "info-only"):  # RelightLab's own info.json, not ps-lab's
        (out / "info.json").write_text(json.dumps({"type": "ptm", "colorspace": "rgb"}))
    if content in ("info-and-notes", "notes-only"):
        (out / "notes.txt").write_text("my notes")
    if content == "planes-only":
        (out / "plane_0.jpg").write_bytes(b"my picture")
    line = refused(_export(made["result"], out), case, home, (str(out),))
    named = {"info-and-notes": "notes.txt", "info-only": "info.json", "notes-only": "notes.txt",
             "planes-only": "plane_0.jpg"}[content]
    assert named in line and "did not write" in line, line


def test_an_earlier_export_is_replaced(made, tmp_path):
    case, home = _case(tmp_path)
    out = case / "export"
    shutil.copytree(made["export"], out)
    result = run(_export(made["result"], out), case, home)
    assert result.code == 0, result.stderr
    assert_quiet(result)
    assert "dB PSNR" in result.stdout and len(result.stdout.strip().splitlines()) == 1
    assert sorted(p.name for p in case.iterdir()) == ["export"]


@pytest.mark.parametrize("where", ["onto-a-file", "under-a-file", "link-to-a-file"])
def test_an_output_that_cannot_be_a_folder(made, tmp_path, where):
    case, home = _case(tmp_path)
    file = case / "file.txt"
    file.write_text("mine")
    out = {"onto-a-file": file, "under-a-file": file / "out"}.get(where, case / "link")
    if where == "link-to-a-file":
        out.symlink_to(file)
    refused(_export(made["result"], out), case, home, (str(out), str(file)))


@pytest.mark.skipif(IS_ROOT, reason="root writes into read-only folders")
def test_a_read_only_parent_is_one_line(made, tmp_path):
    case, home = _case(tmp_path)
    parent = case / "locked"
    parent.mkdir()
    parent.chmod(0o555)
    try:
        result = run(_export(made["result"], parent / "out"), case, home)
        assert_one_error_line(result, (str(parent / "out"),))
    finally:
        parent.chmod(0o755)


def test_a_moved_dataset_is_named_not_exported_without_lights(made, tmp_path):
    """A PTM export takes the captured lights from the dataset: gone, it is one error naming
    it (it wrote ``"lights": []`` before)."""
    from ps_lab.appearance.models import Appearance
    from ps_lab.appearance.store import write_appearance

    case, home = _case(tmp_path)
    data, result = case / "data", case / "result"
    shutil.copytree(made["data"], data)
    shutil.copytree(made["result"], result)
    metrics = json.loads((result / "metrics.json").read_text())
    metrics["dataset"] = str(data)
    (result / "metrics.json").write_text(json.dumps(metrics))
    import numpy as np

    h, w = np.load(result / "normals.npy").shape[:2]
    write_appearance(result, Appearance("ptm", np.zeros((h, w, 3, 6), np.float32),
                                        {"basis": "ptm", "K": 6}))
    data.rename(case / "moved")
    line = refused(_export(result, case / "out"), case, home, (str(data),))
    assert "missing" in line, line


# ---- info.json read back -----------------------------------------------------------------------

DAMAGED_INFO = {
    "ps-lab-a-string": lambda i: {**i, "ps_lab": "ps-lab"},
    "lights-a-number": lambda i: {**i, "lights": 5},
    "lights-not-triples": lambda i: {**i, "lights": [0.1, 0.2]},
    "lights-nan-text": lambda i: {**i, "lights": ["x", 1, 2]},
    "width-a-string": lambda i: {**i, "width": "32"},
    "height-negative": lambda i: {**i, "height": -4},
    "nplanes-zero": lambda i: {**i, "nplanes": 0},
    "nplanes-huge": lambda i: {**i, "nplanes": 10**9},
    "materials-an-object": lambda i: {**i, "materials": {"scale": 1}},
    "scale-short": lambda i: {**i, "materials": [{**i["materials"][0], "scale": [1.0]}]},
    "range-zero": lambda i: {**i, "materials": [{**i["materials"][0],
                                                  "range": [0.0] * i["nplanes"]}]},
    "basis-short": lambda i: {**i, "basis": i["basis"][:-3]},
    "basis-out-of-bytes": lambda i: {**i, "basis": [300] * len(i["basis"])},
    "sigma-negative": lambda i: {**i, "sigma": -1},
    "sigma-missing": lambda i: {k: v for k, v in i.items() if k != "sigma"},
    "exposure-zero": lambda i: {**i, "ps_lab": {**i["ps_lab"], "exposure": 0}},
    "exposure-bool": lambda i: {**i, "ps_lab": {**i["ps_lab"], "exposure": True}},
    "type-a-list": lambda i: {**i, "type": ["rbf"]},
    "a-list": lambda i: [i],
}


@pytest.mark.parametrize("damage", list(DAMAGED_INFO))
def test_a_damaged_info_json_is_one_line_naming_it(made, tmp_path, damage):
    case, home = _case(tmp_path)
    folder = case / "export"
    shutil.copytree(made["export"], folder)
    info = json.loads((folder / "info.json").read_text())
    (folder / "info.json").write_text(json.dumps(DAMAGED_INFO[damage](info)))
    refused(["view", str(folder), "--export", str(case / "site")], case, home,
            (str(folder / "info.json"),))


@pytest.mark.parametrize("damage", ["deep", "not-utf8", "empty", "a-directory"])
def test_an_unreadable_info_json_is_one_line_naming_it(made, tmp_path, damage):
    case, home = _case(tmp_path)
    folder = case / "export"
    shutil.copytree(made["export"], folder)
    info = folder / "info.json"
    if damage == "deep":
        info.write_text("[" * 100000 + "]" * 100000)
    elif damage == "not-utf8":
        info.write_bytes(b"\xff\xfe{")
    elif damage == "empty":
        info.write_text("")
    else:
        info.unlink()
        info.mkdir()
    refused(["view", str(folder), "--export", str(case / "site")], case, home, (str(folder),))


def test_the_export_opens_as_a_result(made, tmp_path):
    case, home = _case(tmp_path)
    result = run(["view", str(made["export"]), "--export", str(case / "site")], case, home)
    assert result.code == 0, result.stderr
    assert_quiet(result)


# ---- a full disk -------------------------------------------------------------------------------


def test_a_full_disk_names_the_users_folder_not_a_staging_one(made, tmp_path):
    case, home = _case(tmp_path)
    full = case / "full"
    prefix = tmpfs_prefix(full)
    if prefix is None:
        pytest.skip("cannot mount a tmpfs here (unshare -rm not allowed): full disk not tested")
    out = full / "export"
    outcome, before, after = run_on_tmpfs(prefix, full, _export(made["result"], out), home,
                                          leave=8192)
    line = assert_one_error_line(outcome, (str(out),))
    assert "space" in line and ".partial" not in line, line
    assert after == before
