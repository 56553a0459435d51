"""Depth outputs, normal maps for other tools, .lp light files, and the integrate command."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers.tolerances import LIGHT_TABLE_ROUNDING
from plyfile import PlyData
from typer.testing import CliRunner

from ps_lab.cli import app
from ps_lab.errors import DatasetError
from ps_lab.io.light_files import lp_directions_for, read_lp, write_lp
from ps_lab.io.mesh import depth_mesh, write_ply
from ps_lab.io.normal_maps import normal16_picture, read_normals_exr, write_normals_exr
from ps_lab.reconstruct.metrics import depth_error

runner = CliRunner()


def test_normals_exr_round_trip_is_exact(tmp_path):
    normals = np.random.default_rng(0).standard_normal((7, 9, 3)).astype(np.float32)
    write_normals_exr(tmp_path / "n.exr", normals)
    assert np.array_equal(read_normals_exr(tmp_path / "n.exr"), normals)


def test_normal16_uses_the_normal_png_mapping():
    normals = np.array([[[0.0, 0.0, 1.0], [-1.0, 1.0, 0.0]]])
    picture = normal16_picture(normals, np.array([[True, False]]))
    assert picture.dtype == np.uint16
    assert picture[0, 0].tolist() == [32768, 32768, 65535]  # RGB = (n + 1) / 2
    assert picture[0, 1].tolist() == [0, 0, 0]


def test_lp_round_trip_and_matching_by_name(tmp_path):
    directions = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -0.6, 0.8]])
    write_lp(tmp_path / "lights.lp", ["a.png", "b.png", "c.png"], directions)
    names, read = read_lp(tmp_path / "lights.lp")
    assert names == ["a.png", "b.png", "c.png"]
    # 9 decimals, then each row normalised: a unit vector moved by d moves by <= 2 |d|
    atol = 2.0 * np.sqrt(3.0) * LIGHT_TABLE_ROUNDING
    np.testing.assert_allclose(read, directions, rtol=0, atol=atol)
    (tmp_path / "win.lp").write_text(
        "3\nC:\\rti\\b.png 0.6 0 0.8\nC:\\rti\\a.png 0 0 1\nC:\\rti\\d.png 0 -0.6 0.8\n"
    )
    np.testing.assert_allclose(
        lp_directions_for(tmp_path / "win.lp", [Path("a.png"), Path("b.png"), Path("d.png")]),
        directions,
        rtol=0,
        atol=atol,
    )
    with pytest.raises(DatasetError, match="no light for image c.png"):
        lp_directions_for(tmp_path / "win.lp", [Path("a.png"), Path("c.png"), Path("d.png")])
    (tmp_path / "bad.lp").write_text("3\na.png 0 0 1\n")
    with pytest.raises(DatasetError, match="says 3 images but lists 1"):
        read_lp(tmp_path / "bad.lp")


def test_mesh_has_no_triangle_across_a_step(tmp_path):
    depth = np.zeros((4, 6), np.float32)
    depth[:, 3:] = -50.0  # a step between columns 2 and 3
    depth[0, 0] = np.nan
    vertices, colours, triangles = depth_mesh(depth)
    assert len(vertices) == 23
    columns = vertices[:, 0][triangles]
    assert not np.any((columns.min(axis=1) <= 2) & (columns.max(axis=1) >= 3))
    # 3 x 5 cells, less the 3 across the step, 2 triangles each, less the one triangle of the
    # top-left cell that uses the missing pixel.
    assert len(triangles) == 2 * (3 * 5 - 3) - 1
    # Counter-clockwise seen from the camera (+z): normals of the flat parts point to +z.
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    assert np.all(np.cross(b - a, c - a)[:, 2] > 0)
    write_ply(tmp_path / "m.ply", vertices, colours, triangles)
    ply = PlyData.read(str(tmp_path / "m.ply"))
    assert not ply.text and ply["vertex"].count == 23 and ply["face"].count == len(triangles)


def test_depth_error_removes_one_offset_per_component():
    truth = np.arange(20.0).reshape(4, 5)
    depth = truth + 3.0
    depth[:, 2] = np.nan  # two components with different offsets
    depth[:, 3:] += 7.0
    error = depth_error(depth, truth)
    assert error["rmse"] < 1e-12 and error["pixels"] == 16


def test_simulate_reconstruct_integrate_end_to_end(tmp_path):
    data = tmp_path / "relief"
    result = runner.invoke(app, ["simulate", str(data), "--scene", "relief", "--size", "96"])
    assert result.exit_code == 0, result.output
    recon = tmp_path / "recon"
    result = runner.invoke(
        app, ["reconstruct", str(data), "--method", "ls", "--out", str(recon), "--depth", "poisson"]
    )
    assert result.exit_code == 0, result.output
    for name in ("normal16.png", "normals.exr", "depth.npy", "depth.tiff", "depth.png", "mesh.ply"):
        assert (recon / name).is_file(), name
    truth = np.load(data / "depth_gt.npy")
    depth = np.load(recon / "depth.npy")
    error = depth_error(depth, truth)
    assert error["relative"] < 0.03  # measured 1.8 % (LS normals, shadows kept, 96 px)
    metrics = json.loads((recon / "metrics.json").read_text())
    assert metrics["depth"]["method"] == "poisson" and metrics["depth"]["components"] == 1
    n16 = cv2.imread(str(recon / "normal16.png"), cv2.IMREAD_UNCHANGED)
    assert n16.dtype == np.uint16

    out = tmp_path / "bilateral"
    result = runner.invoke(
        app,
        ["integrate", str(recon), "--method", "bilateral", "--pixel-size", "0.5", "--out", str(out)],
    )
    assert result.exit_code == 0, result.output
    assert "depth: bilateral" in result.output
    in_mm = np.load(out / "depth.npy")
    assert depth_error(in_mm, truth * 0.5)["relative"] < 0.03
    assert json.loads((out / "metrics.json").read_text())["depth"]["unit"] == "mm"


def test_integrate_reports_a_bad_folder_in_one_line(tmp_path):
    result = runner.invoke(app, ["integrate", str(tmp_path)])
    assert result.exit_code == 2
    assert "no normals.npy" in result.output


def test_a_dataset_with_an_lp_file_instead_of_light_directions(tmp_path):
    data = tmp_path / "relief"
    simulated = runner.invoke(app, ["simulate", str(data), "--size", "48", "--lights", "12"])
    assert simulated.exit_code == 0
    names = (data / "filenames.txt").read_text().split()
    directions = np.loadtxt(data / "light_directions.txt")
    reference = tmp_path / "txt"
    args = ["reconstruct", str(data), "--method", "ls", "--out"]
    assert runner.invoke(app, [*args, str(reference)]).exit_code == 0
    (data / "light_directions.txt").unlink()
    write_lp(data / "relief.lp", names[::-1], directions[::-1])  # any order: matched by name
    result = runner.invoke(app, [*args, str(tmp_path / "lp")])
    assert result.exit_code == 0, result.output
    # The .lp holds light_directions.txt's own 9 decimals, both readers normalise the rows
    # alike: the same lights, the same solve.
    np.testing.assert_array_equal(
        np.load(tmp_path / "lp" / "normals.npy"), np.load(reference / "normals.npy")
    )


# --- progress and convergence of the depth stage (issue 21) ------------------------------------


class Bars:
    """A stand-in for the CLI's progress bars: records each bar's total, descriptions and steps."""

    def __init__(self):
        self.bars = []

    def __call__(self, total, description):
        from contextlib import contextmanager

        bar = {"total": total, "descriptions": [description], "steps": 0}
        self.bars.append(bar)

        @contextmanager
        def opened():
            def advance(n=1, description=None):
                bar["steps"] += n
                if description is not None:
                    bar["descriptions"].append(description)

            yield advance

        return opened()

    def depth(self):
        return [bar for bar in self.bars if bar["descriptions"][0].startswith("depth")]


@pytest.fixture(scope="module")
def relief_result(tmp_path_factory):
    # A 48 px sphere: its bilateral reweighting settles (at 14 iterations); simulated reliefs and
    # larger spheres end in a two-state cycle of the side weights (docs/results.md).
    root = tmp_path_factory.mktemp("sphere")
    result = runner.invoke(app, ["simulate", str(root / "sphere"), "--size", "48"])
    assert result.exit_code == 0, result.output
    return root / "sphere"


def test_reconstruct_depth_shows_a_bar_over_the_reweighting(relief_result, tmp_path, monkeypatch):
    bars = Bars()
    monkeypatch.setattr("ps_lab.commands.reconstruct._terminal_bars", bars)
    out = tmp_path / "out"
    result = runner.invoke(
        app, ["reconstruct", str(relief_result), "--out", str(out), "--depth", "bilateral"]
    )
    assert result.exit_code == 0, result.output
    depth = json.loads((out / "metrics.json").read_text())["depth"]
    assert depth["converged"] and "warning" not in result.output
    [bar] = bars.depth()
    assert bar["total"] == 150 and bar["steps"] == depth["iterations"]
    assert bar["descriptions"] == [
        "depth (bilateral): iterations",
        f"depth (bilateral): converged at iteration {depth['iterations']}",
    ]


def test_integrate_shows_a_bar_and_warns_when_it_stops_unconverged(
    relief_result, tmp_path, monkeypatch
):
    out = tmp_path / "out"
    result = runner.invoke(app, ["reconstruct", str(relief_result), "--out", str(out)])
    assert result.exit_code == 0, result.output
    bars = Bars()
    monkeypatch.setattr("ps_lab.commands.integrate._terminal_bars", bars)
    monkeypatch.setattr("ps_lab.reconstruct.depth.BILATERAL_MAX_ITERATIONS", 2)
    result = runner.invoke(app, ["integrate", str(out), "--method", "bilateral"])
    assert result.exit_code == 0, result.output
    depth = json.loads((out / "metrics.json").read_text())["depth"]
    assert not depth["converged"] and depth["iterations"] == 2
    assert bars.depth()[0]["steps"] == 2
    warnings = [line for line in result.output.splitlines() if line.startswith("warning:")]
    change = f"{100 * depth['energy_change']:.2g} %"
    assert warnings == [
        "warning: depth (bilateral) did not converge: stopped at its limit of 2 reweighting "
        f"iterations before the energy settled (last change {change}); depth.npy holds the last "
        f"iterate (residual {depth['residual']:.2g}): check depth.png, or integrate with poisson"
    ]
    assert result.output.splitlines()[-1] == warnings[0]  # after the results


def test_reconstruct_depth_warns_when_it_stops_unconverged(relief_result, tmp_path, monkeypatch):
    monkeypatch.setattr("ps_lab.reconstruct.depth.BILATERAL_MAX_ITERATIONS", 2)
    result = runner.invoke(
        app,
        ["reconstruct", str(relief_result), "--out", str(tmp_path / "o"), "--depth", "bilateral"],
    )
    assert result.exit_code == 0, result.output
    assert result.output.splitlines()[-1].startswith(
        "warning: depth (bilateral) did not converge: stopped at its limit of 2"
    )
