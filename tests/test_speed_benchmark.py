"""benchmarks/speed.py (issue 37), reduced: a 64 x 60 px x 12-light synthetic JPEG capture.

The benchmark runs end to end (floor, the ps-lab runs, RelightLab when its tool is here, the
targets, ``--json``); the per-stage table is read from the result's flat timings (today's layout)
and from a made-up ``timings["stages"]`` / ``timings["files"]`` (the layout being added).
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "speed.py"


def _load():
    spec = importlib.util.spec_from_file_location("ps_lab_bench_speed", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


speed = _load()
# conftest.py has compiled the kernels already: no warm-up run
TINY = ["--megapixels", "0.00384", "--lights", "12", "--synthetic", "--repeats", "1",
        "--no-warm-up"]


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    """One reduced run of the benchmark: its exit code, report, JSON and arguments."""
    work = tmp_path_factory.mktemp("speed")
    out = work / "speed.json"
    argv = [*TINY, "--captures", "jpeg4", "--runs", "default,sbl,ls,relightlab", "--work",
            str(work), "--check", "--json", str(out), "--markdown", str(work / "speed.md")]
    code = speed.main(argv)
    return code, (work / "speed.md").read_text(), json.loads(out.read_text()), work


def test_capture_is_made_as_planned_and_reused(tmp_path):
    plan = speed.capture_plan("jpeg4", 0.00384, 12, synthetic=True)
    assert (plan["height"], plan["width"]) == (61, 63) and plan["source"] == "synthetic"
    record = speed.make_capture(tmp_path, plan)
    folder = Path(record["folder"])
    assert len(record["files"]) == 12 and record["generate_seconds"] > 0 and not record["reused"]
    image = cv2.imread(str(folder / record["files"][0]), cv2.IMREAD_UNCHANGED)
    assert image.shape == (61, 63, 3) and image.dtype == np.uint8
    assert (folder / "dirs.lp").read_text().splitlines()[0] == "12"
    assert speed.make_capture(tmp_path, plan)["reused"]  # cached
    other = speed.capture_plan("jpeg4", 0.00384, 10, synthetic=True)
    assert speed.capture_folder(tmp_path, other) != folder


def test_png16_capture_and_its_floor(tmp_path):
    plan = speed.capture_plan("png16-12mp", 0.003, 8, synthetic=True)
    record = speed.make_capture(tmp_path, plan)
    folder = Path(record["folder"])
    image = cv2.imread(str(folder / record["files"][0]), cv2.IMREAD_UNCHANGED)
    assert image.dtype == np.uint16 and image.ndim == 3
    assert np.loadtxt(folder / "light_directions.txt").shape == (8, 3)
    assert (folder / "mask.png").is_file()
    floor = speed.run_floor(record, tmp_path)
    assert floor["exit_code"] == 0 and floor["wall_seconds"] > 0
    assert floor["steps"]["pixels"] == plan["width"] * plan["height"]


def test_real_jpeg_capture_is_resized(tmp_path):
    source = speed.CAPTURES["jpeg4"]["source"]
    if not source.is_dir():
        pytest.skip(f"{source}: no RealRTI data")
    plan = speed.capture_plan("jpeg4", 0.004, 6, synthetic=False)
    record = speed.make_capture(tmp_path, plan)
    image = cv2.imread(str(Path(record["folder"]) / record["files"][0]))
    assert image.shape[:2] == (plan["height"], plan["width"]) and len(record["files"]) == 6


def test_every_run_has_a_row_and_the_floor_is_positive(ran):
    code, text, results, _ = ran
    (entry,) = results["captures"]
    assert entry["floor"]["ok"] and entry["floor"]["wall_seconds"] > 0
    assert entry["floor"]["cpu_seconds"] > 0 and entry["floor"]["peak_rss"] > 0
    for name in ("default", "sbl", "ls", "relightlab"):
        label = speed.RUNS[name][0]
        assert f"| {label} |" in text, name
        run = entry["runs"][name]
        if name != "relightlab" or "skipped" not in run:
            assert run["exit_code"] == 0, (name, run.get("stderr_tail"))
            assert run["wall_seconds"] > 0 and run["peak_rss"] > 0
    assert "| floor (numpy) |" in text
    assert "Machine: " in text


def test_targets_are_printed_with_their_values(ran):
    code, text, results, _ = ran
    targets = [c["target"] for c in results["checks"]]
    assert len(targets) == 4  # default and ls against the floor, solve, peak RSS (4 MP)
    for check in results["checks"]:
        assert check["measured"] is not None and check["target"] in text
    assert code == (1 if any(c["passed"] is False for c in results["checks"]) else 0)


def test_stage_table_falls_back_to_the_flat_timings(ran):
    _, text, results, _ = ran
    metrics = results["captures"][0]["runs"]["default"]["metrics"]
    rows = speed.stage_rows(metrics, {"decode+grey": 0.5, "solve": 0.1})
    if "stages" not in metrics["timings"]:
        names = [r["stage"] for r in rows]
        assert names[:2] == ["read + stage", "solve"] and "surface" in names
        assert rows[0]["floor_seconds"] == 0.5 and rows[1]["floor_seconds"] == 0.1
        assert all(r["cpu_seconds"] is None for r in rows)
        assert speed.solve_seconds(metrics) == metrics["timings"]["solve_seconds"]
    assert "| read + stage |" in text or "| solve |" in text
    assert "| normals.npy |" in text


def test_stage_table_of_the_flat_layout():
    metrics = {"solve_seconds": 2.0, "appearance": {"timings": {"fit_seconds": 1.5}},
               "timings": {"read_seconds": 1.0, "solve_seconds": 2.0, "write_seconds": 2.5,
                           "surface_seconds": 0.25}}
    rows = speed.stage_rows(metrics, {"decode+grey": 0.5, "solve": 0.1})
    assert [(r["stage"], r["wall_seconds"], r["floor_seconds"]) for r in rows] == [
        ("read + stage", 1.0, 0.5), ("solve", 2.0, 0.1), ("outputs + appearance", 2.5, None),
        ("  of which appearance fit", 1.5, None), ("surface", 0.25, None)]
    assert speed.solve_seconds(metrics) == 2.0
    entry = {"floor": {"ok": False}, "runs": {"default": {"wall_seconds": 7.0, "metrics": metrics}}}
    assert "| rest (process start, imports: wall - stages) | 1.25 |" in "\n".join(
        speed.stages_table(entry))


def test_stage_table_reads_the_new_layout():
    metrics = {"timings": {
        "stages": {
            "solve": {"wall_seconds": 3.0, "cpu_seconds": 5.5, "bytes": 1000},
            "decode": {"wall_seconds": 1.0, "cpu_seconds": 1.5, "bytes": 2_000_000},
            "extra": {"wall_seconds": 0.5, "cpu_seconds": 0.5, "bytes": 0},
            "appearance": {"wall_seconds": 2.0, "cpu_seconds": 3.0, "bytes": 10},
        },
        "files": {"normals.npy": {"wall_seconds": 0.25, "bytes": 123}},
        "read_seconds": 9.0, "solve_seconds": 9.0,
    }}
    rows = speed.stage_rows(metrics, {"decode": 0.4, "solve": 0.2})
    assert [r["stage"] for r in rows] == ["decode", "solve", "appearance", "extra"]
    assert rows[0]["floor_seconds"] == 0.4 and rows[1]["cpu_seconds"] == 5.5
    assert speed.solve_seconds(metrics) == 3.0
    files = speed.file_rows(metrics, {"normals.npy": 124, "albedo.png": 7})
    assert files[0] == {"file": "normals.npy", "bytes": 124, "wall_seconds": 0.25}
    assert files[1] == {"file": "albedo.png", "bytes": 7, "wall_seconds": None}
    entry = {"floor": {"ok": False}, "runs": {"default": {"wall_seconds": 7.0, "metrics": metrics,
                                                          "files": {"normals.npy": 124}}}}
    table = "\n".join(speed.stages_table(entry))
    assert "| decode | 1.00 | 1.50 | 2.00 MB |" in table
    assert "| rest (process start, imports: wall - stages) | 0.50 |" in table
    assert "| normals.npy | 124 B | 0.25 |" in table


def test_json_is_valid_and_complete(ran):
    _, _, results, work = ran
    text = (work / "speed.json").read_text()
    json.loads(text, parse_constant=lambda name: pytest.fail(f"{name} in the JSON"))
    assert set(results) >= {"machine", "arguments", "captures", "checks"}
    assert results["machine"]["cores"] >= 1 and results["machine"]["numpy"]


def test_a_failed_run_fails_its_targets():
    entry = {"capture": {"name": "png16-12mp", "kind": "png16"},
             "floor": {"ok": True, "wall_seconds": 2.0},
             "runs": {"default": {"exit_code": 1, "wall_seconds": 1.0, "peak_rss": 1},
                      "ls": {"exit_code": 0, "wall_seconds": 5.0, "peak_rss": 1}}}
    checks = {c["target"]: c for c in speed.check_targets([entry])}
    assert checks["png16-12mp: default <= 15x floor"]["passed"] is False
    assert checks["png16-12mp: default <= 300 s"]["passed"] is False
    assert checks["png16-12mp: --method ls --appearance none <= 3x floor"]["passed"] is True
    assert checks["png16-12mp: --method ls --appearance none <= 3x floor"]["measured"] == 2.5
