"""The depth stage: integrate a result's normals and write depth maps, a picture and a mesh.

Used at the end of ``ps-lab reconstruct --depth METHOD`` (on the staged result folder) and by
``ps-lab integrate RESULT`` (on a finished result folder). Files (``docs/datasets.md``):
``depth.npy`` and ``depth.tiff`` (float32, NaN outside the integrated pixels; pixels, or mm with a
pixel size), ``depth.png`` (a shaded relief), ``mesh.ply`` (binary PLY, albedo-coloured vertices);
and the normal maps for other tools written by every reconstruction: ``normal16.png`` and
``normals.exr``. Metrics go under ``"depth"`` in ``metrics.json``.

An integration that stops before it converged (``bilateral`` at its limit of reweighting
iterations, or a linear solve at its limit) is logged as a warning: the command prints it as one
``warning:`` line after its results. Progress goes to a ``progress_bars`` callable, as in
:func:`ps_lab.reconstruct.pipeline.reconstruct_to_folder`: one bar over the reweighting
iterations.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import tifffile

from ps_lab.errors import OutputError
from ps_lab.io.camera import CAMERA_FILE, CameraModel
from ps_lab.io.codecs import imwrite
from ps_lab.io.files import json_safe, staged_files
from ps_lab.io.images import read_npy_header
from ps_lab.io.mesh import depth_mesh, write_ply
from ps_lab.io.normal_maps import write_normal16, write_normals_exr
from ps_lab.io.result import RESULT_FORMAT
from ps_lab.reconstruct._outputs import run_jobs
from ps_lab.reconstruct.integrate import (
    BILATERAL_MAX_ITERATIONS,
    INTEGRATION_METHODS,
    Integration,
    IntegrationInputError,
    integrate,
)

__all__ = [
    "DepthOptions",
    "depth_picture",
    "integrate_result",
    "write_depth",
    "write_normal_maps",
]

log = logging.getLogger(__name__)

ProgressBars = Callable[[int, str], Any]

# Direction toward the light of the shaded relief: from the upper left, as maps are shaded.
_RELIEF_LIGHT = np.array([-1.0, 1.0, 1.5]) / np.linalg.norm([-1.0, 1.0, 1.5])


@dataclass(frozen=True)
class DepthOptions:
    """How to integrate a result's normals.

    Attributes
    ----------
    method : {"poisson", "bilateral"}
        See :func:`ps_lab.reconstruct.integrate.integrate`.
    pixel_size : float or None
        Width of a pixel on the object in mm: depth and mesh in mm (default: in pixels).
    focal_length : float or None
        Perspective camera, focal length in pixels (default orthographic).
    principal_point : (x, y) or None
        Perspective camera's principal point in pixels (default the image centre).
    camera : str or None
        The ``camera.json`` the focal length and principal point come from (recorded).
    """

    method: str = "poisson"
    pixel_size: float | None = None
    focal_length: float | None = None
    principal_point: tuple[float, float] | None = None
    camera: str | None = None

    def __post_init__(self) -> None:
        if self.method not in INTEGRATION_METHODS:
            raise IntegrationInputError(
                f"--depth: unknown depth method {self.method!r}; choose "
                f"{' or '.join(INTEGRATION_METHODS)}"
            )
        if self.pixel_size is not None and not self.pixel_size > 0:
            raise IntegrationInputError(f"--pixel-size must be positive, got {self.pixel_size}")
        if self.focal_length is not None and not self.focal_length > 0:
            raise IntegrationInputError(
                f"--focal-length must be positive, got {self.focal_length}"
            )


@contextmanager
def _no_bar(total: int, description: str) -> Iterator[Callable[..., None]]:
    yield lambda n=1, description=None: None


def _warn_unconverged(result: Integration) -> None:
    """Log one warning (the CLI prints it as a ``warning:`` line) for an unconverged result."""
    if result.converged:
        return
    if result.method == "bilateral" and result.iterations >= BILATERAL_MAX_ITERATIONS:
        why = f"stopped at its limit of {BILATERAL_MAX_ITERATIONS} reweighting iterations"
        change = f"{100 * result.energy_change:.2g} %"
        if result.alternating:
            why += (
                f", its side weights flipping between two states (the energy alternates by "
                f"{change})"
            )
        else:
            why += f" before the energy settled (last change {change})"
    else:
        why = "a linear solve stopped at its iteration limit"
    log.warning(
        "depth (%s) did not converge: %s; depth.npy holds the last iterate (residual %.2g): "
        "check depth.png%s",
        result.method,
        why,
        result.residual,
        ", or integrate with poisson" if result.method == "bilateral" else "",
    )


def depth_picture(depth: np.ndarray) -> np.ndarray:
    """Shaded relief of a depth map in pixel units: grey 8-bit, black where there is no depth.

    Parameters
    ----------
    depth : ndarray of shape (H, W)
        Depth away from the camera, in pixels; NaN where there is none.

    Returns
    -------
    ndarray of shape (H, W), uint8
    """
    valid = np.isfinite(depth)
    filled = np.where(valid, depth, np.nanmedian(depth) if valid.any() else 0.0)
    d_row, d_col = np.gradient(filled)
    # Normal of z = -depth in the camera frame (y up): (d depth/d col, -d depth/d row, 1).
    normals = np.stack([d_col, -d_row, np.ones_like(d_col)], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    shade = 0.15 + 0.85 * np.clip(normals @ _RELIEF_LIGHT, 0.0, 1.0)
    picture = np.rint(shade * 255.0).astype(np.uint8)
    picture[~valid] = 0
    return picture


#: Largest coordinate (depth, mesh x and y) written: float32 files, with room for the mesh's
#: differences and products (float32 holds 3.4e38).
MAX_COORDINATE = 1e30


def _check_range(depth: np.ndarray, shape: tuple[int, int], scale: float, options) -> None:
    """Refuse a pixel size or focal length that puts the depth or mesh beyond float32's range."""
    with np.errstate(over="ignore", invalid="ignore"):
        integrated = depth[~np.isnan(depth)].astype(np.float64)
        deepest = float(np.max(np.abs(integrated), initial=0.0))
        extent = max(deepest, float(max(shape))) * float(scale)
        if options.focal_length is not None:
            extent = max(extent, deepest * max(shape) / options.focal_length * float(scale))
    if not extent <= MAX_COORDINATE:
        given = []
        if options.pixel_size is not None:
            given.append(f"--pixel-size {options.pixel_size:g}")
        if options.focal_length is not None:
            given.append(f"--focal-length {options.focal_length:g}")
        raise IntegrationInputError(
            f"{' with '.join(given) or 'the normals'}: the depth and mesh would reach "
            f"{extent:.3g}, beyond what their float32 files hold (at most {MAX_COORDINATE:.0e})"
        )


