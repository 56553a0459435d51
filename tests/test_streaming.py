"""Streamed reconstruction: row bands and the staging store give the single-band result."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers.captures import N_LIGHTS, SHAPE, budget_for, write_capture
from helpers.tolerances import (
    EPS,
    LIGHT_TABLE_ROUNDING,
    angles_deg,
    assert_within,
    error_summary,
    least_squares,
    light_conditioning,
    light_refit,
    moved_lights,
    stored_float32,
)
from typer.testing import CliRunner

from ps_lab import reconstruct as solvers
from ps_lab.cli import app
from ps_lab.errors import DatasetError
from ps_lab.io.bands import ObservationStore, plan_bands, stage_observations
from ps_lab.io.dataset import load_dataset, open_dataset
from ps_lab.reconstruct import _bands, _outputs
from ps_lab.reconstruct._outputs import ERROR_BIN_DEG
from ps_lab.reconstruct.pipeline import (
    OutputError,
    ReconstructOptions,
    _Histogram,
    parse_memory_size,
    reconstruct_to_folder,
)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("streaming") / "sphere"
    write_capture(folder)
    return folder


# --- band plan and staging store ---------------------------------------------------------------


@pytest.mark.parametrize("max_pixels", [1, 7, 40, 10_000])
def test_bands_cover_the_image_within_the_pixel_limit(max_pixels):
    rng = np.random.default_rng(max_pixels)
    mask = rng.random((37, 11)) < 0.6
    bands = plan_bands(mask, max_pixels)
    assert bands[0].row_start == 0 and bands[-1].row_stop == mask.shape[0]
    for before, after in zip(bands, bands[1:], strict=False):
        assert before.row_stop == after.row_start
        assert after.pixel_start == before.pixel_start + before.pixel_count
    for band in bands:
        assert band.row_stop > band.row_start
        assert band.pixel_count == mask[band.row_start : band.row_stop].sum()
        one_row = band.row_stop - band.row_start == 1
        assert band.pixel_count <= max_pixels or one_row
    assert sum(b.pixel_count for b in bands) == mask.sum()


def _assert_store_is(store, data, mask) -> None:
    """Every band of ``store`` and its noise sample are ``data``'s (load_dataset) bit for bit."""
    for band in store.bands:
        observations, valid = store.read(band)
        rows = slice(band.row_start, band.row_stop)
        inside = mask[rows]
        np.testing.assert_array_equal(observations, data.images[:, rows][:, inside])
        np.testing.assert_array_equal(valid, data.valid[:, rows][:, inside])
    np.testing.assert_array_equal(store.sample_observations,
                                  data.images[:, mask][:, store.sample_index])


@pytest.mark.numerical
@pytest.mark.parametrize("colour", [False, True])
@pytest.mark.parametrize("in_memory", [False, True])
@pytest.mark.parametrize("max_pixels", [5, 97, 100_000])
def test_store_equals_load_dataset_bit_for_bit(tmp_path, colour, in_memory, max_pixels):
    folder = tmp_path / "d"
    write_capture(folder, colour=colour, seed=2)
    for channel in ("mean", "g") if colour else ("mean",):
        data = load_dataset(folder, channel=channel, shadow_threshold=0.01)
        header = open_dataset(folder, channel=channel)
        mask = header.read_mask()
        np.testing.assert_array_equal(mask, data.mask)
        bands = plan_bands(mask, max_pixels)
        with stage_observations(
            header, mask, bands, channel=channel, shadow_threshold=0.01,
            folder=tmp_path, in_memory=in_memory, sample_pixels=50,
        ) as store:  # fmt: skip
            assert (store.path is None) == in_memory
            _assert_store_is(store, data, mask)
            assert store.sample_index.size == 50
        assert not list(tmp_path.glob("ps-lab-observations-*"))  # closed: file deleted


