"""Solvers on real captures with ground truth (DiLiGenT-style folders): ``ps-lab bench real``.

Every object folder under a root (a folder holding ``light_directions.txt`` and ground-truth
normals) is loaded as ``ps-lab reconstruct`` loads it (channels divided by the light intensities
and averaged, saturated observations dropped, observations at the black level dropped as shadows
(:func:`ps_lab.reconstruct._shadows.black_threshold` on an evenly spaced sample, as the
reconstruction's store does), every mask pixel) and solved with the default (``auto``), LS, L1,
SBL, PL-LS, PL-SBL and R-PCA at their defaults, plus SBL at fixed ``lam`` values for comparison.

Relighting (every method with its defaults): every ``RELIGHT_EVERY``-th light (0, 8, 16, ...) is
left out, the method solves the others (their own shadow rule), and its normals and albedo
predict the left-out images as ``albedo * max(n.l, 0)``; the column is the PSNR (dB, peak 1: the
images' full scale) of that prediction against the left-out observations over the object mask
(every mask pixel of the kept sample, shadows included, saturated ones excluded). An albedo
defect (scale, salt-and-pepper) shows here where the normals' error does not.
The numbers go to
``docs/results.md``; ``docs/solvers.md`` explains SBL's default ``lam`` with them.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ps_lab.bench.report import method_table
from ps_lab.io.dataset import load_dataset
from ps_lab.reconstruct import angular_errors_deg, error_summary, light_noise_factors, solve
from ps_lab.reconstruct._shadows import black_threshold
from ps_lab.reconstruct._noise import NOISE_SAMPLE_PIXELS
from ps_lab.reconstruct.methods import METHODS, SOLVERS

# The repository's sibling data folder (``../shared/data/diligent-8bit`` from the repo root).
DEFAULT_FOLDER = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "diligent-8bit"
# Methods that take each light's share of the noise floor (SBL's default lambda).
_LIGHT_NOISE = tuple(row.name for row in SOLVERS if row.sbl_noise)
FIXED_LAMBDAS = (1e-6, 1e-4, 1e-2, 1e-1)
# Every RELIGHT_EVERY-th light is left out of the relighting fit.
RELIGHT_EVERY = 8


@dataclass(frozen=True)
class RealObject:
    """One object's solver inputs, as ``ps-lab reconstruct`` gives them to the solvers.

    Observations (n, P), usable mask (n, P), lights (n, 3), truth (P, 3), and each light's share
    of the noise floor (n,), which ``ps-lab reconstruct`` passes to SBL.
    """

    name: str
    observations: np.ndarray
    valid: np.ndarray
    light_directions: np.ndarray
    normal_gt: np.ndarray
    light_noise: np.ndarray
    unsaturated: np.ndarray | None = None


@dataclass
class RealRow:
    """Results of one object: per column name, mean/median error (deg) and seconds."""

    name: str
    pixels: int
    lights: int
    cells: dict[str, dict[str, float]] = field(default_factory=dict)


def find_objects(folder: Path) -> list[Path]:
    """Object folders directly under ``folder`` (light directions and ground truth), sorted."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(
        p
        for p in folder.iterdir()
        if (p / "light_directions.txt").is_file()
        and ((p / "normal_gt.npy").is_file() or (p / "Normal_gt.mat").is_file())
    )


def load_object(path: Path, every: int = 1, lights: np.ndarray | None = None) -> RealObject:
    """Load one object folder; ``every`` > 1 keeps every ``every``-th mask pixel (quick runs).

    ``lights``: indices of the lights to keep (a subset, e.g. 12 of 96), default all.
    """
    data = load_dataset(Path(path))
    if data.normal_gt is None:
        raise ValueError(f"{path}: no ground-truth normals")
    mask = data.mask
    pick = np.arange(data.images.shape[0]) if lights is None else np.asarray(lights)
    obs = data.images[pick][:, mask]
    unsaturated = data.valid[pick][:, mask]
    factors = light_noise_factors(data.light_intensities[pick])
    valid = shadow_free(obs, unsaturated, factors, data.light_directions[pick])
    gt = np.asarray(data.normal_gt, dtype=np.float64)[mask][::every]
    return RealObject(Path(path).name, obs[:, ::every], valid[:, ::every],
                      data.light_directions[pick], gt, factors, unsaturated[:, ::every])


def shadow_free(
    observations: np.ndarray,
    unsaturated: np.ndarray,
    light_noise: np.ndarray,
    light_directions: np.ndarray,
) -> np.ndarray:
    """The reconstruction's default shadow rule: ``unsaturated`` less what is black.

    The black threshold (:func:`ps_lab.reconstruct._shadows.black_threshold`) is measured on
    the same evenly spaced sample of at most ``NOISE_SAMPLE_PIXELS`` pixels as the
    reconstruction takes.

    Parameters
    ----------
    observations : ndarray of shape (n, m)
        Divided by the light intensities.
    unsaturated : ndarray of shape (n, m), bool
    light_noise : ndarray of shape (n,)
        Each light's relative noise (:func:`ps_lab.reconstruct.light_noise_factors`).
    light_directions : ndarray of shape (n, 3)

    Returns
    -------
    ndarray of shape (n, m), bool
    """
    m = observations.shape[1]
    sample = np.unique(np.linspace(0, m - 1, min(m, NOISE_SAMPLE_PIXELS)).round().astype(np.int64))
    black = black_threshold(observations[:, sample], unsaturated[:, sample], light_noise,
                            light_directions=light_directions)
    return unsaturated if black is None else unsaturated & (observations > black[:, None])


