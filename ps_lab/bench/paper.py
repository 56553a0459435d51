"""The experiments of Ikehata et al. (CVPR 2012), regenerated on rendered scenes.

The paper evaluates its sparse-regression photometric stereo (SBL) against least squares (LS),
L1 regression and R-PCA on a synthetic object with attached and cast shadows and Cook-Torrance
speculars, with light directions drawn at random from the upper hemisphere (here: uniform over
the cap of zenith angle <= ``max_zenith_deg`` = 60 degrees). This module renders
its own scenes with :mod:`ps_lab.render` (a sphere and the height-field "relief" object)
and rebuilds the paper's tables:

* Table 1 -- number of images 5...40, **with** shadow removal: observations whose noise-free
  rendered value is at most ``shadow_threshold`` (attached and cast shadows render to exactly 0)
  are dropped through the solvers' ``valid`` mask. Errors are taken over the pixels that keep at
  least 3 valid observations (the share is reported).
* Table 3 -- the same **without** shadow removal: shadows stay in the data as corruptions.
* Table 4 -- noise density 10...50 %: additive Gaussian noise of variance ``noise_variance`` (0.1,
  in units of the scene's largest Lambertian radiance, i.e. albedo 1 under a unit light gives 1,
  as in the paper's [0, 1] intensity scale) on that share of observations; 40 images, shadows
  and speculars kept.
* Table 5 -- every light turned by ``light_error_deg`` (5 degrees) about a random axis; the
  normals are estimated with the wrong lights and the lights are refined 1...6 times
  (:func:`ps_lab.reconstruct.refine_lights`); normal and light-direction errors per iteration.

Speculars: a white Cook-Torrance lobe of strength ``specular_strength`` (1: at roughness 0.3
its peak is about the largest Lambertian radiance) whose roughness is chosen per scene, by
bisection on the first light set, so that a share ``specular_share`` (10 %) of all observations
carries a specular part larger than ``specular_threshold`` (0.1) times the scene's largest
Lambertian radiance: a narrow, bright lobe, i.e. sparse and large corruptions. The measured share
is reported for every light set.

Every number is averaged over ``light_sets`` random light sets drawn with fixed seeds
(``numpy.random.default_rng([seed, set_index])``); each set has 40 lights and the smaller image
counts use its first k lights.
"""

from __future__ import annotations

import math
import os
import platform
import subprocess
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from ps_lab import render as _render
from ps_lab.bench.scenes import (
    LightSet,
    PreparedScene,
    albedo_scale,
    light_set_rng,
    make_surface,
    masked_observations,
    roughness_for_specular_share,
)
from ps_lab.reconstruct import metrics as _metrics
from ps_lab.reconstruct import refine_lights, solve
from ps_lab.reconstruct.methods import SOLVERS

__all__ = [
    "METHOD_LABELS",
    "PaperConfig",
    "Cell",
    "ErrorTable",
    "RefinementTable",
    "SceneStats",
    "PaperResults",
    "run_paper",
    "table_images",
    "table_noise",
    "table_refinement",
    "machine_description",
    "source_revision",
    "make_config",
    "parse_tables",
    "total_steps",
]

# Each method's name in the tables (the solver table's labels).
METHOD_LABELS = {row.name: row.label for row in SOLVERS}

Progress = Callable[[int], None] | None


@dataclass(frozen=True)
class PaperConfig:
    """Everything that defines a run of the paper's experiments (the defaults are the full run)."""

    size: int = 128
    light_sets: int = 5
    seed: int = 0
    scenes: tuple[str, ...] = ("sphere", "relief")
    methods: tuple[str, ...] = ("ls", "l1", "rpca", "sbl")
    n_lights: int = 40
    max_zenith_deg: float = 60.0
    image_counts: tuple[int, ...] = (5, 10, 15, 20, 25, 30, 35, 40)
    noise_densities: tuple[float, ...] = (0.1, 0.2, 0.3, 0.4, 0.5)
    noise_variance: float = 0.1
    specular_share: float = 0.10
    specular_strength: float = 1.0
    specular_threshold: float = 0.1
    shadow_threshold: float = 1e-6
    light_error_deg: float = 5.0
    refine_iterations: int = 6
    # R-PCA re-solves the whole low-rank problem for every refinement step: left out by default.
    refine_methods: tuple[str, ...] = ("ls", "l1", "sbl")
    tables: tuple[int, ...] = (1, 3, 4, 5)

    @classmethod
    def quick(cls, **overrides: object) -> PaperConfig:
        """The reduced version CI runs: 48 x 48 images, two light sets, no R-PCA.

        R-PCA is not part of the orderings the paper reports and costs more than the rest
        together (a full low-rank decomposition per solve), so CI leaves it to the full run.
        """
        base = cls(size=48, light_sets=2, methods=("ls", "l1", "sbl"))
        return replace(base, **overrides)  # type: ignore[arg-type]

    def command_line(self) -> str:
        """The ``ps-lab bench paper`` arguments that reproduce this configuration."""
        parts = [f"--size {self.size}", f"--light-sets {self.light_sets}", f"--seed {self.seed}"]
        if self.methods == PaperConfig.quick().methods:
            parts.insert(0, "--quick")
        if self.tables != (1, 3, 4, 5):
            parts.append("--tables " + ",".join(str(t) for t in self.tables))
        return "ps-lab bench paper " + " ".join(parts)