def _without_dark(folder: Path, target: Path, suffix: str, colour: bool) -> None:
    """The capture as 8-bit sRGB JPEG or 16-bit PNG files, no dark frame (staged as codes)."""
    target.mkdir()
    for name in ("light_directions.txt", "light_intensities.txt", "mask.png"):
        (target / name).write_bytes((folder / name).read_bytes())
    for i in range(N_LIGHTS):
        counts = cv2.imread(str(folder / f"{i:03d}.png"), cv2.IMREAD_UNCHANGED)
        if suffix == ".jpg":  # bright enough to clip: the highlights are saturated
            counts = np.clip(counts.astype(np.float64) / 65535 * 1.6, 0, 1) ** (1 / 2.2)
            counts = np.rint(counts * 255).astype(np.uint8)
            cv2.imwrite(str(target / f"{i:03d}.jpg"), counts, [cv2.IMWRITE_JPEG_QUALITY, 92])
        else:
            cv2.imwrite(str(target / f"{i:03d}.png"), counts)


@pytest.mark.numerical
@pytest.mark.parametrize(("suffix", "colour", "dtype"), [
    (".jpg", True, np.uint8), (".jpg", False, np.uint8), (".png", True, np.uint16)])
@pytest.mark.parametrize("in_memory", [False, True])
def test_store_of_codes_equals_load_dataset_bit_for_bit(tmp_path, suffix, colour, dtype,
                                                        in_memory):
    # 8- and 16-bit frames with no dark frame are staged as their codes (one or two bytes a
    # sample) and observed when read: the same bits as decoding each frame to float.
    source = tmp_path / "source"
    write_capture(source, colour=colour, seed=5)
    folder = tmp_path / "coded"
    _without_dark(source, folder, suffix, colour)
    for channel in ("mean", "r") if colour else ("mean",):
        data = load_dataset(folder, channel=channel, shadow_threshold=0.01)
        header = open_dataset(folder, channel=channel)
        mask = header.read_mask()
        bands = plan_bands(mask, 97)
        with stage_observations(header, mask, bands, channel=channel, shadow_threshold=0.01,
                                folder=tmp_path, in_memory=in_memory, sample_pixels=50,
                                colours=3 if colour else 0) as store:
            assert store.coding.dtype == dtype
            channels = 3 if colour else 1
            assert store.nbytes == N_LIGHTS * int(mask.sum()) * channels * np.dtype(dtype).itemsize
            _assert_store_is(store, data, mask)
        if suffix == ".jpg":
            assert not data.valid[:, mask].all()  # the clipped highlights are dropped


def test_a_capture_with_a_dark_frame_is_staged_in_float(capture):
    header = open_dataset(capture)
    mask = header.read_mask()
    with stage_observations(header, mask, plan_bands(mask, 10_000), in_memory=True) as store:
        assert store.coding.dtype == np.float32 and not store.coding.coded


