"""Relighting quality on held-out lights: ``ps-lab bench relight``.

Eight folds: fold ``f`` holds out the lights of index ``i % 8 == f`` (0-based, the file's order),
so that every light is held out once. In each fold the normals (the default solver on the channel
mean, with the reconstruction's shadow rule) and every appearance model are fitted on the other
lights only (the same training lights for all; ``auto``'s cross-validated choice sees only them),
in colour (each channel divided by its light's intensity), and each model predicts the held-out
images. The judged metric (RealRTI's): the prediction and the held-out image in the images' own
units (the solver's units times the light's intensity, clipped to [0, 1]) reduced to grey (the
channel mean of linear RGB), sRGB-encoded, PSNR per image at peak 255 over the object mask; mean
over the held-out images, then over the folds. SSIM (:func:`ssim`: Wang et al. 2004, 11 × 11
Gaussian window of σ = 1.5, K1 = 0.01, K2 = 0.03, on the same grey sRGB images) is averaged the
same way. ``--extrapolate``: one split instead, the lowest eighth of the lights held out.

``lambertian`` is ``ρ_c · max(n·l, 0)`` with the solver's normal and a per-channel albedo fitted
to the training observations the solver kept (least squares with the normal fixed).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ps_lab.appearance.fit import fit_appearance
from ps_lab.appearance.models import coefficients_per_pixel, evaluate_appearance, lambertian
from ps_lab.bench.real import shadow_free
from ps_lab.bench.report import method_table
from ps_lab.io.dataset import load_dataset
from ps_lab.io.encoding import linear_to_srgb
from ps_lab.io.light_files import find_lp
from ps_lab.reconstruct import light_noise_factors, solve

DEFAULT_FOLDER = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "diligent-8bit"
MODELS = ("auto", "ps", "lambertian", "ptm", "hsh2", "hsh3", "rbf", "bln", "gp")
HOLD_OUT_EVERY = 8


@dataclass
class RelightRow:
    """One capture: per model the fold-mean PSNR (dB) and SSIM, per fold PSNR (``folds``),
    coefficients per pixel and fit seconds (summed over folds); ``choices``: per fold what
    ``auto`` chose."""

    name: str
    pixels: int
    train: int
    test: int
    cells: dict[str, dict] = field(default_factory=dict)
    choices: list[str] = field(default_factory=list)


def find_captures(folder: Path) -> list[Path]:
    """``folder`` itself when it is a capture (light directions or an .lp file), else its
    sub-folders that are, sorted."""
    folder = Path(folder)

    def is_capture(p: Path) -> bool:
        return (p / "light_directions.txt").is_file() or find_lp(p) is not None

    if not folder.is_dir():
        return []
    if is_capture(folder):
        return [folder]
    return sorted(p for p in folder.iterdir() if p.is_dir() and is_capture(p))


def split_lights(
    n: int, every: int = HOLD_OUT_EVERY, directions: np.ndarray | None = None,
    fold: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Training and held-out light indices: the lights ``i % every == fold`` held out (default
    fold ``every − 1``: the 8th, 16th... light).

    With ``directions`` (n, 3): the ``n // every`` lights farthest from the view axis (lowest
    z) are held out instead, to measure extrapolation outside the training lights' range.
    """
    index = np.arange(n)
    if directions is not None:
        held = np.zeros(n, bool)
        held[np.argsort(np.asarray(directions)[:, 2], kind="stable")[: n // every]] = True
    else:
        held = (index % every) == (every - 1 if fold is None else fold)
    return index[~held], index[held]


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray, peak: float = 1.0) -> float:
    """Mean SSIM (Wang et al. 2004) of two (H, W) images over ``mask`` (Gaussian window).

    Parameters
    ----------
    a, b : ndarray of shape (H, W)
    mask : ndarray of shape (H, W), bool
    peak : float
        Dynamic range L.

    Returns
    -------
    float

    """
    c1, c2 = (0.01 * peak) ** 2, (0.03 * peak) ** 2
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)

    def blur(x: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(x, (11, 11), 1.5, borderType=cv2.BORDER_REFLECT)

    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a**2
    var_b = blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    value = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / (
        (mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2)
    )
    return float(value[mask].mean())


def _load_colour(path: Path):
    data = {c: load_dataset(path, channel=c) for c in ("mean", "r", "g", "b")}
    base = data["mean"]
    mask = base.mask
    obs = np.stack([data[c].images[:, mask] for c in "rgb"], axis=-1)  # (n, P, 3)
    return base, mask, obs


def _solver_normals(base, mask, train):
    obs, valid = base.images[train][:, mask], base.valid[train][:, mask]
    factors = light_noise_factors(base.light_intensities[train])
    valid = shadow_free(obs, valid, factors, base.light_directions[train])
    solution = solve(obs, base.light_directions[train], valid=valid, light_noise=factors)
    return solution.normals, valid


def _colour_albedo(obs, valid, directions, normals):
    shade = np.maximum(directions @ normals.T, 0.0)  # (n, P)
    w = valid & (shade > 0)
    num = np.einsum("np,npc->pc", shade * w, np.nan_to_num(obs))
    den = np.einsum("np->p", shade * shade * w)[:, None]
    return np.where(den > 0, num / np.maximum(den, 1e-12), 0.0)


def _grey_srgb(linear: np.ndarray) -> np.ndarray:
    """(..., P, C) linear in [0, 1] -> (..., P) grey sRGB at peak 255."""
    return linear_to_srgb(np.mean(linear, axis=-1)) * 255.0


def _fold_splits(n: int, directions: np.ndarray, extrapolate: bool):
    if extrapolate:
        return [split_lights(n, directions=directions)]
    return [split_lights(n, fold=f) for f in range(HOLD_OUT_EVERY)]


def evaluate_capture(
    path: Path,
    models=MODELS,
    progress: Callable[[str], None] | None = None,
    *,
    extrapolate: bool = False,
) -> RelightRow:
    """Every model on every fold of one capture (module docstring); ``progress`` is called once
    per model and fold.

    ``extrapolate``: one split, the lowest lights held out (:func:`split_lights`).
    """
    base, mask, obs = _load_colour(path)
    n = obs.shape[0]
    directions = base.light_directions / np.linalg.norm(base.light_directions, axis=1,
                                                        keepdims=True)
    splits = _fold_splits(n, directions, extrapolate)
    row = RelightRow(Path(path).name, int(mask.sum()), n - len(splits[0][1]), len(splits[0][1]))
    height, width = mask.shape
    intensities = np.asarray(base.light_intensities, np.float64).reshape(n, -1)
    cells = {m: {"folds": [], "ssim_folds": [], "coefficients": 0, "seconds": 0.0}
             for m in models}
    for train, test in splits:
        started = time.perf_counter()
        solved = bool({"ps", "lambertian"} & set(models))
        if solved:
            normals, valid = _solver_normals(base, mask, train)
            albedo = _colour_albedo(obs[train], valid, directions[train], normals)
        else:  # the interpolating models need neither (auto then does not consider ps)
            normals, albedo = np.zeros((obs.shape[1], 3)), np.zeros((obs.shape[1], 3))
        solve_seconds = time.perf_counter() - started
        normal_image = np.zeros((height, width, 3), np.float32)
        normal_image[mask] = normals
        albedo_image = np.zeros((height, width, 3), np.float32)
        albedo_image[mask] = albedo
        truth = _grey_srgb(np.clip(obs[test] * intensities[test][:, None, :], 0.0, 1.0))
        for model in models:
            started = time.perf_counter()
            appearance = None
            count = 2 + 3  # lambertian: the normal and the albedo
            if model != "lambertian":
                appearance = fit_appearance(model, obs[train], directions[train], mask,
                                            normals=normals if solved else None,
                                            albedo=albedo if solved else None)
                count = coefficients_per_pixel(appearance) + (5 if model == "ps" else 0)
                if model == "auto":
                    row.choices.append(f"{appearance.model}/{appearance.meta.get('space')}")
            seconds = time.perf_counter() - started + (solve_seconds if model == "ps" else 0.0)
            scores, ssims = [], []
            for k, light in enumerate(test):
                if appearance is None:
                    picture = lambertian(directions[light], normal_image, albedo_image)
                else:
                    picture = evaluate_appearance(appearance, directions[light], normal_image,
                                                  albedo_image)
                predicted = _grey_srgb(np.clip(picture[mask] * intensities[light], 0.0, 1.0))
                mse = float(np.mean((predicted - truth[k]) ** 2))
                scores.append(10 * np.log10(255.0**2 / max(mse, 1e-12)))
                full_p, full_t = np.zeros((height, width)), np.zeros((height, width))
                full_p[mask], full_t[mask] = predicted, truth[k]
                ssims.append(ssim(full_p, full_t, mask, peak=255.0))
            cell = cells[model]
            cell["folds"].append(float(np.mean(scores)))
            cell["ssim_folds"].append(float(np.mean(ssims)))
            cell["coefficients"] = count
            cell["seconds"] += seconds
            if progress is not None:
                progress(f"{row.name} {model}")
    for model, cell in cells.items():
        cell["psnr"] = float(np.mean(cell["folds"]))
        cell["ssim"] = float(np.mean(cell.pop("ssim_folds")))
        row.cells[model] = cell
    return row


def folds_of(path: Path, *, extrapolate: bool = False) -> int:
    """How many folds :func:`evaluate_capture` runs (1 with ``extrapolate``, else 8)."""
    return 1 if extrapolate else HOLD_OUT_EVERY


def run_relight(
    folder: Path, progress: Callable[[str], None] | None = None, *, extrapolate: bool = False
) -> list[RelightRow]:
    """:func:`evaluate_capture` on every capture under ``folder``."""
    return [evaluate_capture(path, progress=progress, extrapolate=extrapolate)
            for path in find_captures(folder)]


def format_table(rows: list[RelightRow], *, markdown: bool = False) -> str:
    """Per capture and model: ``fold-mean PSNR dB / SSIM (coefficients per pixel)
    [worst fold]``; ``auto`` also its margin over the best other model ``{mean, min per fold}``."""

    def cell(row: RelightRow, name: str, names: list[str]) -> str:
        c = row.cells[name]
        text = f"{c['psnr']:.2f} / {c['ssim']:.4f} ({c['coefficients']}) [{min(c['folds']):.2f}]"
        others = [m for m in names if m != "auto"]
        if name == "auto" and others:
            folds = np.array([row.cells[m]["folds"] for m in others])
            mean = c["psnr"] - folds.mean(axis=1).max()
            worst = float(np.min(np.array(c["folds"]) - folds.max(axis=0)))
            text += f" {{{mean:+.2f}, {worst:+.2f}}}"
        return text

    return method_table(rows, ["capture", "train/held out"],
                        lambda row: [row.name, f"{row.train}/{row.test}"], cell, markdown=markdown)


def results_as_dict(rows: list[RelightRow]) -> list[dict]:
    """Plain data for JSON."""
    return [{"capture": r.name, "pixels": r.pixels, "train": r.train, "held_out": r.test,
             "auto_choices": r.choices, "results": r.cells} for r in rows]
