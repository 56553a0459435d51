"""Relighting quality on held-out lights: ``ps-lab bench relight``.

Every 8th light of a capture (lights 8, 16, ...) is left out; the normals (the default solver on
the channel mean, with the reconstruction's shadow rule) and every appearance model are fitted on
the rest (the same training lights for all), in colour (each channel divided by its light's
intensity), and each model predicts the held-out images. The predictions are compared with the
held-out images in the images' own units (the solver's units times the light's intensity,
clipped to [0, 1]) over the object mask: PSNR of the pooled squared error (peak 1), and SSIM
(:func:`ssim`: Wang et al. 2004, 11 × 11 Gaussian window of σ = 1.5, K1 = 0.01, K2 = 0.03,
averaged over the mask pixels, channels and held-out lights).

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

from ps_lab.io.appearance import coefficients_per_pixel, evaluate_appearance, lambertian
from ps_lab.io.dataset import load_dataset
from ps_lab.io.lights import find_lp
from ps_lab.reconstruct import light_noise_factors, solve
from ps_lab.reconstruct._shadows import black_threshold
from ps_lab.reconstruct._solve import NOISE_SAMPLE_PIXELS
from ps_lab.reconstruct.appearance import fit_appearance

DEFAULT_FOLDER = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "diligent-8bit"
MODELS = ("lambertian", "ptm", "hsh2", "hsh3", "rbf", "ps")
HOLD_OUT_EVERY = 8


@dataclass
class RelightRow:
    """One capture: per model PSNR (dB), SSIM, coefficients per pixel and fit seconds."""

    name: str
    pixels: int
    train: int
    test: int
    cells: dict[str, dict[str, float]] = field(default_factory=dict)


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
    n: int, every: int = HOLD_OUT_EVERY, directions: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Training and held-out light indices: every ``every``-th light (8th, 16th...) held out.

    With ``directions`` (n, 3): the ``n // every`` lights farthest from the view axis (lowest
    z) are held out instead, to measure extrapolation outside the training lights' range.
    """
    index = np.arange(n)
    if directions is not None:
        held = np.zeros(n, bool)
        held[np.argsort(np.asarray(directions)[:, 2], kind="stable")[: n // every]] = True
    else:
        held = (index % every) == every - 1
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
    sample = np.unique(np.linspace(0, obs.shape[1] - 1, min(obs.shape[1], NOISE_SAMPLE_PIXELS))
                       .round().astype(np.int64))
    black = black_threshold(obs[:, sample], valid[:, sample], factors,
                            light_directions=base.light_directions[train])
    if black is not None:
        valid = valid & (obs > black[:, None])
    solution = solve(obs, base.light_directions[train], valid=valid, light_noise=factors)
    return solution.normals, valid


def _colour_albedo(obs, valid, directions, normals):
    shade = np.maximum(directions @ normals.T, 0.0)  # (n, P)
    w = valid & (shade > 0)
    num = np.einsum("np,npc->pc", shade * w, np.nan_to_num(obs))
    den = np.einsum("np->p", shade * shade * w)[:, None]
    return np.where(den > 0, num / np.maximum(den, 1e-12), 0.0)


def evaluate_capture(
    path: Path,
    models=MODELS,
    progress: Callable[[str], None] | None = None,
    *,
    extrapolate: bool = False,
) -> RelightRow:
    """Fit every model on the training lights of one capture; score the held-out lights.

    ``extrapolate``: hold out the lowest lights instead (:func:`split_lights`).
    """
    base, mask, obs = _load_colour(path)
    n = obs.shape[0]
    directions = base.light_directions / np.linalg.norm(base.light_directions, axis=1,
                                                        keepdims=True)
    train, test = split_lights(n, directions=directions if extrapolate else None)
    started = time.perf_counter()
    normals, valid = _solver_normals(base, mask, train)
    solve_seconds = time.perf_counter() - started
    albedo = _colour_albedo(obs[train], valid, directions[train], normals)
    row = RelightRow(Path(path).name, int(mask.sum()), len(train), len(test))
    height, width = mask.shape
    normal_image = np.zeros((height, width, 3), np.float32)
    normal_image[mask] = normals
    albedo_image = np.zeros((height, width, 3), np.float32)
    albedo_image[mask] = albedo
    intensities = np.asarray(base.light_intensities, np.float64).reshape(n, -1)
    truth = np.clip(obs[test] * intensities[test][:, None, :], 0.0, 1.0)
    for model in models:
        started = time.perf_counter()
        if model == "lambertian":
            appearance = None
            count = 2 + 3  # the normal and the albedo
        else:
            appearance = fit_appearance(model, obs[train], directions[train], mask,
                                        normals=normals, albedo=albedo)
            count = coefficients_per_pixel(appearance)
            if model == "ps":
                count += 2 + 3  # the normal and the albedo it relights with
        seconds = time.perf_counter() - started + (solve_seconds if model == "ps" else 0.0)
        squared, scores = [], []
        for k, light in enumerate(test):
            if appearance is None:
                picture = lambertian(directions[light], normal_image, albedo_image)
            else:
                picture = evaluate_appearance(appearance, directions[light], normal_image,
                                              albedo_image)
            predicted = np.clip(picture[mask] * intensities[light], 0.0, 1.0)
            squared.append(np.mean((predicted - truth[k]) ** 2))
            full_p = np.zeros((height, width, 3))
            full_t = np.zeros((height, width, 3))
            full_p[mask], full_t[mask] = predicted, truth[k]
            scores += [ssim(full_p[..., c], full_t[..., c], mask) for c in range(3)]
        mse = float(np.mean(squared))
        row.cells[model] = {
            "psnr": 10 * np.log10(1.0 / max(mse, 1e-20)),
            "ssim": float(np.mean(scores)),
            "coefficients": count,
            "seconds": seconds,
        }
        if progress is not None:
            progress(f"{row.name} {model}")
    return row


def run_relight(
    folder: Path, progress: Callable[[str], None] | None = None, *, extrapolate: bool = False
) -> list[RelightRow]:
    """:func:`evaluate_capture` on every capture under ``folder``."""
    return [evaluate_capture(path, progress=progress, extrapolate=extrapolate)
            for path in find_captures(folder)]


def format_table(rows: list[RelightRow], *, markdown: bool = False) -> str:
    """Per capture and model: ``PSNR dB / SSIM (coefficients per pixel)``."""
    if not rows:
        return ""
    names = list(rows[0].cells)
    head = ["capture", "train/held out", *names]
    lines = []
    for row in rows:
        cells = [row.name, f"{row.train}/{row.test}"]
        best = max(row.cells[m]["psnr"] for m in names if m not in ("ps", "lambertian"))
        for name in names:
            c = row.cells[name]
            text = f"{c['psnr']:.2f} / {c['ssim']:.4f} ({c['coefficients']})"
            if name == "ps":
                text += f" [{c['psnr'] - best:+.2f}]"
            cells.append(text)
        lines.append(cells)
    if markdown:
        out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        out += ["| " + " | ".join(cells) + " |" for cells in lines]
        return "\n".join(out)
    widths = [max(len(r[k]) for r in [head, *lines]) for k in range(len(head))]
    return "\n".join("  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True))
                     for r in [head, *lines])


def results_as_dict(rows: list[RelightRow]) -> list[dict]:
    """Plain data for JSON."""
    return [{"capture": r.name, "pixels": r.pixels, "train": r.train, "held_out": r.test,
             "results": r.cells} for r in rows]