def test_a_frame_of_another_bit_depth_is_named(tmp_path):
    source = tmp_path / "source"
    write_capture(source, seed=6)
    folder = tmp_path / "coded"
    _without_dark(source, folder, ".png", False)
    counts = cv2.imread(str(folder / "004.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(folder / "004.png"), (counts >> 8).astype(np.uint8))
    header = open_dataset(folder)
    mask = header.read_mask()
    with pytest.raises(DatasetError, match="004.png: 8-bit image among 16-bit"):
        stage_observations(header, mask, plan_bands(mask, 50), folder=tmp_path)
    assert not list(tmp_path.glob("ps-lab-observations-*"))


def test_store_file_is_removed_when_reading_fails(tmp_path):
    folder = tmp_path / "d"
    write_capture(folder)
    # A sound header (open_dataset reads it) over missing pixel data (found while staging).
    (folder / "005.png").write_bytes((folder / "005.png").read_bytes()[:40])
    header = open_dataset(folder)
    mask = header.read_mask()
    with pytest.raises(DatasetError, match="005.png"):
        stage_observations(header, mask, plan_bands(mask, 50), folder=tmp_path)
    assert not list(tmp_path.glob("ps-lab-observations-*"))


def test_store_in_system_temp_is_removed_on_close():
    mask = np.ones((3, 4), bool)
    store = ObservationStore(plan_bands(mask, 5), 3, mask)
    assert store.path is not None and store.path.parent == Path(tempfile.gettempdir())
    assert store.path.exists()
    store.close()
    assert not store.path.exists()


# --- streamed results equal the single-band result ---------------------------------------------


def run(folder: Path, out: Path, **options) -> dict:
    options.setdefault("shadow_threshold", 0.005)
    return reconstruct_to_folder(folder, out, ReconstructOptions(**options)).metrics


def outputs(out: Path) -> dict:
    return {
        "normals": np.load(out / "normals.npy"),
        "albedo": np.load(out / "albedo.npy"),
        "corruption": cv2.imread(str(out / "corruption.png"), cv2.IMREAD_UNCHANGED),
        "normal_png": cv2.imread(str(out / "normal.png"), cv2.IMREAD_UNCHANGED),
        "metrics": json.loads((out / "metrics.json").read_text()),
    }


@pytest.mark.numerical
@pytest.mark.parametrize("method", ["ls", "l1", "sbl"])
def test_any_band_height_gives_the_single_band_result(capture, tmp_path, method):
    single = run(capture, tmp_path / "single", method=method, threads=1)
    assert single["streaming"]["bands"] == 1
    reference = outputs(tmp_path / "single")
    for pixels, staging in ((13, "file"), (60, "memory"), (250, "file")):
        out = tmp_path / f"bands-{pixels}"
        metrics = run(
            capture, out, method=method, memory_budget=budget_for(pixels), staging=staging,
            threads=2,
        )  # fmt: skip
        assert metrics["streaming"]["bands"] > 1
        assert metrics["streaming"]["max_band_pixels"] <= max(pixels, SHAPE[1])
        result = outputs(out)
        # L1, SBL: each band is solved with the whole image's parameters by the same kernel, bit
        # for bit; LS: BLAS products of other shapes (least squares' rounding), stored as float32
        bound = stored_float32(least_squares(N_LIGHTS)) if method == "ls" else 0.0
        assert_within(result["normals"], reference["normals"], bound)
        # |d albedo| <= albedo (half the normal bound + eps32)
        assert_within(result["albedo"], reference["albedo"], bound * reference["albedo"], "albedo")
        # the flags: none (LS) or bit-equal (L1, SBL)
        np.testing.assert_array_equal(result["corruption"], reference["corruption"])
        # normals within bound << 1/255 round to the same 8-bit level or the next
        levels = np.abs(result["normal_png"].astype(int) - reference["normal_png"])
        assert levels.max() <= (1 if bound else 0)
        summary = error_summary(int(reference["metrics"]["pixels"]), bound, ERROR_BIN_DEG)
        for key in ("angular_error_deg", "iterations", "outlier_share", "unsolved_pixels"):
            assert result["metrics"][key] == pytest.approx(reference["metrics"][key], **summary)
        parameters = result["metrics"]["parameters"]
        for key in ("lambda", "noise_sigma", "outlier_threshold"):
            assert parameters.get(key) == reference["metrics"]["parameters"].get(key), key
        if method != "ls":
            assert parameters["noise_sigma"] > 0


@pytest.mark.numerical
@pytest.mark.parametrize("method", ["ls", "l1", "sbl"])
def test_streamed_result_equals_the_in_memory_solve(capture, tmp_path, method):
    data = load_dataset(capture, shadow_threshold=0.005)
    # as the pipeline solves: normalised directions and, for SBL, each light's noise share
    unit = data.light_directions / np.linalg.norm(data.light_directions, axis=1, keepdims=True)
    shares = {"light_noise": solvers.light_noise_factors(data.light_intensities)}
    solution = solvers.solve(
        data.images[:, data.mask], unit, method=method, valid=data.valid[:, data.mask],
        threads=1, **(shares if method == "sbl" else {}),
    )  # fmt: skip
    metrics = run(capture, tmp_path / "out", method=method, memory_budget=budget_for(40))
    assert metrics["streaming"]["bands"] > 3
    result = outputs(tmp_path / "out")
    normals = result["normals"][data.mask]
    # L1, SBL: bit-equal solves, then renormalised and stored as float32; LS: BLAS of other shapes
    bound = stored_float32(least_squares(N_LIGHTS) if method == "ls" else 0.0)
    assert_within(normals, solution.normals, bound)
    assert_within(result["albedo"][data.mask], solution.albedo, bound * solution.albedo, "albedo")
    # the store kept the very sample the solve takes its noise level from
    for key in ("lambda", "noise_sigma", "outlier_threshold"):
        assert metrics["parameters"].get(key) == solution.params.get(key), key
    # the same flags (none for LS), integer counts
    assert metrics["outlier_share"] == solution.outliers.sum() / data.valid[:, data.mask].sum()
    errors = solvers.angular_errors_deg(normals.astype(np.float64), data.normal_gt[data.mask])
    summary = metrics["angular_error_deg"]
    # the same angles, the mean's sum taken band by band
    assert summary["mean"] == pytest.approx(errors.mean(), rel=errors.size * EPS, abs=0)
    assert summary["max"] == errors.max()
    # median and p90 come from a histogram of ERROR_BIN_DEG bins
    assert summary["median"] == pytest.approx(np.median(errors), abs=ERROR_BIN_DEG)
    assert summary["p90"] == pytest.approx(np.percentile(errors, 90), abs=ERROR_BIN_DEG)


def perturb(lights: np.ndarray, degrees: float, rng: np.random.Generator) -> np.ndarray:
    axis = np.cross(lights, rng.normal(size=lights.shape))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.radians(degrees)
    return lights * np.cos(angle) + np.cross(axis, lights) * np.sin(angle)


@pytest.mark.numerical
@pytest.mark.parametrize("fixed_intensities", [False, True])
def test_streamed_light_refinement_equals_refine_lights(tmp_path, fixed_intensities):
    folder = tmp_path / "d"
    truth = write_capture(folder, seed=4, n=16)
    np.savetxt(
        folder / "light_directions.txt", perturb(truth["lights"], 4.0, np.random.default_rng(1))
    )
    data = load_dataset(folder, shadow_threshold=0.005)
    expected = solvers.refine_lights(
        data.images[:, data.mask], data.light_directions, method="sbl", iterations=2,
        fixed_intensities=fixed_intensities, valid=data.valid[:, data.mask],
        normal_gt=data.normal_gt[data.mask], threads=1,
        light_noise=solvers.light_noise_factors(data.light_intensities),
    )  # fmt: skip
    metrics = run(
        folder, tmp_path / "out", method="sbl", refine_lights=2,
        fixed_intensities=fixed_intensities, memory_budget=budget_for(45),
    )  # fmt: skip
    assert metrics["streaming"]["bands"] > 3
    # The first solves are bit-equal (same lights, sample and kernel); then the streamed path adds
    # each light's sums band by band, refine_lights in one product: each refit moves the lights
    # (light_refit), each solve the normals (moved_lights), twice; tables carry 9 decimals.
    valid = data.valid[:, data.mask]
    solution = expected.solution
    sums, _, _ = solvers.light_fit_sums(data.images[:, data.mask], valid, solution)
    vectors = expected.light_directions * expected.light_intensities[:, None]
    cond = light_conditioning(vectors, valid & ~solution.outliers)[1]  # the inliers' fit
    first = light_refit(sums, vectors, solution.normals.shape[0])
    x_change = np.sum(np.sqrt(3.0) * solution.albedo * moved_lights(first, cond))
    second = light_refit(sums, vectors, solution.normals.shape[0], x_change)
    directions = np.loadtxt(tmp_path / "out" / "light_directions.txt")
    assert_within(directions, expected.light_directions, second + LIGHT_TABLE_ROUNDING, "lights")
    intensities = np.loadtxt(tmp_path / "out" / "light_intensities.txt")
    np.testing.assert_allclose(
        intensities, data.light_intensities * expected.light_intensities[:, None], rtol=second,
        atol=LIGHT_TABLE_ROUNDING,
    )  # fmt: skip
    normals = np.load(tmp_path / "out" / "normals.npy")[data.mask]
    assert_within(normals, solution.normals, stored_float32(moved_lights(second, cond)))
    history = metrics["refinement"]["history"]
    assert [h["iteration"] for h in history] == [0, 1, 2]
    # Each entry's angles move with its lights (or the normals), its shares are counts: a flag
    # flips only where a statistic lies within these changes (< 1e-6) of the threshold.
    normal_change = angles_deg(moved_lights(second, cond).max())
    for got, want, change in zip(history, expected.history, (0.0, first, second), strict=True):
        assert set(got) == set(want)
        for key, value in want.items():
            shift = {"mean_intensity_change": change, "used_fraction": 0.0}.get(
                key, angles_deg(change) + normal_change * bool(change))
            assert got[key] == pytest.approx(value, rel=valid.size * EPS, abs=shift), key


def test_tiny_memory_budget_still_works(capture, tmp_path):
    metrics = run(capture, tmp_path / "out", method="ls", memory_budget=1)
    mask = cv2.imread(str(capture / "mask.png"), cv2.IMREAD_UNCHANGED) > 0
    assert metrics["streaming"]["bands"] == SHAPE[0]  # one row per band
    assert metrics["streaming"]["staging"] == "file"
    normals = np.load(tmp_path / "out" / "normals.npy")
    np.testing.assert_allclose(np.linalg.norm(normals[mask], axis=1), 1.0, atol=1e-5)
    assert metrics["angular_error_deg"]["median"] < 5.0


# --- staging is removed after success and failure ---------------------------------------------


def listing(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def test_staging_removed_after_success(capture, tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "sys-tmp"))
    (tmp_path / "sys-tmp").mkdir()
    out = tmp_path / "results" / "out"
    seen = []
    original = solvers.solve

    def spy(observations, *args, **kwargs):
        seen.extend(p.name for p in out.parent.rglob("ps-lab-observations-*"))
        return original(observations, *args, **kwargs)

    monkeypatch.setattr(_bands, "solve", spy)
    run(capture, out, method="ls", memory_budget=budget_for(50), staging="file")
    assert seen  # the store was a file in the staged output folder while solving
    assert listing(tmp_path / "results") == {
        "out", *(f"out/{name}" for name in
                 ("normals.npy", "albedo.npy", "normal.png", "albedo.png", "corruption.png",
                  "metrics.json", "normal16.png", "normals.exr", "appearance.npz"))  # fmt: skip
    }
    assert not list((tmp_path / "sys-tmp").iterdir())


@pytest.mark.parametrize("staging", ["file", "memory"])
def test_staging_removed_after_failure(capture, tmp_path, monkeypatch, staging):
    before = listing(capture)
    out = tmp_path / "new" / "out"
    calls = []

    def failing_solve(observations, *args, progress=None, **kwargs):
        calls.append(observations.shape[1])
        if len(calls) == 3:
            raise DatasetError("solver failed in band 3")
        return original(observations, *args, progress=progress, **kwargs)

    original = solvers.solve
    monkeypatch.setattr(_bands, "solve", failing_solve)
    with pytest.raises(DatasetError, match="band 3"):
        run(capture, out, method="ls", memory_budget=budget_for(60), staging=staging)
    assert len(calls) == 3
    assert not (tmp_path / "new").exists()
    assert listing(capture) == before


def test_bad_budget_and_staging_are_refused(capture, tmp_path):
    with pytest.raises(OutputError, match="memory-budget"):
        run(capture, tmp_path / "o", memory_budget="lots")
    with pytest.raises(OutputError, match="staging"):
        run(capture, tmp_path / "o", staging="disk")
    assert not (tmp_path / "o").exists()


# --- helpers ------------------------------------------------------------------------------------


def test_parse_memory_size():
    assert parse_memory_size("512MB") == 512 << 20
    assert parse_memory_size("1.5G") == int(1.5 * (1 << 30))
    assert parse_memory_size("2 GiB") == 2 << 30
    assert parse_memory_size("800") == 800 << 20
    assert parse_memory_size(" 4096 ") == 4096 << 20
    for bad in ("", "-1GB", "0", "12 parsecs"):
        with pytest.raises(OutputError):
            parse_memory_size(bad)


def test_error_histogram_matches_numpy_within_a_bin():
    rng = np.random.default_rng(3)
    values = rng.gamma(2.0, 1.5, 20001)
    histogram = _Histogram(0.001, 180.0)
    for part in np.array_split(values, 7):
        histogram.add(part)
    summary = histogram.summary()
    assert summary["mean"] == pytest.approx(values.mean(), rel=1e-12)
    assert summary["max"] == values.max()
    assert summary["median"] == pytest.approx(np.median(values), abs=1e-3)
    assert summary["p90"] == pytest.approx(np.percentile(values, 90), abs=1e-3)


def test_cli_memory_budget(capture, tmp_path):
    runner = CliRunner()
    args = ["reconstruct", str(capture), "--method", "ls", "--shadow-threshold", "0.005"]
    result = runner.invoke(app, [*args, "--out", str(tmp_path / "a"), "--memory-budget", "20KB"])
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "a" / "metrics.json").read_text())["streaming"]["bands"] > 1
    result = runner.invoke(app, [*args, "--out", str(tmp_path / "b")])
    assert result.exit_code == 0, result.output
    a, b = (np.load(tmp_path / name / "normals.npy") for name in "ab")
    assert_within(a, b, stored_float32(least_squares(N_LIGHTS)))  # LS in bands: BLAS shapes
    result = runner.invoke(app, [*args, "--out", str(tmp_path / "c"), "--memory-budget", "lots"])
    assert result.exit_code == 2 and result.output.startswith("error: --memory-budget")
    assert not (tmp_path / "c").exists()


