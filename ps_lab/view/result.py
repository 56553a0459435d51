"""A reconstruction result as the viewer shows it: its layers on one pixel grid, and its mesh.

A result folder (``ps-lab reconstruct``'s output) holds ``normals.npy`` and ``albedo.npy``, and
maybe ``corruption.png`` (outlier share), ``depth.npy`` / ``depth.png`` (depth and its shaded
relief), ``mesh.ply`` and ``metrics.json``. The ground truth, when the dataset has one, is read
from the dataset folder that ``metrics.json`` names, and gives the angular-error layer.

The layers are stacked as eight float32 channels per pixel (:data:`CHANNELS`), the layout of
the viewer's two RGBA textures.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from plyfile import PlyData

from ps_lab.errors import DatasetError
from ps_lab.io.images import check_is_file
from ps_lab.io.truth import open_normal_gt

__all__ = ["CHANNELS", "ViewResult", "decimate_mesh", "load_result", "vertex_normals"]

#: The channels of :attr:`ViewResult.layers`: normal x, y, z, albedo (divided by
#: :attr:`ViewResult.albedo_scale`), outlier share 0..1, angular error in degrees (NaN without
#: ground truth), shaded relief 0..1, depth (NaN where there is none).
CHANNELS = ("nx", "ny", "nz", "albedo", "outliers", "error_deg", "relief", "depth")

#: The 3-D view gets at most this many triangles (a 12 MP mesh is decimated by vertex clustering).
MAX_VIEW_TRIANGLES = 1_500_000


@dataclass
class ViewResult:
    """One result, ready to be tiled for the viewer.

    Attributes
    ----------
    root : Path
        The result folder.
    name : str
        Shown above its panel.
    layers : ndarray of shape (H, W, 8), float32
        See :data:`CHANNELS`; normals are zero outside the mask.
    albedo_scale : float
        The albedo's 99th percentile inside the mask (the layer holds albedo / scale).
    has : dict of str to bool
        Which optional layers exist: ``outliers``, ``error``, ``depth``, ``mesh``.
    metrics : dict
        ``metrics.json`` (empty when absent).
    mesh : tuple of ndarray or None
        ``(vertices (V, 3) float32, normals (V, 3) float32, colours (V, 3) uint8,
        triangles (T, 3) uint32)`` in the camera frame (x right, y up, z toward the camera).
    """

    root: Path
    name: str
    layers: np.ndarray
    albedo_scale: float
    has: dict[str, bool]
    metrics: dict = field(default_factory=dict)
    mesh: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return self.layers.shape[:2]


def load_result(root: Path, name: str | None = None) -> ViewResult:
    """Read a ``ps-lab reconstruct`` result folder for the viewer.

    Parameters
    ----------
    root : Path
        The folder holding ``normals.npy`` (and the other result files).
    name : str, optional
        Panel title; default the folder's path relative to its grandparent (``ball/recon/sbl``).

    Raises
    ------
    DatasetError
        Not a result folder, or a file that cannot be read (the message names it).
    """
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: no such result folder")
    normals_file = root / "normals.npy"
    if not normals_file.exists():
        raise DatasetError(f"{root}: not a ps-lab result (no normals.npy)")
    check_is_file(normals_file, "normal map")
    normals = _load_npy(normals_file)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise DatasetError(f"{normals_file}: expected an H x W x 3 array, got {normals.shape}")
    h, w = normals.shape[:2]
    normals = np.nan_to_num(normals.astype(np.float32))
    mask = np.linalg.norm(normals, axis=2) > 0.5
    layers = np.zeros((h, w, len(CHANNELS)), np.float32)
    layers[..., 0:3] = normals
    layers[..., 5:8] = np.nan
    albedo_file = root / "albedo.npy"
    scale = 1.0
    if albedo_file.exists():
        albedo = _load_npy(albedo_file)
        if albedo.ndim == 3:
            albedo = albedo.mean(axis=2)
        _check_shape(albedo_file, albedo.shape, (h, w))
        albedo = np.nan_to_num(albedo.astype(np.float32))
        inside = albedo[mask]
        top = float(np.percentile(inside, 99)) if inside.size else 0.0
        scale = top if np.isfinite(top) and top > 0 else 1.0
        layers[..., 3] = np.where(mask, albedo / scale, 0.0)
    else:
        layers[..., 3] = mask
    has = {"outliers": False, "error": False, "depth": False, "mesh": False}
    corruption_file = root / "corruption.png"
    if corruption_file.exists():
        layers[..., 4] = _read_grey(corruption_file, (h, w)) / 255.0
        has["outliers"] = True
    metrics = _read_metrics(root / "metrics.json")
    truth = _truth_for(metrics, (h, w))
    if truth is not None:
        layers[..., 5] = _angular_error_deg(normals, truth, mask)
        has["error"] = True
    depth_file = root / "depth.npy"
    if depth_file.exists():
        depth = _load_npy(depth_file).astype(np.float32)
        _check_shape(depth_file, depth.shape, (h, w))
        layers[..., 7] = depth
        relief_file = root / "depth.png"
        if relief_file.exists():
            layers[..., 6] = _read_grey(relief_file, (h, w)) / 255.0
        else:
            layers[..., 6] = np.where(np.isfinite(depth), 0.8, np.nan)
        has["depth"] = True
    mesh = None
    mesh_file = root / "mesh.ply"
    if mesh_file.exists():
        mesh = read_view_mesh(mesh_file)
        has["mesh"] = True
    if name is None:
        parts = root.resolve().parts
        name = "/".join(parts[-3:]) if len(parts) >= 3 else str(root)
    return ViewResult(root, name, layers, scale, has, metrics, mesh)


def _load_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise DatasetError(f"{path}: corrupt or unreadable .npy file ({exc})") from None


def _check_shape(path: Path, shape: tuple, expected: tuple[int, int]) -> None:
    if tuple(shape[:2]) != expected:
        raise DatasetError(
            f"{path}: size {shape[1]}x{shape[0]} differs from normals.npy "
            f"({expected[1]}x{expected[0]})"
        )


def _read_grey(path: Path, shape: tuple[int, int]) -> np.ndarray:
    picture = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if picture is None:
        raise DatasetError(f"{path}: corrupt or unreadable PNG file")
    _check_shape(path, picture.shape, shape)
    return picture.astype(np.float32)


def _read_metrics(path: Path) -> dict:
    if not path.exists():
        return {}
    try:
        value = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: unreadable metrics ({exc})") from None
    return value if isinstance(value, dict) else {}


def _truth_for(metrics: dict, shape: tuple[int, int]) -> np.ndarray | None:
    dataset = metrics.get("dataset")
    if not isinstance(dataset, str) or not Path(dataset).is_dir():
        return None
    truth = open_normal_gt(Path(dataset), shape)
    return None if truth is None else truth.rows(0, shape[0])


def _angular_error_deg(normals: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    valid = mask & (np.linalg.norm(truth, axis=2) > 0.5)
    cosine = np.einsum("hwc,hwc->hw", normals.astype(np.float64), truth)
    norms = np.linalg.norm(normals, axis=2) * np.linalg.norm(truth, axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        error = np.degrees(np.arccos(np.clip(cosine / norms, -1.0, 1.0)))
    return np.where(valid, error, np.nan).astype(np.float32)


def read_view_mesh(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Read a PLY mesh for the 3-D view: vertices, unit vertex normals, colours, triangles.

    Vertex normals are the file's (``nx ny nz``) or, when it has none, area-weighted face
    normals; a mesh over :data:`MAX_VIEW_TRIANGLES` is decimated (:func:`decimate_mesh`).
    """
    try:
        ply = PlyData.read(str(path))
        vertex = ply["vertex"].data
        faces = ply["face"].data
    except Exception as exc:  # noqa: BLE001 - plyfile raises many types for a broken file
        raise DatasetError(f"{path}: corrupt or unreadable PLY mesh ({exc})") from None
    vertices = np.stack([vertex[c] for c in "xyz"], axis=1).astype(np.float32)
    names = vertex.dtype.names or ()
    if all(c in names for c in ("red", "green", "blue")):
        colours = np.stack([vertex[c] for c in ("red", "green", "blue")], axis=1).astype(np.uint8)
    else:
        colours = np.full(vertices.shape, 200, np.uint8)
    field_name = faces.dtype.names[0]
    lists = faces[field_name]
    triangles = (
        np.stack(list(lists)).astype(np.int64) if len(lists) else np.zeros((0, 3), np.int64)
    )
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise DatasetError(f"{path}: the viewer shows triangle meshes only")
    if len(triangles) > MAX_VIEW_TRIANGLES:
        vertices, colours, triangles = decimate_mesh(
            vertices, colours, triangles, MAX_VIEW_TRIANGLES
        )
        normals = vertex_normals(vertices, triangles)
    elif all(c in names for c in ("nx", "ny", "nz")):
        normals = np.stack([vertex[c] for c in ("nx", "ny", "nz")], axis=1).astype(np.float32)
    else:
        normals = vertex_normals(vertices, triangles)
    return vertices, normals, colours, triangles.astype(np.uint32)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (V, 3) float32 of a triangle mesh (zeros for lone vertices).

    Each face's cross product ``(b - a) x (c - a)`` (twice its area along its normal) is added
    to its three vertices, then every sum is normalised.
    """
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    face = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    sums = np.zeros_like(v)
    for k in range(3):
        np.add.at(sums, t[:, k], face)
    norms = np.linalg.norm(sums, axis=1, keepdims=True)
    return np.divide(sums, norms, out=np.zeros_like(sums), where=norms > 0).astype(np.float32)


def decimate_mesh(
    vertices: np.ndarray, colours: np.ndarray, triangles: np.ndarray, max_triangles: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fewer triangles by vertex clustering: vertices merged on a grid, degenerate faces dropped.

    The grid cell grows by sqrt(2) until at most ``max_triangles`` remain (a height field loses
    about half its faces per step). Merged vertices take the cells' mean position and colour.
    """
    v = np.asarray(vertices, np.float64)
    span = float(np.max(np.ptp(v, axis=0))) or 1.0
    cell = span * np.sqrt(2.0 * max(len(triangles), 1) / max_triangles) / np.sqrt(len(v) + 1)
    cell = max(cell, span * 1e-6)
    while True:
        keys = np.floor((v - v.min(axis=0)) / cell).astype(np.int64)
        _, index, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
        inverse = inverse.ravel()
        t = inverse[np.asarray(triangles, np.int64)]
        keep = (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])
        if keep.sum() <= max_triangles:
            break
        cell *= np.sqrt(2.0)
    count = len(index)
    weights = np.bincount(inverse, minlength=count).astype(np.float64)[:, None]
    merged = np.stack([np.bincount(inverse, v[:, k], count) for k in range(3)], 1) / weights
    c = np.asarray(colours, np.float64)
    merged_colours = np.stack([np.bincount(inverse, c[:, k], count) for k in range(3)], 1) / weights
    return (
        merged.astype(np.float32),
        np.clip(np.rint(merged_colours), 0, 255).astype(np.uint8),
        t[keep],
    )