@dataclass(frozen=True)
class Cell:
    """One method in one row: angular error of the normals in degrees and solve time in seconds."""

    mean: float
    median: float
    seconds: float


@dataclass(frozen=True)
class ErrorTable:
    """Tables 1, 3 and 4: rows (``keys``) by method, one block per scene."""

    number: int
    title: str
    key_label: str
    keys: tuple
    scenes: tuple[str, ...]
    methods: tuple[str, ...]
    cells: dict  # (scene, key, method) -> Cell
    coverage: dict  # (scene, key) -> share of object pixels evaluated
    notes: tuple[str, ...] = ()

    def cell(self, scene: str, key: object, method: str) -> Cell:
        """The cell of ``method`` in row ``key`` of ``scene``."""
        return self.cells[(scene, key, method)]


@dataclass(frozen=True)
class RefinementTable:
    """Table 5: mean normal error and mean light-direction error (degrees) per iteration."""

    number: int
    title: str
    iterations: tuple[int, ...]  # 0 = unrefined
    scenes: tuple[str, ...]
    methods: tuple[str, ...]
    normal_error: dict  # (scene, iteration, method) -> float
    light_error: dict  # (scene, iteration, method) -> float
    seconds: dict  # (scene, method) -> float, time for all iterations of one light set
    aligned_light_error: dict = field(default_factory=dict)  # (scene, method) -> float
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class SceneStats:
    """What the rendered scene looks like: how much of it is corrupted, and by what."""

    scene: str
    pixels: int
    roughness: float
    specular_share: tuple[float, ...]  # measured per light set, all 40 observations
    shadow_share: tuple[float, ...]  # observations at or below the shadow threshold
    max_specular_ratio: float  # largest specular part / largest Lambertian radiance


@dataclass(frozen=True)
class PaperResults:
    """All tables of one run, with the configuration and the machine that made them."""

    config: PaperConfig
    scene_stats: tuple[SceneStats, ...]
    tables: tuple  # ErrorTable | RefinementTable, in the order of config.tables
    seconds: float
    machine: str
    date: str = field(default="")  # when the run started
    revision: str = field(default="unknown")  # source revision at the start


# --------------------------------------------------------------------------------------------
# Scene preparation (the pieces in ps_lab.bench.scenes)


def _prepare_scene(name: str, config: PaperConfig) -> PreparedScene:
    surface = make_surface(name, config.size, config.seed)
    mask = surface.mask
    normals = np.asarray(surface.normals, dtype=np.float64)[mask]
    scale = albedo_scale(surface)
    threshold = config.specular_threshold * scale
    roughness = None
    max_ratio = 0.0
    sets = []
    for index in range(config.light_sets):
        lights = _render.random_light_directions(
            config.n_lights, light_set_rng(config.seed, index), max_zenith_deg=config.max_zenith_deg
        )
        if roughness is None:
            # Tuned once per scene, on the first light set, then kept for every set.
            roughness = roughness_for_specular_share(
                surface,
                lights,
                strength=config.specular_strength,
                share=config.specular_share,
                threshold=threshold,
            )
        diffuse = masked_observations(_render.render(surface, lights), mask)
        observed = masked_observations(
            _render.render(
                surface, lights, specular=config.specular_strength, roughness=roughness
            ),
            mask,
        )
        specular = observed - diffuse
        max_ratio = max(max_ratio, float(specular.max()) / scale)
        sets.append(
            LightSet(
                light_directions=lights,
                observations=observed,
                specular_share=float(np.mean(specular > threshold)),
                shadow_share=float(np.mean(observed <= config.shadow_threshold)),
            )
        )
    return PreparedScene(
        name=name,
        surface=surface,
        normals=normals,
        scale=scale,
        roughness=float(roughness),
        max_specular_ratio=max_ratio,
        light_sets=tuple(sets),
    )