def write_normal_maps(
    folder: Path, normals: np.ndarray, mask: np.ndarray, convention: str = "opengl",
    threads: int | None = None,
) -> None:
    """Write ``normal16.png`` and ``normals.exr`` (``ps_lab.io.normal_maps``) into ``folder``.

    ``convention``: ``opengl`` (y up, the camera frame) or ``directx`` (y down). The two are
    encoded side by side on up to ``threads`` threads (None: all cores; the encoders release
    the GIL).
    """
    run_jobs([lambda: write_normal16(folder / "normal16.png", normals, mask, convention),
              lambda: write_normals_exr(folder / "normals.exr", normals, convention)], threads)


def write_depth(
    folder: Path,
    normals: np.ndarray,
    albedo: np.ndarray | None,
    options: DepthOptions,
    *,
    progress_bars: ProgressBars | None = None,
) -> dict[str, Any]:
    """Integrate ``normals`` and write the depth files into ``folder``; return the metrics.

    Parameters
    ----------
    folder : Path
        Where ``depth.npy``, ``depth.tiff``, ``depth.png`` and ``mesh.ply`` are written.
    normals : ndarray of shape (H, W, 3)
        Unit normals, zeros where there is none.
    albedo : ndarray of shape (H, W) or (H, W, 3), optional
        Vertex colours of the mesh (scaled so that its 99th percentile is white).
    options : DepthOptions
        Method and units.
    progress_bars : callable or None
        ``progress_bars(total, description)`` returning a context manager that yields
        ``advance(n=1, description=None)`` (:func:`ps_lab._cli_util.progress_bar`): one bar over
        the reweighting iterations (one step for ``poisson``). Default: none.

    Returns
    -------
    dict
        ``method``, ``camera``, ``seconds``, ``iterations``, ``solver_iterations``, ``residual``,
        ``components``, ``discontinuities``, ``converged``, ``energy_change``, ``alternating``,
        ``pixels``, ``unit``, ``offset`` (:class:`~ps_lab.reconstruct.integrate.Integration`).
    """
    bars = progress_bars or _no_bar
    total = BILATERAL_MAX_ITERATIONS if options.method == "bilateral" else 1
    label = f"depth ({options.method})"
    started = time.perf_counter()
    with bars(total, f"{label}: iterations" if total > 1 else label) as advance:
        result = integrate(
            normals,
            None,
            options.method,
            focal_length=options.focal_length,
            principal_point=options.principal_point,
            max_iterations=BILATERAL_MAX_ITERATIONS,
            progress=advance,
        )
        if total > 1:
            state = "converged" if result.converged else "not converged"
            advance(0, description=f"{label}: {state} at iteration {result.iterations}")
    seconds = time.perf_counter() - started
    _warn_unconverged(result)
    scale = options.pixel_size if options.pixel_size is not None else 1.0
    _check_range(result.depth, normals.shape[:2], scale, options)
    depth = (result.depth * np.float64(scale)).astype(np.float32)
    np.save(folder / "depth.npy", depth)
    tifffile.imwrite(folder / "depth.tiff", depth)
    if not imwrite(folder / "depth.png", depth_picture(result.depth)):
        raise OutputError(f"{folder / 'depth.png'}: OpenCV could not write the PNG")
    colours = None
    if albedo is not None:
        top = np.nanpercentile(albedo[np.isfinite(result.depth)], 99) if result.pixels else 0
        colours = np.clip(np.nan_to_num(albedo) / top, 0, 1) if top > 0 else None
    vertices, vertex_colours, triangles = depth_mesh(
        depth, colours, pixel_size=scale, focal_length=options.focal_length,
        principal_point=options.principal_point,
    )
    write_ply(
        folder / "mesh.ply",
        vertices,
        vertex_colours,
        triangles,
        normals=np.asarray(normals, np.float32)[np.isfinite(depth)],
        comments=mesh_comments(options, result.method),
    )
    gauge = (
        "unknown: each component's median depth is set to 0"
        if options.focal_length is None
        else "unknown scale: each component's median depth is set to the focal length"
    )
    return {
        "method": result.method,
        "camera": result.camera,
        "seconds": seconds,
        "iterations": result.iterations,
        "solver_iterations": result.solver_iterations,
        "residual": result.residual,
        "components": result.components,
        "offset": gauge,
        "discontinuities": result.discontinuities,
        "converged": result.converged,
        "energy_change": result.energy_change,
        "alternating": result.alternating,
        "pixels": result.pixels,
        "unit": "mm" if options.pixel_size is not None else "pixel",
        "mesh": {"vertices": len(vertices), "triangles": len(triangles)},
        "options": asdict(options),
    }