@pytest.mark.numerical
def test_rpca_bands_share_the_whole_image_noise_level(capture, tmp_path):
    # R-PCA's low-rank model is fitted per band (documented); its noise level and outlier
    # threshold are still the whole-image ones.
    single = run(capture, tmp_path / "single", method="rpca", threads=1)
    banded = run(capture, tmp_path / "banded", method="rpca", memory_budget=budget_for(60))
    assert single["streaming"]["bands"] == 1 and banded["streaming"]["bands"] > 1
    for key in ("noise_sigma", "outlier_threshold"):
        assert banded["parameters"][key] == single["parameters"][key], key
    assert single["parameters"]["noise_sigma"] > 0
    errors = banded["angular_error_deg"]
    assert errors["mean"] == pytest.approx(single["angular_error_deg"]["mean"], rel=0.25)


def test_writer_takes_a_solution_or_its_band_result(capture, tmp_path):
    header = open_dataset(capture)
    mask = header.read_mask()
    bands = plan_bands(mask, 10_000)
    store = stage_observations(header, mask, bands, in_memory=True)
    with store:
        observations, valid = store.read(bands[0])
    solution = solvers.solve(observations, header.light_directions, method="l1", valid=valid)
    written = {}
    for name, args in (("solution", (solution, valid)),
                       ("result", (_bands.reduce_solution(0, solution, valid),))):  # fmt: skip
        folder = tmp_path / name
        folder.mkdir()
        writer = _outputs._OutputWriter(folder, mask, None, len(header.names))
        writer.add(bands[0], *args)
        written[name] = (np.load(folder / "normals.npy"), writer.iterations, writer.outlier_count)
    a, b = written["solution"], written["result"]
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and a[2] == b[2]