def _stats(scene: PreparedScene) -> SceneStats:
    return SceneStats(
        scene=scene.name,
        pixels=int(scene.normals.shape[0]),
        roughness=scene.roughness,
        specular_share=tuple(s.specular_share for s in scene.light_sets),
        shadow_share=tuple(s.shadow_share for s in scene.light_sets),
        max_specular_ratio=scene.max_specular_ratio,
    )


# --------------------------------------------------------------------------------------------
# Experiments


def _solve(observations, lights, method, valid=None):
    # A private writable copy per solve: a solver must not be able to change the shared data.
    observations = np.array(observations, dtype=np.float64, order="C")
    start = time.perf_counter()
    solution = solve(observations, lights, method=method, valid=valid)
    return solution, time.perf_counter() - start


def _average(cells: list[tuple[float, float, float]]) -> Cell:
    arr = np.asarray(cells, dtype=np.float64)
    mean, median, seconds = (float(v) for v in arr.mean(axis=0))
    return Cell(mean=mean, median=median, seconds=seconds)


def _score(config, observations, lights, valid, normal_gt, evaluated, per_method, progress):
    """Solve one light set with each of ``config.methods``; append (mean, median, seconds).

    ``evaluated``: the pixels whose errors count (None: all); ``per_method``: method -> list.
    """
    keep = slice(None) if evaluated is None else evaluated
    for method in config.methods:
        solution, seconds = _solve(observations, lights, method, valid)
        errors = _metrics.angular_errors_deg(solution.normals[keep], normal_gt[keep])
        summary = _metrics.error_summary(errors)
        per_method[method].append((summary["mean"], summary["median"], seconds))
        _tick(progress)


def _tick(progress: Progress) -> None:
    if progress is not None:
        progress(1)


def table_images(
    config: PaperConfig,
    *,
    shadow_removal: bool,
    scenes: Sequence[PreparedScene] | None = None,
    progress: Progress = None,
) -> ErrorTable:
    """Table 1 (``shadow_removal=True``) or Table 3: error against the number of images.

    Returns
    -------
    ErrorTable
        Keys are the image counts of ``config.image_counts``; cells average over light sets the
        per-set mean and median angular errors (degrees) and the solve time (seconds).
    """
    scenes = scenes if scenes is not None else [_prepare_scene(s, config) for s in config.scenes]
    cells: dict = {}
    coverage: dict = {}
    for scene in scenes:
        for count in config.image_counts:
            per_method: dict[str, list] = {m: [] for m in config.methods}
            shares = []
            for light_set in scene.light_sets:
                obs = light_set.observations[:count]
                lights = light_set.light_directions[:count]
                if shadow_removal:
                    valid = obs > config.shadow_threshold
                    evaluated = valid.sum(axis=0) >= 3
                else:
                    valid = None
                    evaluated = np.ones(obs.shape[1], dtype=bool)
                shares.append(float(evaluated.mean()))
                _score(config, obs, lights, valid, scene.normals, evaluated, per_method, progress)
            for method in config.methods:
                cells[(scene.name, count, method)] = _average(per_method[method])
            coverage[(scene.name, count)] = float(np.mean(shares))
    if shadow_removal:
        number, title = 1, "with shadow removal"
        notes = (
            f"observations whose rendered value is <= {config.shadow_threshold:g} (attached and "
            "cast shadows) are dropped via `valid`; errors over pixels that keep >= 3 observations",
        )
    else:
        number, title = 3, "without shadow removal (shadows kept as corruptions)"
        notes = ("all observations used; errors over all object pixels",)
    return ErrorTable(
        number=number,
        title=title,
        key_label="images",
        keys=tuple(config.image_counts),
        scenes=tuple(s.name for s in scenes),
        methods=tuple(config.methods),
        cells=cells,
        coverage=coverage,
        notes=notes,
    )


