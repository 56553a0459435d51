"""`ps-lab reconstruct` end to end through the CLI: outputs, and every bad-input case."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from ps_lab import render
from ps_lab.cli import app
from ps_lab.errors import DatasetError
from ps_lab.io import dng
from ps_lab.reconstruct import _bands

runner = CliRunner()
SHAPE = (24, 24)
N_LIGHTS = 16


def invoke(*args: str):
    return runner.invoke(app, ["reconstruct", *map(str, args)])


def tree(root: Path) -> dict[str, int]:
    """Every path under root with its size, to prove that nothing was written."""
    return {str(p.relative_to(root)): p.stat().st_size for p in root.rglob("*")}


def write_dataset(
    folder: Path,
    *,
    seed: int = 0,
    specular: float = 0.0,
    colour: bool = False,
    shape=SHAPE,
    n: int = N_LIGHTS,
) -> dict:
    """A rendered sphere saved as 16-bit PNGs with lights, mask and ground truth."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True)
    albedo = (0.8, 0.5, 0.3) if colour else 0.8
    surface = render.sphere_surface(shape, albedo=albedo)
    lights = render.random_light_directions(n, rng)
    images = render.render(surface, lights, specular=specular, rng=rng)
    scale = 0.9 / max(float(images.max()), 1e-9)
    for i, image in enumerate(images):
        counts = np.clip(np.rint(image * scale * 65535), 0, 65535).astype(np.uint16)
        if counts.ndim == 3:
            counts = np.ascontiguousarray(counts[..., ::-1])
        assert cv2.imwrite(str(folder / f"{i:03d}.png"), counts)
    np.savetxt(folder / "light_directions.txt", lights)
    cv2.imwrite(str(folder / "mask.png"), surface.mask.astype(np.uint8) * 255)
    np.save(folder / "normal_gt.npy", surface.normals)
    return {"surface": surface, "lights": lights, "scale": scale}


# --- end to end --------------------------------------------------------------------------------


