"""`ps-lab reconstruct`: surface normals from a dataset folder or capture run."""

from __future__ import annotations

import sys
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Annotated, Any

import typer

from ps_lab._cli_util import choices, from_params, lab_command, progress_bar
from ps_lab.appearance.models import APPEARANCE_MODELS
from ps_lab.commands._shared_options import Encoding, EncodingOption
from ps_lab.errors import DatasetError
from ps_lab.io.frames import FolderOfDatasetsError
from ps_lab.reconstruct.methods import DEFAULT_METHOD, METHODS, method_help
from ps_lab.reconstruct.pipeline import (
    ReconstructOptions,
    parse_memory_budget,
    reconstruct_to_folder,
)


Method = choices("Method", " ".join(METHODS), "The solver table's methods (reconstruct/methods.py).")


AppearanceModel = choices(
    "AppearanceModel",
    " ".join(("auto", *APPEARANCE_MODELS)),
    "Appearance models fitted per pixel (``ps_lab.appearance.fit``), or auto (chosen per capture).",
)


AppearanceOption = Annotated[
    AppearanceModel,
    typer.Option(
        case_sensitive=False,
        help="Appearance model fitted per pixel for relighting (appearance.npz): auto (the "
        "model and fit space, linear or sRGB, that best predict each light from the others), "
        "ps (ps-lab's: the normal and albedo plus gloss terms), ptm, hsh2, hsh3, rbf, bln "
        "(as RTI tools fit them), gp (kernel regression over the lights) or none. See "
        "docs/appearance.md.",
    ),
]


Lights = choices(
    "Lights",
    "auto near directional",
    "Light model: LEDs at a finite distance or lights at infinity.",
)
LedModel = choices(
    "LedModel", "auto isotropic beam flat-field", "Near lights: the LEDs' emission model."
)
Channel = choices(
    "Channel", "mean r g b", "How colour observations become one value per light and pixel."
)
DepthMethod = choices(
    "DepthMethod",
    "poisson bilateral",
    "Normal integration methods (see ``ps_lab.reconstruct.integrate``).",
)


# Every choice is case-insensitive (`--method SBL`), as a lab user types it.


# Options that `ps-lab batch` shares with `ps-lab reconstruct` (one declaration each).
MethodOption = Annotated[
    Method,
    typer.Option(
        case_sensitive=False,
        help=method_help(),
    ),
]
SegmentsOption = Annotated[
    int | None,
    typer.Option(help="Segments of plls / plsbl / auto (1-8; default 3).", show_default=False),
]
ShadowThresholdOption = Annotated[
    float | None,
    typer.Option(
        help="Drop observations at or below this value (after intensity division). "
        "Default: 3 sigma of the noise at black, measured on the negative observations "
        "of dark-subtracted frames; without negatives, each light's clipped black level plus "
        "3 noise floors (0 for a noise-free render); a negative value keeps all.",
        show_default=False,
    ),
]


ChannelOption = Annotated[
    Channel,
    typer.Option(
        case_sensitive=False, help="Colour rule: mean of the channels, or one of r, g, b."
    ),
]
RefineLightsOption = Annotated[
    int, typer.Option(min=0, help="Iterations of light refinement (0 = none).")
]
FixedIntensitiesOption = Annotated[
    bool, typer.Option(help="With --refine-lights: refine directions only.")
]
LightsOption = Annotated[
    Lights,
    typer.Option(
        case_sensitive=False,
        help="near: per-pixel lights from light_positions.txt (LEDs at a finite distance); "
        "directional: light_directions.txt only; auto: near when light_positions.txt exists."
    ),
]
LambdaOption = Annotated[
    float | None,
    typer.Option(
        "--lambda",
        help="SBL noise variance, or R-PCA sparse weight (relative units, docs/solvers.md; "
        "default: from the data).",
        show_default=False,
    ),
]
SigmaX2Option = Annotated[
    float | None,
    typer.Option(
        help="SBL prior variance of albedo x normal (relative; default 1e6).", show_default=False
    ),
]
MaxIterOption = Annotated[
    int | None,
    typer.Option(
        help="Iterations at most (defaults: sbl 100, l1 100, rpca 500).", show_default=False
    ),
]
TolOption = Annotated[
    float | None,
    typer.Option(
        help="Convergence tolerance (docs/solvers.md; defaults: sbl from the noise level, at "
        "least 1e-4; l1 1e-6; rpca 1e-7).",
        show_default=False,
    ),
]


NormalMap = choices(
    "NormalMap", "opengl directx", "Normal-map conventions (``ps_lab.io.normal_maps``)."
)


DepthOption = Annotated[
    DepthMethod | None,
    typer.Option(
        case_sensitive=False,
        help="Also integrate depth and a mesh: poisson or bilateral (see ps-lab integrate).",
        show_default=False,
    ),
]
MemoryBudgetOption = Annotated[
    str,
    typer.Option(
        metavar="<size>",
        help="Memory for the staged images and one row band's solve, e.g. 800MB or 2GB: "
        "the images stay in memory when they fit, else go to a temporary file; auto (the "
        "default): half the memory available when the run starts.",
    ),
]