def table_noise(
    config: PaperConfig,
    *,
    scenes: Sequence[PreparedScene] | None = None,
    progress: Progress = None,
) -> ErrorTable:
    """Table 4: error against the share of observations with additive Gaussian noise.

    The noise is rendered by :func:`ps_lab.render.render` (``noise_fraction`` = the
    density, ``noise_sigma`` = sqrt(``noise_variance``) times the scene's largest Lambertian
    radiance), on top of the speculars and the shadows, with all ``n_lights`` images.
    """
    scenes = scenes if scenes is not None else [_prepare_scene(s, config) for s in config.scenes]
    sigma_rel = math.sqrt(config.noise_variance)
    cells: dict = {}
    coverage: dict = {}
    measured: list[str] = []
    for scene_index, scene in enumerate(scenes):
        for density in config.noise_densities:
            per_method: dict[str, list] = {m: [] for m in config.methods}
            shares = []
            for set_index, light_set in enumerate(scene.light_sets):
                rng = np.random.default_rng(
                    [config.seed, set_index, scene_index, round(density * 1000), 4]
                )
                images = _render.render(
                    scene.surface,
                    light_set.light_directions,
                    cast_shadows=True,
                    specular=config.specular_strength,
                    roughness=scene.roughness,
                    noise_sigma=sigma_rel * scene.scale,
                    noise_fraction=density,
                    rng=rng,
                )
                obs = masked_observations(images, scene.surface.mask)
                shares.append(float(np.mean(obs != light_set.observations)))
                _score(config, obs, light_set.light_directions, None, scene.normals, None,
                       per_method, progress)
            for method in config.methods:
                cells[(scene.name, density, method)] = _average(per_method[method])
            coverage[(scene.name, density)] = 1.0
            measured.append(f"{scene.name} {density:.0%}: {np.mean(shares):.1%}")
    return ErrorTable(
        number=4,
        title=(
            f"noise density, {config.n_lights} images, sigma^2 = {config.noise_variance:g} "
            "(x largest Lambertian radiance), shadows and speculars kept"
        ),
        key_label="noise",
        keys=tuple(config.noise_densities),
        scenes=tuple(s.name for s in scenes),
        methods=tuple(config.methods),
        cells=cells,
        coverage=coverage,
        notes=("measured share of noisy observations: " + ", ".join(measured),),
    )


def table_refinement(
    config: PaperConfig,
    *,
    scenes: Sequence[PreparedScene] | None = None,
    progress: Progress = None,
) -> RefinementTable:
    """Table 5: normals from lights turned by ``light_error_deg``, refined 1...K times.

    Iteration 0 is the plain solve with the wrong lights. One call of
    :func:`ps_lab.reconstruct.refine_lights` with ``iterations = refine_iterations`` and the
    ground truth reports, per iteration k, the mean normal error of the solve with the lights
    updated k times (normals with the current lights, then every light re-fitted by least squares
    with the normals fixed, on the observations the solver kept; intensities refined too) and
    the mean angle between those lights and the true ones. All ``n_lights`` images, shadows and
    speculars kept.
    """
    scenes = scenes if scenes is not None else [_prepare_scene(s, config) for s in config.scenes]
    iterations = tuple(range(config.refine_iterations + 1))
    normal_error: dict = {}
    light_error: dict = {}
    seconds: dict = {}
    aligned_error: dict = {}
    for scene in scenes:
        for method in config.refine_methods:
            normal_runs = np.zeros((len(scene.light_sets), len(iterations)))
            light_runs = np.zeros_like(normal_runs)
            elapsed = []
            aligned = []
            for set_index, light_set in enumerate(scene.light_sets):
                true_lights = light_set.light_directions
                rng = np.random.default_rng([config.seed, set_index, 5])
                lights = _render.perturb_light_directions(true_lights, config.light_error_deg, rng)
                result, elapsed_s = _refine(config, light_set, lights, scene.normals, method)
                for entry in result.history:
                    k = int(entry["iteration"])
                    normal_runs[set_index, k] = entry["normal_error_deg"]
                    light_runs[set_index, k] = entry["light_error_deg"]
                aligned.append(_rotation_free_error(result.light_directions, true_lights))
                _tick(progress)
                elapsed.append(elapsed_s)
            for k in iterations:
                normal_error[(scene.name, k, method)] = float(normal_runs[:, k].mean())
                light_error[(scene.name, k, method)] = float(light_runs[:, k].mean())
            seconds[(scene.name, method)] = float(np.mean(elapsed))
            aligned_error[(scene.name, method)] = float(np.mean(aligned))
    return RefinementTable(
        number=5,
        title=(
            f"every light turned {config.light_error_deg:g} deg in a random direction, "
            f"{config.n_lights} images, shadows and speculars kept; iteration 0 = unrefined"
        ),
        iterations=iterations,
        scenes=tuple(s.name for s in scenes),
        methods=tuple(config.refine_methods),
        normal_error=normal_error,
        light_error=light_error,
        seconds=seconds,
        aligned_light_error=aligned_error,
        notes=(
            "light error: mean angle between the refined and the true light directions; "
            "a common rotation of all lights cannot be recovered, so it need not reach 0. "
            f"Row 'rot. removed': the light error after {config.refine_iterations} iterations "
            "once the best common rotation is taken out (what refinement can fix); "
            "row 'time s': seconds for all iterations of one light set",
        ),
    )