def test_the_default_budget_follows_the_machine_and_the_stages_are_timed(capture, tmp_path):
    from ps_lab.io.images import available_memory
    from ps_lab.reconstruct.options import DEFAULT_MEMORY_SHARE, auto_memory_budget

    before = available_memory()
    metrics = run(capture, tmp_path / "out", method="ls")
    streaming = metrics["streaming"]
    assert streaming["memory_budget"].startswith("auto")
    share = streaming["memory_budget_bytes"] / DEFAULT_MEMORY_SHARE
    assert auto_memory_budget(0) <= streaming["memory_budget_bytes"]
    assert 0.5 * before <= share <= 1.5 * before  # the memory available at the start
    assert streaming["staging"] == "memory"  # a small capture fits: nothing goes to disk
    stages = metrics["timings"]["stages"]
    assert list(stages)[:3] == ["open", "decode and stage", "solve"]
    for name in ("open", "decode and stage", "solve", "outputs", "appearance", "surface"):
        assert stages[name]["wall_seconds"] >= 0 and stages[name]["cpu_seconds"] >= 0, name
    assert stages["decode and stage"]["bytes"] == sum(
        f.stat().st_size for f in capture.glob("0*.png")) + (capture / "dark.png").stat().st_size
    assert stages["observe"]["bytes"] >= streaming["staging_bytes"]
    files = metrics["timings"]["files"]
    assert files["normals.npy"]["bytes"] == (tmp_path / "out" / "normals.npy").stat().st_size
    assert "metrics.json" not in files


def test_an_explicit_budget_too_small_for_the_store_stages_to_a_file(capture, tmp_path):
    metrics = run(capture, tmp_path / "out", method="ls", memory_budget=budget_for(40))
    assert metrics["streaming"]["staging"] == "file"
    assert metrics["streaming"]["memory_budget"] == "given"