def mesh_comments(options: DepthOptions, method: str) -> tuple[str, ...]:
    """The header comments of ``mesh.ply``: what it is, its unit and its axes."""
    if options.focal_length is not None:
        camera = f"perspective camera, focal length {options.focal_length:g} px"
    else:
        camera = "orthographic camera"
    unit = (
        f"mm (pixel size {options.pixel_size:g} mm)"
        if options.pixel_size is not None
        else "pixel widths"
    )
    return (
        f"ps-lab mesh: depth integrated from photometric normals ({method}), {camera}",
        f"units: {unit}; "
        + (
            "scale unknown (each part's median depth is the focal length)"
            if options.focal_length is not None
            else "depth offset unknown (each part's median depth is 0)"
        ),
        "axes: x right, y up, z toward the camera (z = -depth), right-handed",
        "faces counter-clockwise seen from the camera; nx ny nz: unit photometric normals",
    )



#: ``metrics.json`` formats of the folders ``ps-lab integrate --out`` may write into: a
#: reconstruction (``ps_lab.io.result.RESULT_FORMAT``) or an earlier integration.
DEPTH_FORMAT = "ps-lab-depth"
RESULT_FORMATS = (RESULT_FORMAT, DEPTH_FORMAT)
#: The files an integration writes (besides ``metrics.json``).
DEPTH_FILES = ("depth.npy", "depth.tiff", "depth.png", "mesh.ply")
_STAGING_PREFIX = ".integrate-"