def _refine(config, light_set, lights, normal_gt, method):
    observations = np.array(light_set.observations, dtype=np.float64, order="C")
    start = time.perf_counter()
    result = refine_lights(
        observations,
        lights,
        method=method,
        iterations=config.refine_iterations,
        normal_gt=normal_gt,
        light_directions_gt=light_set.light_directions,
    )
    return result, time.perf_counter() - start


def _rotation_free_error(light_directions: np.ndarray, reference: np.ndarray) -> float:
    """Mean angle (degrees) between two light sets after the best common rotation (Kabsch)."""
    a = np.asarray(light_directions, dtype=np.float64)
    b = np.asarray(reference, dtype=np.float64)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt))
    rotation = u @ np.diag([1.0, 1.0, d]) @ vt  # a @ rotation ~ b
    return float(_metrics.angular_errors_deg(a @ rotation, b).mean())


def _solve_count(config: PaperConfig) -> int:
    per_scene = config.light_sets * (
        (len(config.image_counts) * len(config.methods) * sum(t in (1, 3) for t in config.tables))
        + (len(config.noise_densities) * len(config.methods) * (4 in config.tables))
        + (len(config.refine_methods) * (5 in config.tables))
    )
    return per_scene * len(config.scenes)


def machine_description() -> str:
    """CPU model and core count of this machine (from /proc/cpuinfo where available)."""
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return (
        f"{model}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}, numpy {np.__version__}"
    )


def source_revision() -> str:
    """``git describe``-style revision of the checkout ps-lab runs from ("unknown" if none)."""
    root = Path(__file__).resolve().parent.parent
    try:
        out = subprocess.run(
            ["git", "-C", str(root), "describe", "--always", "--dirty"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip() or "unknown"


def run_paper(config: PaperConfig, *, progress: Progress = None) -> PaperResults:
    """Render the scenes once and run every table of ``config.tables``.

    Parameters
    ----------
    config : PaperConfig
        What to run.
    progress : callable, optional
        Called with 1 after every solve (see :func:`total_steps`).

    Returns
    -------
    PaperResults
    """
    start = time.perf_counter()
    revision = source_revision()
    started = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    scenes = [_prepare_scene(name, config) for name in config.scenes]
    tables: list = []
    for number in config.tables:
        if number in (1, 3):
            removal = number == 1
            tables.append(
                table_images(config, shadow_removal=removal, scenes=scenes, progress=progress)
            )
        elif number == 4:
            tables.append(table_noise(config, scenes=scenes, progress=progress))
        elif number == 5:
            tables.append(table_refinement(config, scenes=scenes, progress=progress))
        else:
            raise ValueError(f"no table {number} (the paper's tables are 1, 3, 4, 5)")
    return PaperResults(
        config=config,
        scene_stats=tuple(_stats(s) for s in scenes),
        tables=tuple(tables),
        seconds=time.perf_counter() - start,
        machine=machine_description(),
        date=started,
        revision=revision,
    )


def total_steps(config: PaperConfig) -> int:
    """Number of progress ticks :func:`run_paper` makes (one per solve)."""
    return _solve_count(config)


def parse_tables(text: str) -> tuple[int, ...]:
    """Parse ``"1,3,4,5"`` into a tuple of table numbers."""
    try:
        numbers = tuple(int(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise ValueError(f"--tables takes numbers separated by commas, got {text!r}") from None
    bad = [n for n in numbers if n not in (1, 3, 4, 5)]
    if bad or not numbers:
        raise ValueError(f"--tables: the paper's tables are 1, 3, 4, 5 (got {text!r})")
    return numbers


def make_config(
    *,
    quick: bool = False,
    size: int | None = None,
    light_sets: int | None = None,
    seed: int | None = None,
    tables: tuple[int, ...] | None = None,
) -> PaperConfig:
    """The configuration for the command-line options (None = the default of the mode)."""
    config = PaperConfig.quick() if quick else PaperConfig()
    overrides = {
        k: v
        for k, v in {"size": size, "light_sets": light_sets, "seed": seed, "tables": tables}.items()
        if v is not None
    }
    if overrides.get("size", config.size) < 8:
        raise ValueError("--size must be at least 8 pixels")
    if overrides.get("light_sets", config.light_sets) < 1:
        raise ValueError("--light-sets must be at least 1")
    return replace(config, **overrides)
