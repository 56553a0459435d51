"""What one reconstruction is asked to do: :class:`ReconstructOptions`, validated where it is made.

The options object is passed whole to each stage of :mod:`ps_lab.reconstruct.pipeline`; this
module also holds the memory model that sets the band height (:func:`band_pixels`) and the
command-line sizes it accepts (:func:`parse_memory_size`).
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ps_lab.appearance.models import APPEARANCE_MODELS
from ps_lab.errors import OutputError
from ps_lab.io.encoding import ENCODINGS
from ps_lab.io.images import available_memory
from ps_lab.io.normal_maps import CONVENTIONS
from ps_lab.reconstruct._solution import SolverInputError
from ps_lab.reconstruct.depth import DepthOptions
from ps_lab.reconstruct.methods import DEFAULT_METHOD, METHODS, methods_with, solver

__all__ = [
    "BYTES_PER_OBSERVATION",
    "BYTES_PER_PIXEL",
    "COLOUR_BYTES_PER_OBSERVATION",
    "DEFAULT_MEMORY_SHARE",
    "MAX_BAND_PIXELS",
    "LIGHT_MODELS",
    "NEAR_BYTES_PER_OBSERVATION",
    "SOLVER_OPTIONS",
    "STAGING",
    "ReconstructOptions",
    "auto_memory_budget",
    "band_pixels",
    "parse_memory_budget",
    "parse_memory_size",
]

#: The default memory budget (``--memory-budget auto``): this share of the memory available when
#: the reconstruction starts (``MemAvailable``), within the bounds below.
DEFAULT_MEMORY_SHARE = 0.5
MIN_AUTO_BUDGET = 256 << 20
MAX_AUTO_BUDGET = 64 << 30
#: A band holds at most this many mask pixels whatever the budget: a band's solve is cut into
#: tiles anyway, so larger bands only hold more memory (R-PCA, fitted per band, is not capped).
MAX_BAND_PIXELS = 1 << 18
# Bytes held per observation of a band while it is solved: the float32 observations, their
# validity, the solver's usable and outlier masks, and headroom for the refinement sums.
BYTES_PER_OBSERVATION = 12
# Colour frames: bytes per observation of a band for its three colour channels (float32), staged
# beside the solve channel and read for the colour albedo (reconstruct/_colour.py).
COLOUR_BYTES_PER_OBSERVATION = 12
# Bytes per pixel of a band: the solver's per-pixel results and the band's output images.
BYTES_PER_PIXEL = 200
_SIZE_UNITS = {"": 1 << 20, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}
STAGING = ("auto", "memory", "file")
LIGHT_MODELS = ("auto", "near", "directional")
LED_MODELS = ("auto", "isotropic", "beam", "flat-field")
# Per-pixel light vectors (float64 x 3) held beside a band's observations in near-light mode.
NEAR_BYTES_PER_OBSERVATION = 24

ProgressBars = Callable[[int, str], Any]


def parse_memory_size(text: str) -> int:
    """Parse a memory size such as ``"512MB"``, ``"1.5G"``, ``"2 GiB"`` or ``"800"`` (MB), in bytes.

    Raises
    ------
    OutputError
        Not a positive size.

    """
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([kKmMgGtT]?)(?:i?[bB])?\s*", str(text))
    if match is None:
        raise OutputError(f"--memory-budget {text!r}: expected a size such as 800MB or 2GB")
    size = int(float(match.group(1)) * _SIZE_UNITS[match.group(2).lower()])
    if size <= 0:
        raise OutputError(f"--memory-budget {text!r} must be positive")
    return size


# Solver fields of ReconstructOptions -> (command-line flag, methods they apply to: the solver
# table's, methods.py).
SOLVER_OPTIONS = {
    name: (flag, methods_with(name))
    for name, flag in (("lam", "--lambda"), ("sigma_x2", "--sigma-x2"), ("max_iter", "--max-iter"),
                       ("tol", "--tol"), ("segments", "--segments"))
}
# Most segments of the piecewise-linear models (reconstruct/_pl_model.py).
MAX_SEGMENTS = 8


def _check_solver_options(options: ReconstructOptions) -> None:
    """Raise :class:`SolverInputError` for a bad solver field.

    A field must be finite and positive (``max_iter`` whole) and apply to ``options.method``.
    """
    for name, (flag, methods) in SOLVER_OPTIONS.items():
        value = getattr(options, name)
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SolverInputError(f"{flag} must be a number, got {value!r}")
        if not math.isfinite(value) or value <= 0:
            raise SolverInputError(f"{flag} must be finite and positive, got {value!r}")
        if name in ("max_iter", "segments") and int(value) != value:
            raise SolverInputError(f"{flag} must be a whole number, got {value!r}")
        if name == "segments" and value > MAX_SEGMENTS:
            raise SolverInputError(f"{flag} must be at most {MAX_SEGMENTS}, got {value!r}")
        if options.method not in methods:
            raise SolverInputError(
                f"{flag} does not apply to method {options.method} (only {', '.join(methods)})"
            )


def auto_memory_budget(available: int | None = None) -> int:
    """``--memory-budget auto``: :data:`DEFAULT_MEMORY_SHARE` of the available memory, bounded.

    Parameters
    ----------
    available : int or None
        Bytes available (default: ``MemAvailable`` now, :func:`ps_lab.io.images.available_memory`).
    """
    have = available_memory() if available is None else int(available)
    return int(min(max(DEFAULT_MEMORY_SHARE * have, MIN_AUTO_BUDGET), MAX_AUTO_BUDGET))


def parse_memory_budget(text: str) -> int | None:
    """``--memory-budget``: ``auto`` (None: :func:`auto_memory_budget` when the run starts) or a
    size (:func:`parse_memory_size`)."""
    if str(text).strip().lower() == "auto":
        return None
    try:
        return parse_memory_size(text)
    except OutputError as exc:
        raise OutputError(str(exc).replace("expected a size", "expected auto or a size")) from None


def band_pixels(memory_budget: int, n_lights: int) -> int:
    """Most mask pixels per band that keep one band's solve within ``memory_budget`` bytes."""
    per_pixel = n_lights * BYTES_PER_OBSERVATION + BYTES_PER_PIXEL
    return max(int(memory_budget) // per_pixel, 1)


@dataclass(frozen=True)
class ReconstructOptions:
    """Every choice of one reconstruction; passed whole to each stage of the pipeline.

    Attributes
    ----------
    method : str
        Solver, one of ``ps_lab.reconstruct.METHODS`` (the solver table,
        :mod:`ps_lab.reconstruct.methods`; ``auto``: per pixel SBL or PL-SBL, by their evidence,
        docs/solvers.md).
        Noise level and outlier threshold are estimated once for the whole image; R-PCA's
        low-rank model is fitted per band.
    channel : {"r", "g", "b", "mean"}
        As for :func:`ps_lab.io.dataset.load_dataset`.
    shadow_threshold : float or None
        Observations at or below it are dropped (as for :func:`ps_lab.io.dataset.load_dataset`).
    threads : int or None
        Solver threads (default all cores).
    refine_lights : int
        Iterations of light refinement (0 = none); the refined lights are written as
        ``light_directions.txt`` / ``light_intensities.txt``.
    fixed_intensities : bool
        Refine directions only.
    memory_budget : int or str or None
        Bytes, or a size such as ``"1GB"`` (:func:`parse_memory_size`; stored as bytes), for the
        staged observations (kept in memory when they fit with one band's work, else in a
        temporary file) and one band's solve (sets the band height). None:
        :func:`auto_memory_budget` when the run starts (half the available memory).
    staging : {"auto", "memory", "file"}
        Backing of the observation store: in memory when small (``auto``), or forced.
    lights : {"auto", "near", "directional"}
        Light model: ``near`` solves with per-pixel light vectors from ``light_positions.txt``
        (LEDs at a finite distance, alternating normals and depth; :mod:`ps_lab.reconstruct.near`),
        ``directional`` with ``light_directions.txt`` alone; ``auto`` is near when the dataset
        has ``light_positions.txt``.
    scheduler : str or None
        Address of a Dask scheduler (``tcp://host:8786``): the frames are staged and the bands
        solved as tasks on its workers (:mod:`ps_lab.reconstruct.distributed`; the dataset and
        the output folder must be on a filesystem the workers share). None: in this process.
    lam, sigma_x2, max_iter, tol : float, float, int, float, or None
        Solver parameters in the units of ``docs/solvers.md`` (relative to each pixel's robust
        scale); None keeps the method's default. ``lam``: SBL's noise variance, or R-PCA's
        sparse weight; ``sigma_x2``: SBL's prior variance of ``x``; ``max_iter`` and ``tol``:
        SBL, L1 and R-PCA. Each must be finite and positive, and apply to ``method``.
        (``auto`` and ``plsbl`` take SBL's.)
    segments : int or None
        Segments of the piecewise-linear models (``auto``, ``plls``, ``plsbl``; 1 to 8, default
        3).
    depth : {"poisson", "bilateral"} or None
        Also integrate the normals into depth maps and a mesh (:mod:`ps_lab.reconstruct.depth`).
    encoding : {"auto", "linear", "srgb"}
        How integer frames map to light (:mod:`ps_lab.io.encoding`; ``auto``: the files'
        metadata, sRGB for JPEG).
    normal_map : {"opengl", "directx"}
        The y axis of ``normal16.png`` and ``normals.exr``: up (OpenGL) or down (DirectX).
    object_outline : float or None
        Near lights: height of the object's outline above the spheres' plane (pixels; for an
        object on the spheres' table, minus their radius). None: the dataset's
        ``object_outline.txt`` (``ps-lab calibrate --object``), else found from the shading
        (:func:`ps_lab.reconstruct.near.near_light_rounds`).
    appearance : {"auto", "ps", "ptm", "hsh2", "hsh3", "rbf", "bln", "gp", "none"}
        The appearance model fitted per pixel after the normals (``appearance.npz``;
        :mod:`ps_lab.appearance.fit`, docs/appearance.md); ``auto``: the model and fit
        space of best cross-validated relighting (:mod:`ps_lab.appearance.choice`);
        ``none``: no fit.
    led_model : {"auto", "isotropic", "beam", "flat-field"}
        Near lights: the LEDs' emission. ``isotropic`` (the intensities at the origin and
        ``light_anisotropy.txt``'s exponents about the direction to the origin), ``beam``
        (``light_axes.txt`` and ``light_anisotropy.txt``: each LED's fitted axis and exponent),
        ``flat-field`` (``flat_field.npz``: gains measured on a board); ``auto``: flat-field,
        else beam, else isotropic, by the files present (``ps-lab calibrate --flat-field``).
    """

    method: str = DEFAULT_METHOD
    channel: str = "mean"
    shadow_threshold: float | None = None
    threads: int | None = None
    refine_lights: int = 0
    fixed_intensities: bool = False
    memory_budget: int | None = None
    staging: str = "auto"
    lights: str = "auto"
    scheduler: str | None = None
    lam: float | None = None
    sigma_x2: float | None = None
    max_iter: int | None = None
    tol: float | None = None
    segments: int | None = None

    depth: str | None = None
    encoding: str = "auto"
    normal_map: str = "opengl"
    object_outline: float | None = None
    appearance: str = "auto"
    led_model: str = "auto"

    def __post_init__(self) -> None:
        if self.appearance not in ("auto", *APPEARANCE_MODELS):
            raise OutputError(
                f"--appearance must be one of auto, {', '.join(APPEARANCE_MODELS)}, "
                f"got {self.appearance!r}"
            )
        if self.encoding not in ENCODINGS:
            raise OutputError(
                f"--encoding must be one of {', '.join(ENCODINGS)}, got {self.encoding!r}"
            )
        if self.normal_map not in CONVENTIONS:
            raise OutputError(
                f"--normal-map must be one of {', '.join(CONVENTIONS)}, got {self.normal_map!r}"
            )
        if self.depth is not None:
            DepthOptions(method=self.depth)  # validates the method
        _check_solver_options(self)
        if self.shadow_threshold is not None and not math.isfinite(self.shadow_threshold):
            raise OutputError(f"--shadow-threshold {self.shadow_threshold} is not a finite number")
        if self.object_outline is not None and not math.isfinite(self.object_outline):
            raise OutputError(f"object outline height {self.object_outline} is not finite")
        if self.staging not in STAGING:
            raise OutputError(f"staging must be auto, memory or file, got {self.staging!r}")
        if self.led_model not in LED_MODELS:
            raise OutputError(f"--led-model must be one of {', '.join(LED_MODELS)}, "
                              f"got {self.led_model!r}")
        if self.lights not in LIGHT_MODELS:
            raise OutputError(f"lights must be auto, near or directional, got {self.lights!r}")
        budget = self.memory_budget
        if budget is None:
            pass
        elif not isinstance(budget, int):
            object.__setattr__(self, "memory_budget", parse_memory_size(budget))
        elif budget <= 0:
            raise OutputError(f"memory budget must be positive, got {budget}")

    def solver_parameters(self) -> dict[str, Any]:
        """Keyword arguments for :func:`ps_lab.reconstruct.solve` that these options fix.

        The solver fields that are set, each under the method's keyword (the solver table's
        ``options``: ``lam`` is R-PCA's ``lam_sparse``); every band's solve receives them.
        """
        given = {name: getattr(self, name) for name in SOLVER_OPTIONS}
        names = solver(self.method).options if self.method in METHODS else {}
        return {names.get(k, k): v for k, v in given.items() if v is not None}

    def replace(self, **changes: Any) -> ReconstructOptions:
        """Return a copy with some fields changed (:func:`dataclasses.replace`)."""
        return dataclasses.replace(self, **changes)