def _folder_record(out: Path) -> dict[str, Any] | None:
    """The ``metrics.json`` of ``out`` to extend, None for a new or empty folder.

    Raises :class:`OutputError` unless ``out`` is absent, empty, or a ps-lab result (a
    reconstruction or an earlier integration) whose ``metrics.json`` is sound: the user's own
    files are never overwritten.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: exists and is not a folder; choose another --out")
    if not out.is_dir() or not any(
        not entry.name.startswith(_STAGING_PREFIX) for entry in out.iterdir()
    ):
        return None
    metrics_file = out / "metrics.json"
    if not metrics_file.is_file():
        raise OutputError(
            f"{out}: exists and is not a ps-lab result folder (no metrics.json); "
            "choose another --out or remove it"
        )
    try:
        record = json.loads(metrics_file.read_text("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        reason = getattr(exc, "strerror", None) or "not JSON"
        raise OutputError(
            f"{metrics_file}: cannot read ({reason}), so {out} is not a ps-lab result folder "
            "to add depth to; choose another --out"
        ) from None
    if not isinstance(record, dict) or record.get("format") not in RESULT_FORMATS:
        raise OutputError(
            f"{metrics_file}: not the metrics of a ps-lab result, so {out} is not a ps-lab "
            "result folder; choose another --out or remove it"
        )
    return record


def _metrics_or_none(path: Path) -> dict[str, Any] | None:
    """A result's ``metrics.json`` when it is readable JSON, else None (nothing recorded)."""
    try:
        record = json.loads(path.read_text("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def _load_array(path: Path, what: str) -> np.ndarray:
    """A real-valued array from ``path`` (no pickles, no complex or text), or one error line.

    The size the header claims is checked against the file first: a forged or cut header is
    refused before anything is allocated.
    """
    try:
        with open(path, "rb") as stream:
            shape, _, dtype, offset = read_npy_header(stream)
            size = os.fstat(stream.fileno()).st_size
    except (OSError, ValueError, EOFError, SyntaxError, TypeError):
        shape, dtype, offset, size = (), None, 0, 0  # np.load below says what is wrong
    if dtype is not None and not dtype.hasobject:
        claimed = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
        if claimed > size - offset:
            raise IntegrationInputError(
                f"{path}: its header claims {' x '.join(map(str, shape))} {dtype} values "
                f"({claimed} bytes), the file holds {size - offset} (truncated or forged)"
            )
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        detail = "a pickled object array" if "allow_pickle" in str(exc) else str(exc)
        raise IntegrationInputError(f"{path}: cannot read {what} ({detail})") from None
    if not isinstance(array, np.ndarray):
        raise IntegrationInputError(f"{path}: holds several arrays (an .npz?), not {what}")
    if array.dtype == bool or not (
        np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)
    ):
        raise IntegrationInputError(
            f"{path}: {what} must be real numbers, got dtype {array.dtype}"
        )
    return array


def with_camera(options: DepthOptions, camera: CameraModel) -> DepthOptions:
    """``options`` with the perspective camera of a ``camera.json`` (on undistorted frames)."""
    return replace(
        options,
        focal_length=camera.focal_length,
        principal_point=(camera.cx, camera.cy),
        camera=camera.source or CAMERA_FILE,
    )


def with_result_camera(options: DepthOptions, record: dict[str, Any] | None) -> DepthOptions:
    """``options`` with the camera a result's ``metrics.json`` records (its dataset's
    ``camera.json``), unchanged when it records none."""
    camera = (record or {}).get("camera")
    if not isinstance(camera, dict):
        return options
    try:
        fx, fy, cx, cy = (float(camera[k]) for k in ("fx", "fy", "cx", "cy"))
    except (KeyError, TypeError, ValueError):
        return options
    if not all(np.isfinite([fx, fy, cx, cy])) or fx <= 0 or fy <= 0:
        return options
    return replace(options, focal_length=float(np.sqrt(fx * fy)), principal_point=(cx, cy),
                   camera=str(camera.get("file") or CAMERA_FILE))


def integrate_result(
    result: Path,
    out: Path | None,
    options: DepthOptions,
    *,
    progress_bars: ProgressBars | None = None,
) -> dict[str, Any]:
    """``ps-lab integrate``: depth files for a reconstruct result folder.

    Parameters
    ----------
    result : Path
        A ``ps-lab reconstruct`` output folder (``normals.npy``, optional ``albedo.npy``).
    out : Path or None
        Where to write (default: ``result`` itself): absent, empty or a ps-lab result folder
        (another folder is refused: its files are the user's). The files, ``metrics.json``
        with its new ``"depth"`` entry among them, appear together when complete; a folder this
        created is removed again on failure.
    options : DepthOptions
        Method and units.
    progress_bars : callable or None
        As for :func:`write_depth`.

    Returns
    -------
    dict
        The depth metrics (see :func:`write_depth`).

    Raises
    ------
    IntegrationInputError
        Unreadable or unusable normals or albedo (the line names the file).
    OutputError
        ``out`` is not a folder that may be written, or the disk is full.
    """
    result = Path(result)
    normals_file = result / "normals.npy"
    if not normals_file.is_file():
        raise IntegrationInputError(f"{result}: no normals.npy (not a ps-lab reconstruct result)")
    normals = _load_array(normals_file, "normals")
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise IntegrationInputError(f"{normals_file}: expected H x W x 3, got {normals.shape}")
    albedo_file = result / "albedo.npy"
    albedo = _load_array(albedo_file, "albedo") if albedo_file.is_file() else None
    if albedo is not None and (
        albedo.shape[:2] != normals.shape[:2]
        or albedo.ndim not in (2, 3)
        or (albedo.ndim == 3 and albedo.shape[2] not in (1, 3))
    ):
        raise IntegrationInputError(
            f"{albedo_file}: expected {normals.shape[0]} x {normals.shape[1]} (or x 3) like "
            f"{normals_file.name}, got {albedo.shape}"
        )
    if albedo is not None and albedo.ndim == 3 and albedo.shape[2] == 1:
        albedo = albedo[..., 0]
    if options.focal_length is None:
        options = with_result_camera(options, _metrics_or_none(result / "metrics.json"))
    out = result if out is None else Path(out)
    record = _folder_record(out)  # before anything is written
    with staged_files(
        out, prefix=_STAGING_PREFIX, check=_folder_record, error=OutputError
    ) as stage:
        try:
            metrics = json_safe(
                write_depth(stage, normals, albedo, options, progress_bars=progress_bars)
            )
            record = _folder_record(out) or {"format": DEPTH_FORMAT, "source": str(result)}
            record["depth"] = metrics
            (stage / "metrics.json").write_text(json.dumps(record, indent=1) + "\n", "utf-8")
        except IntegrationInputError as exc:
            if str(normals_file) in str(exc) or "--" in str(exc):
                raise
            raise IntegrationInputError(f"{normals_file}: {exc}") from None
        except OSError as exc:
            raise OutputError(
                f"{out}: cannot write depth outputs ({exc.strerror or exc})"
            ) from exc
    return metrics