@lab_command
def reconstruct(
    dataset: Annotated[
        Path,
        typer.Argument(help="Image folder (DiLiGenT layout) or capture run.", show_default=False),
    ],
    method: MethodOption = Method(DEFAULT_METHOD),
    out: Annotated[
        Path | None,
        typer.Option(help="Output folder (default: DATASET/recon/<method>).", show_default=False),
    ] = None,
    shadow_threshold: ShadowThresholdOption = None,
    channel: ChannelOption = Channel.mean,
    threads: Annotated[
        int | None,
        typer.Option(min=1, help="Solver threads (default: all cores).", show_default=False),
    ] = None,
    refine_lights: RefineLightsOption = 0,
    fixed_intensities: FixedIntensitiesOption = False,
    memory_budget: MemoryBudgetOption = "auto",
    lights: LightsOption = Lights.auto,
    led_model: Annotated[
        LedModel,
        typer.Option(
            case_sensitive=False,
            help="Near lights: isotropic (1/d^2 and the intensities only), beam (each LED's "
            "fitted axis and cos^mu exponent, light_axes.txt), flat-field (per-LED gains "
            "measured on a flat board, flat_field.npz); auto: flat-field, else beam, else "
            "isotropic, by the files of 'ps-lab calibrate --flat-field'.",
        ),
    ] = LedModel.auto,
    scheduler: Annotated[
        str | None,
        typer.Option(
            envvar="PS_LAB_SCHEDULER",
            metavar="<address>",
            help="Dask scheduler address (tcp://host:8786): solve the row bands on its workers "
            "(dataset and output on a shared filesystem; needs the 'distributed' extra).",
            show_default=False,
        ),
    ] = None,
    lam: LambdaOption = None,
    sigma_x2: SigmaX2Option = None,
    max_iter: MaxIterOption = None,
    tol: TolOption = None,
    segments: SegmentsOption = None,
    depth: DepthOption = None,
    encoding: EncodingOption = Encoding.auto,
    normal_map: Annotated[
        NormalMap,
        typer.Option(
            case_sensitive=False,
            help="normal16.png / normals.exr y axis: opengl (up) or directx (down).",
        ),
    ] = NormalMap.opengl,
    appearance: AppearanceOption = AppearanceModel.auto,
) -> None:
    """Estimate surface normals and albedo; write normals.npy, normal.png, albedo, metrics.json."""
    options = options_from(locals())
    out = out if out is not None else dataset / "recon" / method.value
    try:
        result = reconstruct_to_folder(dataset, out, options, progress_bars=_terminal_bars)
    except FolderOfDatasetsError as exc:
        raise DatasetError(f"{exc}, {batch_hint(exc.folder)}") from None
    metrics = result.metrics
    typer.echo(
        f"{metrics['pixels']} pixels, {metrics['lights']} lights, {method.value} "
        f"in {metrics['solve_seconds']:.2f} s"
    )
    errors = metrics.get("angular_error_deg")
    if errors:
        typer.echo(
            f"normal error vs ground truth: mean {errors['mean']:.2f} deg, "
            f"median {errors['median']:.2f} deg, p90 {errors['p90']:.2f} deg"
        )
    if "near" in metrics:
        typer.echo(
            f"near lights: {metrics['near']['rounds']} rounds, depth changes "
            + ", ".join(f"{c:.2f}" for c in metrics["near"]["depth_change_px"])
            + " px"
        )
    for step in metrics.get("refinement", {}).get("history", [])[1:]:
        line = (
            f"light refinement {step['iteration']}: mean direction change "
            f"{step['mean_direction_change_deg']:.3f} deg"
            if "intensity_change_rms_pct" not in step  # near lights refine intensities only
            else f"light refinement {step['iteration']}: intensity change rms "
            f"{step['intensity_change_rms_pct']:.2f} %"
        )
        if step.get("normal_error_deg") is not None:
            line += f", mean normal error {step['normal_error_deg']:.2f} deg"
        typer.echo(line)
    if "depth" in metrics:
        typer.echo(_depth_line(metrics["depth"]))
    fitted = metrics.get("appearance", {})
    if fitted.get("model", "none") != "none":
        typer.echo(
            f"appearance: {fitted['model']}, {fitted['coefficients_per_pixel']} coefficients "
            "per pixel (appearance.npz)"
        )
    typer.echo(f"results: {out}")


def options_from(params: Mapping[str, Any], leave: Collection[str] = ()) -> ReconstructOptions:
    """The :class:`ReconstructOptions` of a command's parameters (``locals()`` on entry).

    As :func:`ps_lab._cli_util.from_params`, ``--memory-budget`` parsed
    (:func:`parse_memory_budget`): shared by ``ps-lab reconstruct`` and ``ps-lab batch``.
    """
    budget = parse_memory_budget(params["memory_budget"])
    return from_params(ReconstructOptions, params, leave=leave, memory_budget=budget)


def batch_hint(folder: Path) -> str:
    """What to type to reconstruct every dataset under ``folder``."""
    return f"or reconstruct them all with ps-lab batch {folder}/* --out-root RESULTS"


def _depth_line(depth: dict) -> str:
    """One line about an integration (shared with ``ps-lab integrate``)."""
    return (
        f"depth: {depth['method']}, {depth['pixels']} pixels in {depth['components']} "
        f"component(s), {depth['seconds']:.2f} s, residual {depth['residual']:.2g}"
    )


def _terminal_bars(total: int, description: str):
    """Progress bars on a terminal only, so that a failure on a pipe stays one error line."""
    return progress_bar(total, description, enabled=sys.stderr.isatty())


def register(app: typer.Typer) -> None:
    """Add ``reconstruct`` to the app."""
    app.command("reconstruct")(reconstruct)
