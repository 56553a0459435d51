"""``ps-lab relight`` and the appearance fits on hostile input (issue 43).

CLI cases: each damages one thing of a small result folder (written here with numpy, 16 x 16:
a hemisphere's normals, a colour albedo, every appearance model fitted in-process) or passes a
hostile option, and runs the real command in a subprocess. The promise (README, "Failure
behaviour"): exit 2, one ``error:`` line naming the user's file or option (never a staging
path), no traceback or numpy warning, nothing created or changed, no temporary file left.
Fits: what the training lights determine (distinct directions, the design's numerical rank)
and the one rule for saturated observations, checked against straightforward references.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from helpers.hostile import (
    assert_one_error_line,
    assert_quiet,
    refused,
    run,
    run_on_tmpfs,
    tmpfs_prefix,
)

from ps_lab import render
from ps_lab.appearance.blocks import fit_rbf
from ps_lab.appearance.design import (
    SAME_LIGHT,
    determined_terms,
    distinct_lights,
    saturated_observations,
)
from ps_lab.appearance.fit import fit_appearance
from ps_lab.appearance.models import APPEARANCE_FILE, appearance_basis
from ps_lab.appearance.store import read_appearance, write_appearance
from ps_lab.cli import app
from ps_lab.io.result import RESULT_FORMAT

SIZE = 16
runner = CliRunner()
MODELS = ("ps", "ptm", "hsh3", "rbf")


def hemisphere(n: int, rng: np.random.Generator, max_zenith_deg: float = 70.0) -> np.ndarray:
    z = rng.uniform(math.cos(math.radians(max_zenith_deg)), 1.0, n)
    phi = rng.uniform(0, 2 * math.pi, n)
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def ring(n: int, elevation_deg: float = 40.0) -> np.ndarray:
    a = np.linspace(0, 2 * math.pi, n, endpoint=False)
    e = math.radians(elevation_deg)
    return np.stack([np.cos(a) * math.cos(e), np.sin(a) * math.cos(e), np.full(n, math.sin(e))], 1)


# ---- a small result folder, every model ---------------------------------------------------------


def _sphere() -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.indices((SIZE, SIZE))
    x = (cols - (SIZE - 1) / 2) / (0.45 * SIZE)
    y = ((SIZE - 1) / 2 - rows) / (0.45 * SIZE)
    mask = x * x + y * y < 1
    normals = np.zeros((SIZE, SIZE, 3), np.float32)
    normals[mask, 0], normals[mask, 1] = x[mask], y[mask]
    normals[mask, 2] = np.sqrt(1 - x[mask] ** 2 - y[mask] ** 2)
    return normals, mask


def _result(folder: Path, model: str, rng: np.random.Generator, near: bool = False) -> None:
    folder.mkdir()
    normals, mask = _sphere()
    albedo = np.zeros((SIZE, SIZE, 3), np.float32)
    albedo[mask] = rng.uniform(0.3, 0.8, (mask.sum(), 3))
    np.save(folder / "normals.npy", normals)
    np.save(folder / "albedo.npy", albedo)
    metrics = {"format": RESULT_FORMAT, **({"light_model": "near"} if near else {})}
    (folder / "metrics.json").write_text(json.dumps(metrics))
    if near:
        np.save(folder / "depth.npy", np.where(mask, 2.0, np.nan).astype(np.float32))
    lights = hemisphere(24, rng)
    shade = np.maximum(normals[mask] @ lights.T, 0.0).T  # (n, P)
    obs = albedo[mask][None] * shade[..., None] + 0.05 * shade[..., None] ** 8
    write_appearance(folder, fit_appearance(model, obs, lights, mask, normals[mask],
                                            albedo[mask]))


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("relight-made")
    rng = np.random.default_rng(43)
    for model in MODELS:
        _result(root / model, model, rng)
    _result(root / "near", "ps", rng, near=True)
    return {name: root / name for name in (*MODELS, "near")}


# ---- damaging an appearance file --------------------------------------------------------------


def _arrays(folder: Path) -> dict[str, np.ndarray]:
    with np.load(folder / APPEARANCE_FILE, allow_pickle=False) as data:
        return {k: np.asarray(data[k]) for k in data.files}


def _rewrite(folder: Path, change: Callable[[dict], None]) -> None:
    arrays = _arrays(folder)
    meta = json.loads(str(arrays["meta"]))
    arrays["meta"] = meta
    change(arrays)
    if not isinstance(arrays["meta"], np.ndarray):
        arrays["meta"] = np.array(arrays["meta"] if isinstance(arrays["meta"], str)
                                  else json.dumps(arrays["meta"]))
    (folder / APPEARANCE_FILE).unlink()
    np.savez(folder / APPEARANCE_FILE, **arrays)


def _set(key: str, value) -> Callable[[dict], None]:
    def change(arrays: dict) -> None:
        arrays[key] = value

    return change


def _meta(key: str, value) -> Callable[[dict], None]:
    def change(arrays: dict) -> None:
        arrays["meta"][key] = value

    return change


def _map(key: str, how: Callable[[np.ndarray], np.ndarray]) -> Callable[[dict], None]:
    def change(arrays: dict) -> None:
        arrays[key] = how(arrays[key])

    return change


def _truncate(folder: Path) -> None:
    data = (folder / APPEARANCE_FILE).read_bytes()
    (folder / APPEARANCE_FILE).write_bytes(data[: len(data) // 2])


def _nested_metrics(folder: Path) -> None:
    (folder / "metrics.json").write_text("[" * 50000 + "]" * 50000)


def _npy(name: str, value: np.ndarray) -> Callable[[Path], None]:
    """Save ``value`` as ``name``; ``X.npz.npy`` replaces ``X.npz`` by a single array."""
    def damage(folder: Path) -> None:
        np.save(folder / name, value)
        if name.endswith(".npz.npy"):
            (folder / name).replace(folder / name[:-4])

    return damage


def _forged_header(folder: Path) -> None:
    """``normals.npy`` whose header claims 120 GB and holds 1 KB."""
    with open(folder / "normals.npy", "wb") as handle:
        np.lib.format.write_array_header_1_0(
            handle, {"descr": "<f4", "fortran_order": False, "shape": (100000, 100000, 3)})
        handle.write(bytes(1024))


def _tiny_focal(folder: Path) -> None:
    metrics = json.loads((folder / "metrics.json").read_text())
    metrics["camera"] = {"fx": 1e-300, "fy": 1e-300, "cx": 8.0, "cy": 8.0}
    (folder / "metrics.json").write_text(json.dumps(metrics))


def _unit_normals_times(factor: float) -> np.ndarray:
    normals, _ = _sphere()
    return normals * factor


@dataclass
class Case:
    name: str
    base: str  # a result of `made`
    lights: tuple[str, ...] = ("0.3,0.2,0.9",)
    damage: Callable[[Path], None] | None = None  # on the copied result folder
    rewrite: Callable[[dict], None] | None = None  # of its appearance.npz
    out: str = "pic.png"
    names: tuple[str, ...] = (APPEARANCE_FILE,)


CASES = [
    # light vectors and LED positions (the option named)
    Case("light-huge", "ptm", ("1e300,1e300,1e300",), names=("--light",)),
    Case("light-below", "hsh3", ("0.2,0.1,-0.9",), names=("--light",)),
    Case("light-horizon", "rbf", ("1,0,0",), names=("--light",)),
    Case("light-nan", "ps", ("nan,0,1",), names=("--light",)),
    Case("second-light-bad", "ps", ("0,0,1", "0,0,0"), names=("--light",)),
    Case("led-origin", "near", ("0,0,0",), names=("--light",)),
    Case("led-far", "near", ("1e308,0,1e308",), names=("--light",)),
    Case("led-inside", "near", ("0,0,2.5",), names=("--light",)),
    # damaged result and appearance files (the file named)
    Case("meta-nested", "ps", rewrite=_set("meta", np.array("[" * 100000 + "]" * 100000))),
    Case("metrics-nested", "ptm", damage=_nested_metrics, names=("ptm",)),
    Case("lobe-nan", "ps", rewrite=_meta("terms", ["lx", "ly", "lz", "ambient", "lobe:nan",
                                                   "lobe:32"])),
    Case("lobe-huge", "ps", rewrite=_meta("terms", ["lx", "ly", "lz", "ambient", "lobe:1e300",
                                                    "lobe:32"])),
    Case("term-not-text", "ps", rewrite=_meta("terms", ["lx", "ly", "lz", "ambient", 4,
                                                        "lobe:32"])),
    Case("rbf-sigma-tiny", "rbf", rewrite=_meta("sigma", 1e-300)),
    Case("rbf-lights-text", "rbf", rewrite=_map("extra_lights", lambda a: a.astype(str))),
    Case("rbf-lights-not-unit", "rbf", rewrite=_map("extra_lights", lambda a: a * 3)),
    Case("rbf-basis-nan", "rbf", rewrite=_map("extra_basis", lambda a: a * np.nan)),
    Case("ptm-five-terms", "ptm", rewrite=_map("coefficients", lambda a: a[..., :5])),
    Case("coefficients-huge", "ptm", rewrite=_map("coefficients",
                                                  lambda a: (a * 0 + 1e30).astype(np.float32))),
    Case("truncated", "hsh3", damage=_truncate),
    Case("npy-not-npz", "ptm", damage=_npy(APPEARANCE_FILE + ".npy", np.ones(3))),
    Case("normals-long", "ps", damage=_npy("normals.npy", _unit_normals_times(2.0)),
         names=("normals.npy",)),
    Case("albedo-inf", "ps", damage=_npy("albedo.npy", np.full((SIZE, SIZE), np.inf,
                                                                np.float32)),
         names=("albedo.npy",)),
    Case("normals-forged-header", "ps", damage=_forged_header, names=("normals.npy",)),
    Case("camera-focal-tiny", "near", ("0,0,40",), damage=_tiny_focal, names=("metrics.json",)),
    # outputs (the option's file named)
    Case("out-folder", "ps", out="shots", names=("shots",)),
    Case("out-second-is-folder", "ps", ("0,0,1", "0.3,0,1"), out="shots.png",
         names=("shots_light02.png",)),
    Case("out-under-a-file", "ps", out="notes.txt/pic.png", names=("notes.txt",)),
]


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_relight_refuses_in_one_line(case: Case, made, tmp_path) -> None:
    root, home = tmp_path / "case", tmp_path / "home"
    root.mkdir()
    home.mkdir()
    result = root / case.base
    shutil.copytree(made[case.base], result)
    if case.rewrite is not None:
        _rewrite(result, case.rewrite)
    if case.damage is not None:
        case.damage(result)
    (root / "shots").mkdir()
    (root / "shots_light02.png").mkdir()
    (root / "notes.txt").write_text("mine")
    args = ["relight", str(result), "--out", str(root / case.out)]
    for light in case.lights:
        args.append(f"--light={light}")
    line = refused(args, root, home, case.names)
    assert ".relight-partial" not in line, line


def test_relight_several_lights_near_and_far_succeed_quietly(made, tmp_path) -> None:
    home = tmp_path / "home"
    home.mkdir()
    for name in ("ps", "rbf", "near"):
        lights = ["0,0,40", "20,-10,30"] if name == "near" else ["0.3,0.2,0.9", "0,0.99,0.05"]
        args = ["relight", str(made[name]), "--out", str(tmp_path / f"{name}.exr")]
        done = run([*args, *(f"--light={x}" for x in lights)], tmp_path, home)
        assert done.code == 0, done.stderr
        assert_quiet(done)
        assert not done.lines, done.stderr
        for k in (1, 2):
            assert (tmp_path / f"{name}_light{k:02d}.exr").is_file()


def test_relight_overwrites_earlier_pictures_all_or_none(made, tmp_path) -> None:
    home = tmp_path / "home"
    home.mkdir()
    (tmp_path / "pic_light01.png").write_bytes(b"old one")
    (tmp_path / "pic_light03.png").mkdir()
    args = ["relight", str(made["ps"]), "--out", str(tmp_path / "pic.png")]
    done = run([*args, "--light=0,0,1", "--light=0.3,0,1", "--light=0,0.3,1"], tmp_path, home)
    assert_one_error_line(done, ("pic_light03.png",))
    assert (tmp_path / "pic_light01.png").read_bytes() == b"old one"
    assert not (tmp_path / "pic_light02.png").exists()
    (tmp_path / "pic_light03.png").rmdir()
    done = run([*args, "--light=0,0,1", "--light=0.3,0,1", "--light=0,0.3,1"], tmp_path, home)
    assert done.code == 0, done.stderr
    assert cv2.imread(str(tmp_path / "pic_light01.png")).shape == (SIZE, SIZE, 3)
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


# ---- full and read-only disks ---------------------------------------------------------------


@pytest.mark.parametrize("disk", ["full", "read-only"])
def test_relight_on_a_full_or_read_only_disk_names_the_picture(disk, made, tmp_path) -> None:
    home = tmp_path / "home"
    home.mkdir()
    mount = tmp_path / "disk"
    prefix = tmpfs_prefix(mount, "ro" if disk == "read-only" else "rw")
    if prefix is None:
        pytest.skip("cannot mount a tmpfs here (unshare -rm not allowed)")
    out = mount / "pic.exr"
    # fill all but 4 KiB, then relight two lights of 12 KiB each (EXR of 16 x 16 floats)
    done, _, after = run_on_tmpfs(
        prefix, mount, ["relight", str(made["ps"]), "--out", str(out), "--light=0,0,1",
                        "--light=0.3,0.2,0.9"], home, leave=4096 if disk == "full" else None,
        timeout=120,
    )
    left = [name for name in after if name != "filler"]
    line = assert_one_error_line(done, (str(mount / "pic_light0"),))
    assert ".relight-partial" not in line and left == [], (line, left)
    assert ("space" in line) if disk == "full" else ("read-only" in line), line


# ---- what the lights determine ----------------------------------------------------------------


def test_distinct_lights_merges_directions_closer_than_the_tolerance(rng) -> None:
    lights = hemisphere(30, rng)
    close = lights + rng.normal(scale=SAME_LIGHT / 20, size=lights.shape)
    far = lights + rng.normal(scale=SAME_LIGHT * 20, size=lights.shape)
    assert len(distinct_lights(np.vstack([lights, close]))) == 30
    assert len(distinct_lights(np.vstack([lights, far]))) == 60
    assert distinct_lights(np.vstack([lights, lights])).tolist() == list(range(30))


@pytest.mark.parametrize(
    ("model", "lights", "rank"),
    [("hsh3", "six", 6), ("ptm", "four", 4), ("hsh2", "three", 3), ("ptm", "ring", 5),
     ("ptm", "duplicates", 5), ("hsh3", "many", 9), ("ptm", "many", 6)],
)
def test_determined_terms_is_the_design_rank(model, lights, rank, rng) -> None:
    d = {"six": hemisphere(6, rng), "four": hemisphere(4, rng), "three": hemisphere(3, rng),
         "ring": ring(12), "duplicates": np.repeat(hemisphere(5, rng), 3, axis=0),
         "many": hemisphere(40, rng)}[lights]
    terms = tuple(range(appearance_basis(model, d).shape[1]))
    keep, warning = determined_terms(model, d, terms)
    assert len(keep) == rank
    # the numerical rank of the full design at the distinct lights
    design = appearance_basis(model, d[distinct_lights(d)])
    singular = np.linalg.svd(design / np.linalg.norm(design, axis=0), compute_uv=False)
    assert np.sum(singular > 1e-6 * singular[0]) == rank
    assert np.linalg.matrix_rank(design[:, keep]) == rank
    assert (warning is None) == (rank == len(terms))


def test_a_ring_fits_ptm_without_its_undetermined_term_and_says_so(rng, caplog) -> None:
    normals, mask = _sphere()
    d = ring(12)
    obs = rng.uniform(0.1, 0.9, (12, int(mask.sum()), 1))
    with caplog.at_level(logging.WARNING):
        fitted = fit_appearance("ptm", obs, d, mask)
    assert len(caplog.records) == 1 and "ly²" in caplog.records[0].getMessage()
    coeffs = fitted.coefficients[mask][:, 0]  # (P, 6)
    assert np.all(coeffs[:, 5] == 0)
    basis = appearance_basis("ptm", d)[:, :5]
    reference = np.linalg.lstsq(basis, obs[..., 0], rcond=None)[0].T
    assert np.allclose(coeffs[:, :5], reference, atol=1e-5)


def test_five_lights_fit_the_ps_model_on_five_terms_and_the_file_reads_back(rng, caplog,
                                                                            tmp_path) -> None:
    normals, mask = _sphere()
    d = hemisphere(5, rng)
    obs = np.maximum(normals[mask] @ d.T, 0.0).T[..., None] * 0.6
    with caplog.at_level(logging.WARNING):
        fitted = fit_appearance("ps", obs, d, mask, normals[mask], np.full(mask.sum(), 0.6))
    assert [r.getMessage().split(":")[0] for r in caplog.records] == ["appearance ps"]
    assert fitted.meta["terms"] == ["lx", "ly", "lz", "ambient", "lobe:4"]
    write_appearance(tmp_path, fitted)
    assert read_appearance(tmp_path).coefficients.shape[3] == 5


def test_saturated_observations_are_those_not_dropped_as_shadows(rng) -> None:
    obs = rng.uniform(0, 1, (8, 50)).astype(np.float32)
    valid = rng.uniform(size=obs.shape) > 0.3
    assert np.array_equal(saturated_observations(obs, valid), ~valid)
    both = saturated_observations(obs, valid, 0.2)
    assert np.array_equal(both, ~valid & (obs > 0.2))
    # a pixel left with fewer observations than the model's terms keeps all of its own
    kept = saturated_observations(obs, valid, None, 6)
    few = valid.sum(axis=0) < 6
    assert few.any() and not few.all()
    assert not kept[:, few].any() and np.array_equal(kept[:, ~few], ~valid[:, ~few])


def test_rbf_fit_of_missing_observations_is_least_squares_on_the_others(rng) -> None:
    n, p, k = 12, 30, 5
    basis = np.linalg.qr(rng.normal(size=(n, k)))[0][None]  # (1, n, K) orthonormal columns
    obs = rng.uniform(0.1, 1.0, (n, p, 1))
    obs[rng.uniform(size=(n, p)) < 0.2] = np.nan
    coeffs = fit_rbf(obs, basis)
    for q in range(p):
        good = np.isfinite(obs[:, q, 0])
        reference = np.linalg.lstsq(basis[0][good], obs[good, q, 0], rcond=None)[0]
        assert np.allclose(coeffs[q, 0], reference, atol=1e-5)


# ---- reconstruct: warnings and the saturation rule, end to end ---------------------------------


def _dataset(folder: Path, lights: np.ndarray, gain: float = 1.0, lp: bool = False) -> None:
    folder.mkdir()
    surface = render.sphere_surface((SIZE, SIZE), albedo=0.7)
    images = render.render(surface, lights, specular=0.2, cast_shadows=False)
    names = []
    for i, image in enumerate(images):
        if lp:
            counts = np.clip(np.rint(image / images.max() * 230), 0, 255).astype(np.uint8)
            names.append(f"{i:03d}.jpg")
        else:
            scale = 0.9 * 65535 / images.max() * gain
            counts = np.clip(np.rint(image * scale), 0, 65535).astype(np.uint16)
            names.append(f"{i:03d}.png")
        assert cv2.imwrite(str(folder / names[-1]), counts)
    if lp:
        rows = "".join(f"{n} {x} {y} {z}\n" for n, (x, y, z) in zip(names, lights, strict=True))
        (folder / "lights.lp").write_text(f"{len(lights)}\n{rows}")
    else:
        np.savetxt(folder / "light_directions.txt", lights)
    cv2.imwrite(str(folder / "mask.png"), surface.mask.astype(np.uint8) * 255)


@pytest.mark.parametrize(
    ("lights", "model", "dropped"),
    [("ring", "ptm", "ly²"), ("jpeg-lp", "ps", "lobe:32"), ("duplicates", "hsh2", "h3")],
)
def test_reconstruct_warns_once_and_relights(lights, model, dropped, rng, tmp_path) -> None:
    d = {"ring": ring(12), "jpeg-lp": hemisphere(5, rng),
         "duplicates": np.repeat(hemisphere(3, rng), 2, axis=0)}[lights]
    _dataset(tmp_path / "data", d, lp=lights == "jpeg-lp")
    done = runner.invoke(app, ["reconstruct", str(tmp_path / "data"), "--method", "ls", "--out",
                               str(tmp_path / "r"), "--appearance", model])
    assert done.exit_code == 0, done.output
    ours = [line for line in done.output.splitlines() if line.startswith("warning: appearance")]
    assert len(ours) == 1 and dropped in ours[0], done.output
    relit = runner.invoke(app, ["relight", str(tmp_path / "r"), "--light=0.2,0.1,0.9", "--out",
                                str(tmp_path / "pic.exr")])
    assert relit.exit_code == 0 and "warning" not in relit.output, relit.output


def test_reconstruct_fits_every_model_without_the_saturated_observations(rng, tmp_path) -> None:
    d = hemisphere(24, rng, 60)
    _dataset(tmp_path / "data", d, gain=3.0)  # much of the object saturated in most frames
    images = np.stack([cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
                       for p in sorted((tmp_path / "data").glob("*.png")) if p.stem.isdigit()])
    mask = cv2.imread(str(tmp_path / "data" / "mask.png"), 0) > 0
    counts = images[:, mask].astype(np.float64)
    saturated = counts >= 65535
    assert 0.1 < saturated.mean() < 0.9
    for model, terms in (("ptm", 6), ("rbf", 9)):
        # dropped, except where a pixel would keep fewer observations than the model's terms
        few = (~saturated).sum(axis=0) < terms
        dropped = np.where(saturated & ~few, np.nan, counts / 65535)[..., None]
        out = tmp_path / model
        done = runner.invoke(app, ["reconstruct", str(tmp_path / "data"), "--method", "ls",
                                   "--out", str(out), "--appearance", model])
        assert done.exit_code == 0, done.output
        fitted = read_appearance(out)
        if model == "rbf":  # the same basis, fitted without the saturated observations
            coeffs = fit_rbf(dropped, fitted.extra["basis"].astype(np.float64))
        else:
            coeffs = fit_appearance(model, dropped, d, mask).coefficients[mask]
        stored = fitted.coefficients[mask]
        scale = np.abs(coeffs).max()
        assert np.abs(stored - coeffs).max() < 1e-5 * scale, model


def test_a_failed_move_puts_the_earlier_pictures_back(made, tmp_path, monkeypatch) -> None:
    from ps_lab.errors import OutputError
    from ps_lab.appearance import relight as relight_module

    (tmp_path / "pic_light01.png").write_bytes(b"old one")
    real = relight_module.os.replace
    moves: list[str] = []

    def replace(src, dst):  # the second picture's move fails (a disk gone read-only)
        moves.append(Path(dst).name)
        if Path(dst).name == "pic_light02.png":
            raise OSError(30, "Read-only file system")
        return real(src, dst)

    monkeypatch.setattr(relight_module.os, "replace", replace)
    with pytest.raises(OutputError) as caught:
        relight_module.relight_result(made["ptm"], ["0,0,1", "0.3,0,1", "0,0.3,1"],
                                      tmp_path / "pic.png")
    assert "pic_light02.png" in str(caught.value) and "read-only" in str(caught.value)
    assert "pic_light02.png" in moves
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pic_light01.png"]
    assert (tmp_path / "pic_light01.png").read_bytes() == b"old one"


def test_a_ring_leaves_the_ps_model_without_ambient_only(rng) -> None:
    from ps_lab.appearance.models import PS_TERMS

    keep, warning = determined_terms("ps", ring(12), PS_TERMS)
    # on one ring lz is the same for every light: ambient (1) is lz up to a factor
    assert [PS_TERMS[k] for k in keep] == ["lx", "ly", "lz", "lobe:4", "lobe:32"]
    assert warning is not None and warning.endswith("not fitted: ambient")
    keep, warning = determined_terms("ps", hemisphere(40, rng), PS_TERMS)
    assert len(keep) == len(PS_TERMS) and warning is None