def check_outputs(out: Path, truth: dict) -> dict:
    mask = truth["surface"].mask
    normals = np.load(out / "normals.npy")
    assert normals.dtype == np.float32 and normals.shape == (*mask.shape, 3)
    np.testing.assert_allclose(np.linalg.norm(normals[mask], axis=1), 1.0, atol=1e-5)
    assert not normals[~mask].any()
    picture = cv2.imread(str(out / "normal.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    assert picture.dtype == np.uint8
    np.testing.assert_allclose(picture[mask], (normals[mask] + 1) * 127.5, atol=0.51)
    assert not picture[~mask].any()
    albedo = np.load(out / "albedo.npy")
    assert albedo.shape == mask.shape and not albedo[~mask].any()
    albedo_png = cv2.imread(str(out / "albedo.png"), cv2.IMREAD_UNCHANGED)
    assert albedo_png.dtype == np.uint8 and albedo_png.shape == mask.shape
    assert albedo_png[mask].max() == 255 and not albedo_png[~mask].any()
    corruption = cv2.imread(str(out / "corruption.png"), cv2.IMREAD_UNCHANGED)
    assert corruption.shape == mask.shape and corruption.dtype == np.uint8
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("method", "parameters", "pixels", "lights", "solve_seconds", "iterations"):
        assert key in metrics
    assert metrics["pixels"] == int(mask.sum()) and metrics["lights"] == len(truth["lights"])
    assert set(metrics["iterations"]) == {"mean", "median", "max"}
    assert set(metrics["angular_error_deg"]) >= {"mean", "median", "p90"}
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no staging left
    return metrics


@pytest.mark.parametrize("method", ["ls", "l1", "sbl"])
def test_reconstruct_writes_every_output(tmp_path, method):
    truth = write_dataset(tmp_path / "sphere")
    result = invoke(tmp_path / "sphere", "--method", method, "--shadow-threshold", "1e-3")
    assert result.exit_code == 0, result.output
    out = tmp_path / "sphere" / "recon" / method
    metrics = check_outputs(out, truth)
    assert metrics["method"] == method and metrics["shadow_threshold"] == 1e-3
    # Shadows dropped, no corruption: every method recovers the sphere to 16-bit quantisation.
    assert metrics["angular_error_deg"]["mean"] < 0.5
    assert f"results: {out}" in result.output and "normal error" in result.output
    # Albedo in units of the images: the rendered albedo times the 16-bit scaling.
    albedo = np.load(out / "albedo.npy")[truth["surface"].mask]
    np.testing.assert_allclose(np.median(albedo), 0.8 * truth["scale"], rtol=0.02)


def test_rpca_writes_every_output(tmp_path):
    truth = write_dataset(tmp_path / "sphere")
    result = invoke(tmp_path / "sphere", "--method", "rpca", "--shadow-threshold", "1e-3")
    assert result.exit_code == 0, result.output
    metrics = check_outputs(tmp_path / "sphere" / "recon" / "rpca", truth)
    # R-PCA models attached shadows as sparse errors; with 16 lights they are not: loose bound.
    assert metrics["angular_error_deg"]["median"] < 10.0


def test_sbl_beats_ls_on_speculars(tmp_path):
    write_dataset(tmp_path / "glossy", specular=0.5, seed=3)
    errors = {}
    for method in ("ls", "sbl"):
        out = tmp_path / method
        result = invoke(
            tmp_path / "glossy", "--method", method, "--out", out, "--shadow-threshold", "1e-3"
        )
        assert result.exit_code == 0, result.output
        errors[method] = json.loads((out / "metrics.json").read_text())["angular_error_deg"]["mean"]
    assert errors["sbl"] < errors["ls"]


def test_colour_channels_and_rerun_replaces(tmp_path):
    write_dataset(tmp_path / "colour", colour=True)
    out = tmp_path / "result"
    albedo = {}
    for channel in ("r", "b", "mean"):
        result = invoke(
            tmp_path / "colour",
            "--method",
            "ls",
            "--channel",
            channel,
            "--out",
            out,
            "--shadow-threshold",
            "1e-3",
        )
        assert result.exit_code == 0, result.output
        assert json.loads((out / "metrics.json").read_text())["channel"] == channel
        mask = cv2.imread(str(tmp_path / "colour" / "mask.png"), cv2.IMREAD_UNCHANGED) > 0
        # colour frames: albedo.npy is per channel (H, W, 3) whatever channel the normals used
        colour = np.load(out / "albedo.npy")[mask]
        assert colour.shape[1] == 3
        albedo[channel] = np.median(colour, axis=0)
    for channel in ("r", "b", "mean"):
        np.testing.assert_allclose(albedo[channel][0] / albedo[channel][2], 0.8 / 0.3, rtol=0.02)
        np.testing.assert_allclose(albedo[channel][1] / albedo[channel][2], 0.5 / 0.3, rtol=0.02)


def test_refuses_to_replace_a_folder_that_is_not_a_result(tmp_path):
    write_dataset(tmp_path / "d")
    (tmp_path / "precious").mkdir()
    (tmp_path / "precious" / "thesis.tex").write_text("do not delete")
    result = invoke(tmp_path / "d", "--method", "ls", "--out", tmp_path / "precious")
    assert result.exit_code == 2 and "precious" in result.output
    assert (tmp_path / "precious" / "thesis.tex").read_text() == "do not delete"


def test_failed_solve_leaves_no_partial_output(tmp_path, monkeypatch):
    write_dataset(tmp_path / "d")
    out = tmp_path / "new" / "deeper" / "out"
    before = tree(tmp_path)

    def broken_solve(observations, *args, progress=None, **kwargs):
        progress(observations.shape[1] // 2)
        raise DatasetError("solver blew up half way")

    monkeypatch.setattr(_bands, "solve", broken_solve)
    result = invoke(tmp_path / "d", "--method", "ls", "--out", out)
    assert result.exit_code == 2 and "blew up" in result.output
    assert tree(tmp_path) == before


def test_failed_rerun_keeps_the_previous_result(tmp_path, monkeypatch):
    write_dataset(tmp_path / "d")
    assert invoke(tmp_path / "d", "--method", "ls").exit_code == 0
    before = tree(tmp_path)
    monkeypatch.setattr(
        _bands, "solve", lambda *a, **k: (_ for _ in ()).throw(DatasetError("boom"))
    )
    assert invoke(tmp_path / "d", "--method", "ls").exit_code == 2
    assert tree(tmp_path) == before


def perturb(lights: np.ndarray, degrees: float, rng: np.random.Generator) -> np.ndarray:
    """Turn every light by `degrees` about a random axis perpendicular to it."""
    axis = np.cross(lights, rng.normal(size=lights.shape))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.radians(degrees)
    return lights * np.cos(angle) + np.cross(axis, lights) * np.sin(angle)


def test_refine_lights_writes_refined_lights(tmp_path):
    truth = write_dataset(tmp_path / "d", n=24, shape=(32, 32), seed=5)
    rng = np.random.default_rng(11)
    np.savetxt(tmp_path / "d" / "light_directions.txt", perturb(truth["lights"], 5.0, rng))
    out = tmp_path / "refined"
    result = invoke(
        tmp_path / "d", "--method", "sbl", "--out", out, "--refine-lights", "2",
        "--shadow-threshold", "1e-3",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "light refinement 2: mean direction change" in result.output
    directions = np.loadtxt(out / "light_directions.txt")
    intensities = np.loadtxt(out / "light_intensities.txt")
    assert directions.shape == (24, 3) and intensities.shape == (24, 3)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-6)
    metrics = json.loads((out / "metrics.json").read_text())
    history = metrics["refinement"]["history"]
    assert metrics["refinement"]["iterations"] == 2 and len(history) == 3
    # The final normals (solved with the refined lights) beat those from the perturbed lights.
    assert metrics["angular_error_deg"]["mean"] < history[0]["normal_error_deg"]


def test_dng_folder_matches_float_images(tmp_path):
    rng = np.random.default_rng(7)
    surface = render.sphere_surface(SHAPE, albedo=0.7)
    lights = render.random_light_directions(N_LIGHTS, rng)
    images = render.render(surface, lights)
    black, white = 512, 16383
    for folder in ("dng", "npy"):
        (tmp_path / folder).mkdir()
        np.savetxt(tmp_path / folder / "light_directions.txt", lights)
        np.save(tmp_path / folder / "normal_gt.npy", surface.normals)
    for i, image in enumerate(images):
        counts = np.rint(black + image * (white - black)).astype(np.uint16)
        mosaic = np.repeat(np.repeat(counts, 2, axis=0), 2, axis=1)  # each 2x2 block: one pixel
        dng.write_dng(
            tmp_path / "dng" / f"{i:03d}.dng", mosaic, black_level=black, white_level=white
        )
        np.save(tmp_path / "npy" / f"{i:03d}.npy", image.astype(np.float32))
    normals = {}
    for folder in ("dng", "npy"):
        result = invoke(tmp_path / folder, "--method", "ls", "--shadow-threshold", "1e-3")
        assert result.exit_code == 0, result.output
        normals[folder] = np.load(tmp_path / folder / "recon" / "ls" / "normals.npy")
    inside = np.linalg.norm(normals["npy"], axis=2) > 0
    cosine = np.sum(normals["dng"][inside] * normals["npy"][inside], axis=1)
    assert np.degrees(np.arccos(np.clip(cosine, -1, 1))).mean() < 0.1


# --- bad input: one line naming the file, exit 2, nothing written ----------------------------


def _break(kind: str, root: Path) -> tuple[Path, str]:
    """Build a dataset under root broken in one way; return (dataset path, text the error names)."""
    folder = root / "data"
    if kind == "missing folder":
        return root / "nope", "nope"
    write_dataset(folder, n=6, shape=(12, 12))
    if kind == "not a folder":
        (root / "file.png").write_bytes(b"x")
        return root / "file.png", "file.png"
    if kind == "empty light file":
        (folder / "light_directions.txt").write_text("# no rows\n")
        return folder, "light_directions.txt"
    if kind == "no images":
        for p in folder.glob("*.png"):
            if p.name != "mask.png":
                p.unlink()
        return folder, "no images"
    if kind == "no light directions":
        (folder / "light_directions.txt").unlink()
        return folder, "light_directions.txt"
    if kind == "corrupt image":
        (folder / "002.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
        return folder, "002.png"
    if kind == "truncated image":
        data = (folder / "003.png").read_bytes()
        (folder / "003.png").write_bytes(data[: len(data) // 2])
        return folder, "003.png"
    if kind == "corrupt raw":
        (folder / "002.png").unlink()
        (folder / "002.dng").write_bytes(b"II*\x00" + b"not really a raw file" * 50)
        return folder, "002.dng"
    if kind == "truncated raw":
        (folder / "002.png").unlink()
        dng.write_dng(
            folder / "002.dng",
            np.full((24, 24), 2000, np.uint16),
            black_level=512,
            white_level=16383,
        )
        data = (folder / "002.dng").read_bytes()
        (folder / "002.dng").write_bytes(data[: len(data) // 2])
        return folder, "002.dng"
    if kind == "count mismatch":
        (folder / "005.png").unlink()
        return folder, "light_directions.txt"
    if kind == "different sizes":
        cv2.imwrite(str(folder / "004.png"), np.zeros((12, 13), np.uint16))
        return folder, "004.png"
    if kind == "nan light":
        lights = np.loadtxt(folder / "light_directions.txt")
        lights[2, 1] = np.nan
        np.savetxt(folder / "light_directions.txt", lights)
        return folder, "light_directions.txt"
    if kind == "zero light":
        lights = np.loadtxt(folder / "light_directions.txt")
        lights[4] = 0
        np.savetxt(folder / "light_directions.txt", lights)
        return folder, "light_directions.txt"
    if kind == "empty mask":
        cv2.imwrite(str(folder / "mask.png"), np.zeros((12, 12), np.uint8))
        return folder, "mask.png"
    if kind == "mask size":
        cv2.imwrite(str(folder / "mask.png"), np.full((10, 12), 255, np.uint8))
        return folder, "mask.png"
    if kind == "intensities not numbers":
        (folder / "light_intensities.txt").write_text("1 1 1\n" * 5 + "one one one\n")
        return folder, "light_intensities.txt"
    if kind == "intensities count":
        np.savetxt(folder / "light_intensities.txt", np.ones((5, 3)))
        return folder, "light_intensities.txt"
    if kind == "intensities negative":
        values = np.ones((6, 3))
        values[3, 1] = -1
        np.savetxt(folder / "light_intensities.txt", values)
        return folder, "light_intensities.txt"
    if kind == "filenames lists missing file":
        (folder / "filenames.txt").write_text(
            "000.png\n001.png\n999.png\n003.png\n004.png\n005.png\n"
        )
        return folder, "999.png"
    if kind == "ground truth shape":
        np.save(folder / "normal_gt.npy", np.zeros((12, 12)))
        return folder, "normal_gt.npy"
    if kind == "uncalibrated run":
        (folder / "light_directions.txt").unlink()
        (folder / "manifest.json").write_text(
            json.dumps(
                {
                    "format": "ps-lab-run",
                    "version": 1,
                    "plan": {"lights": [1]},
                    "frames": [
                        {"index": 0, "kind": "light", "lights": [1], "repeat": 0, "file": "000.png"}
                    ],
                }
            )
        )
        return folder, "ps-lab calibrate"
    if kind == "corrupt manifest":
        (folder / "manifest.json").write_text("{not json")
        return folder, "manifest.json"
    raise AssertionError(kind)


BAD_INPUTS = [
    "missing folder",
    "not a folder",
    "empty light file",
    "no images",
    "no light directions",
    "corrupt image",
    "truncated image",
    "corrupt raw",
    "truncated raw",
    "count mismatch",
    "different sizes",
    "nan light",
    "zero light",
    "empty mask",
    "mask size",
    "intensities not numbers",
    "intensities count",
    "intensities negative",
    "filenames lists missing file",
    "ground truth shape",
    "uncalibrated run",
    "corrupt manifest",
]


@pytest.mark.parametrize("kind", BAD_INPUTS)
def test_bad_input_one_line_exit_2_nothing_written(tmp_path, kind):
    dataset, names = _break(kind, tmp_path)
    before = tree(tmp_path)
    result = invoke(dataset, "--method", "ls")
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    assert names in lines[0]
    assert tree(tmp_path) == before


# --- solver flags (issue 12) ------------------------------------------------------------------


def test_solver_flags_reach_the_solver_and_metrics(tmp_path):
    write_dataset(tmp_path / "sphere", specular=0.2)
    out = tmp_path / "out"
    result = invoke(tmp_path / "sphere", "--out", out, "--lambda", "1e-4", "--sigma-x2", "1e4",
                    "--max-iter", "7", "--tol", "1e-3")
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["solver_options"] == {"lambda": 1e-4, "sigma-x2": 1e4, "max-iter": 7,
                                         "tol": 1e-3, "segments": None}
    params = metrics["parameters"]
    assert (params["lambda"], params["sigma_x2"], params["max_iter"], params["tol"]) == (
        1e-4, 1e4, 7, 1e-3)
    assert metrics["iterations"]["max"] <= 7
    result = invoke(tmp_path / "sphere", "--out", out, "--method", "rpca", "--lambda", "0.2")
    assert result.exit_code == 0, result.output
    assert json.loads((out / "metrics.json").read_text())["parameters"]["lam_sparse"] == 0.2


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--lambda", "nan"), "--lambda: nan is not a finite number"),
        (("--lambda", "-1e-3"), "--lambda must be finite and positive"),
        (("--sigma-x2", "inf"), "--sigma-x2: inf is not a finite number"),
        (("--tol", "0"), "--tol must be finite and positive"),
        (("--max-iter", "0"), "--max-iter must be finite and positive"),
        (("--method", "ls", "--max-iter", "5"), "does not apply to method ls"),
        (("--method", "l1", "--lambda", "1e-3"), "does not apply to method l1"),
    ],
)
def test_bad_solver_flag_one_line_exit_2(tmp_path, args, message):
    write_dataset(tmp_path / "sphere")
    before = tree(tmp_path)
    result = invoke(tmp_path / "sphere", *args)
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0]
    assert tree(tmp_path) == before