def relight_split(obj: RealObject) -> tuple[RealObject, np.ndarray]:
    """The object without every ``RELIGHT_EVERY``-th light (shadow rule redone), and those lights.

    Returns the fitting object and the indices (into ``obj``'s lights) of the left-out lights.
    """
    n = obj.observations.shape[0]
    held = np.arange(0, n, RELIGHT_EVERY)
    fit = np.setdiff1d(np.arange(n), held)
    obs = obj.observations[fit]
    unsaturated = obj.unsaturated[fit] if obj.unsaturated is not None else obj.valid[fit]
    factors = light_noise_factors_subset(obj.light_noise[fit])
    valid = shadow_free(obs, unsaturated, factors, obj.light_directions[fit])
    return RealObject(obj.name, obs, valid, obj.light_directions[fit], obj.normal_gt, factors,
                      unsaturated), held


def light_noise_factors_subset(factors: np.ndarray) -> np.ndarray:
    """Light noise factors of a subset of lights, rescaled to mean square 1 (as a fresh fit)."""
    f = np.asarray(factors, dtype=np.float64)
    return f / np.sqrt(np.mean(f**2))


def relight_psnr(normals: np.ndarray, albedo: np.ndarray, observations: np.ndarray,
                 lights: np.ndarray, usable: np.ndarray | None = None) -> float:
    """PSNR (dB, peak 1) of ``albedo * max(n.l, 0)`` against observations (n, P) under ``lights``.

    ``normals`` (P, 3), ``albedo`` (P,), ``lights`` (n, 3); ``usable`` (n, P) selects the
    observations compared (default: the finite ones).
    """
    predicted = albedo[None, :] * np.maximum(lights @ np.asarray(normals).T, 0.0)
    use = np.isfinite(observations) if usable is None else usable & np.isfinite(observations)
    mse = float(np.mean((predicted[use] - observations[use]) ** 2))
    return 10.0 * np.log10(1.0 / mse) if mse > 0 else float("inf")


def columns(methods=METHODS, lambdas=FIXED_LAMBDAS) -> list[str]:
    """Column names: the methods with defaults, then ``sbl lam=<value>`` for each fixed lambda."""
    return list(methods) + [f"sbl lam={lam:g}" for lam in lambdas]


def _column_kwargs(obj: RealObject, column: str) -> dict:
    kwargs: dict = {"method": column.split()[0]}
    if column.startswith("sbl lam="):
        kwargs["lam"] = float(column.split("=")[1])
    elif column in _LIGHT_NOISE:
        kwargs["light_noise"] = obj.light_noise
    return kwargs


def solve_column(obj: RealObject, column: str, threads: int | None = None,
                 relight: bool = True) -> dict[str, float]:
    """Mean/median angular error (deg), solve seconds and relighting PSNR of one column.

    ``psnr`` (dB, :func:`relight_psnr`) only for the methods at their defaults, with ``relight``.
    """
    started = time.perf_counter()
    sol = solve(obj.observations, obj.light_directions, valid=obj.valid, threads=threads,
                **_column_kwargs(obj, column))
    seconds = time.perf_counter() - started
    summary = error_summary(angular_errors_deg(sol.normals, obj.normal_gt))
    cell = {"mean": summary["mean"], "median": summary["median"], "seconds": seconds}
    if relight and "=" not in column:
        fit, held = relight_split(obj)
        part = solve(fit.observations, fit.light_directions, valid=fit.valid, threads=threads,
                     **_column_kwargs(fit, column))
        usable = None if obj.unsaturated is None else obj.unsaturated[held]
        cell["psnr"] = relight_psnr(part.normals, part.albedo, obj.observations[held],
                                    obj.light_directions[held], usable)
    return cell


def run_real(
    folder: Path,
    *,
    every: int = 1,
    methods=METHODS,
    lambdas=FIXED_LAMBDAS,
    threads: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[RealRow]:
    """Solve every object under ``folder`` with every column; one row per object."""
    rows = []
    for path in find_objects(folder):
        obj = load_object(path, every)
        row = RealRow(obj.name, obj.observations.shape[1], obj.observations.shape[0])
        for column in columns(methods, lambdas):
            row.cells[column] = solve_column(obj, column, threads)
            if progress is not None:
                progress(f"{obj.name} {column}")
        rows.append(row)
    return rows


def format_table(rows: list[RealRow], *, markdown: bool = False) -> str:
    """One table: per object and column ``mean/median error in degrees (solve seconds)``, and
    for the methods at their defaults the held-out relighting PSNR (``... dB``)."""

    def cell(row: RealRow, name: str, names: list[str]) -> str:
        c = row.cells[name]
        psnr = f" {c['psnr']:.1f} dB" if "psnr" in c else ""
        return f"{c['mean']:.2f}/{c['median']:.2f} ({c['seconds']:.1f} s){psnr}"

    return method_table(rows, ["object", "pixels"], lambda row: [row.name, str(row.pixels)], cell,
                        markdown=markdown)


def results_as_dict(rows: list[RealRow]) -> list[dict]:
    """Plain data for JSON."""
    return [{"object": r.name, "pixels": r.pixels, "lights": r.lights, "results": r.cells}
            for r in rows]
