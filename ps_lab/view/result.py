"""A reconstruction result as the viewer shows it: its layers on one pixel grid, and its mesh.

A result folder (``ps-lab reconstruct``'s output) holds ``normals.npy`` and ``albedo.npy``, and
maybe ``corruption.png`` (outlier share), ``depth.npy`` / ``depth.png`` (depth and its shaded
relief), ``mesh.ply`` and ``metrics.json``. The ground truth, when the dataset has one, is read
from the dataset folder that ``metrics.json`` names, and gives the angular-error layer.

The layers are stacked as eight float32 channels per pixel (:data:`CHANNELS`), the layout of
the viewer's two RGBA textures.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from plyfile import PlyData

from ps_lab.errors import DatasetError
from ps_lab.io.truth import open_normal_gt
from ps_lab.view.readers import open_regular, present, read_array, read_grey_png, read_json

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

    Every file is checked before it is decoded (:mod:`ps_lab.view.readers`): a damaged,
    forged or misplaced one (a FIFO, a folder, an array of the wrong shape or kind, a truncated
    PNG) is refused with a message that names it.

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
    if not _is_dir(root):
        if os.path.lexists(root):
            raise DatasetError(f"{root}: not a result folder (a ps-lab reconstruct --out folder)")
        raise DatasetError(f"{root}: no such result folder")
    normals_file = root / "normals.npy"
    if not present(normals_file, "normal map"):
        raise DatasetError(f"{root}: not a ps-lab result (no normals.npy)")
    normals = normal_layer(normals_file)
    h, w = normals.shape[:2]
    mask = np.einsum("hwc,hwc->hw", normals, normals) > 0.25
    layers = np.zeros((h, w, len(CHANNELS)), np.float32)
    layers[..., 0:3] = normals
    layers[..., 5:8] = np.nan
    albedo_file = root / "albedo.npy"
    scale = 1.0
    if present(albedo_file, "albedo"):
        layers[..., 3], scale = albedo_layer(albedo_file, mask)
    else:
        layers[..., 3] = mask
    has = {"outliers": False, "error": False, "depth": False, "mesh": False}
    corruption_file = root / "corruption.png"
    if present(corruption_file, "outlier map"):
        layers[..., 4] = grey_layer(corruption_file, "outlier map", (h, w))
        has["outliers"] = True
    metrics_file = root / "metrics.json"
    metrics = read_json(metrics_file, "metrics file") if present(metrics_file, "metrics") else {}
    truth = _truth_for(metrics, (h, w))
    if truth is not None:
        layers[..., 5] = _angular_error_deg(normals, truth, mask)
        has["error"] = True
    depth_file = root / "depth.npy"
    if present(depth_file, "depth map"):
        depth = depth_layer(depth_file, (h, w))
        layers[..., 7] = depth
        relief_file = root / "depth.png"
        if present(relief_file, "shaded relief"):
            layers[..., 6] = grey_layer(relief_file, "shaded relief", (h, w))
        else:
            layers[..., 6] = np.where(np.isfinite(depth), 0.8, np.nan)
        has["depth"] = True
    mesh = None
    mesh_file = root / "mesh.ply"
    if present(mesh_file, "mesh"):
        mesh = read_view_mesh(mesh_file)
        has["mesh"] = True
    if name is None:
        parts = root.resolve().parts
        name = "/".join(parts[-3:]) if len(parts) >= 3 else str(root)
    return ViewResult(root, name, layers, scale, has, metrics, mesh)


def _is_dir(path: Path) -> bool:
    try:
        return path.is_dir()
    except (OSError, ValueError):  # a name too long, a NUL byte
        return False


# ---- the layers' files, checked --------------------------------------------------------------


def normal_layer(path: Path) -> np.ndarray:
    """``normals.npy`` as float32 (H, W, 3): non-finite values 0, vectors longer than 0.5 unit.

    A vector of length over 0.5 is in the mask; one whose length is not 1 (to 1e-3: a file of
    scaled normals, or a damaged one) is divided by it, so the pyramid and the shader see unit
    normals and no value overflows.
    """
    normals = read_array(path, "normal map", (3,))
    if normals.shape[2] != 3:
        raise DatasetError(f"{path}: expected an H x W x 3 array, got shape {normals.shape}")
    work = _finite(normals, np.promote_types(normals.dtype, np.float32))
    # Lengths computed on vectors scaled by their largest component: no square overflows.
    biggest = np.abs(work).max(axis=2, keepdims=True)
    scaled = np.divide(work, biggest, out=np.zeros_like(work), where=biggest > 0)
    with np.errstate(over="ignore"):
        length = np.sqrt(np.einsum("hwc,hwc->hw", scaled, scaled)) * biggest[..., 0]
    rescale = (length > 0.5) & (np.abs(length - 1.0) > 1e-3)
    out = np.where(rescale[..., None], 0, work).astype(np.float32)
    if rescale.any():
        chosen = scaled[rescale]
        out[rescale] = chosen / np.linalg.norm(chosen, axis=1, keepdims=True)
    return out


def albedo_layer(path: Path, mask: np.ndarray) -> tuple[np.ndarray, float]:
    """``albedo.npy`` (H, W) or (H, W, 1 or 3; channels averaged) over its 99th percentile.

    Returns
    -------
    layer : ndarray of shape (H, W), float32
        Albedo / scale inside ``mask``, 0 outside, non-finite values 0, within half-float range.
    scale : float
        The 99th percentile inside the mask (1 when that is not positive).
    """
    albedo = read_array(path, "albedo", (2, 3))
    if albedo.ndim == 3 and albedo.shape[2] not in (1, 3):
        raise DatasetError(f"{path}: expected 1 or 3 albedo channels, got shape {albedo.shape}")
    _check_shape(path, albedo.shape, mask.shape)
    albedo = _finite(albedo, np.float64)
    if albedo.ndim == 3:
        albedo = albedo.mean(axis=2)
    inside = albedo[mask]
    top = float(np.percentile(inside, 99)) if inside.size else 0.0
    scale = top if top > 0 else 1.0
    layer = np.where(mask, np.clip(albedo / scale, -HALF_MAX, HALF_MAX), 0.0)
    return layer.astype(np.float32), scale


def depth_layer(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """``depth.npy`` (H, W) as float32: NaN where there is none (infinite values too)."""
    depth = read_array(path, "depth map", (2, 3))
    if depth.ndim == 3 and depth.shape[2] != 1:
        raise DatasetError(f"{path}: expected an H x W depth map, got shape {depth.shape}")
    _check_shape(path, depth.shape, shape)
    with np.errstate(all="ignore"):
        values = np.asarray(depth.reshape(shape), np.float64)
    values = np.where(np.isfinite(values), np.clip(values, -HALF_MAX, HALF_MAX), np.nan)
    return values.astype(np.float32)


def grey_layer(path: Path, what: str, shape: tuple[int, int]) -> np.ndarray:
    """An 8-bit PNG (``corruption.png``, ``depth.png``) of size ``shape``, as 0..1 float32."""
    picture = read_grey_png(path, what)
    _check_shape(path, picture.shape, shape)
    return picture.astype(np.float32) / 255.0


#: The largest half float: layers are stored as half floats, and clipping there keeps the
#: pyramid's sums from overflowing.
HALF_MAX = float(np.finfo(np.float16).max)


def _finite(array: np.ndarray, dtype: type) -> np.ndarray:
    """``array`` as ``dtype`` with NaN and infinities (also from overflowing the cast) 0."""
    with np.errstate(all="ignore"):
        out = np.array(array, dtype)
    out[~np.isfinite(out)] = 0
    return out


def _check_shape(path: Path, shape: tuple, expected: tuple[int, int]) -> None:
    if tuple(shape[:2]) != tuple(expected):
        raise DatasetError(
            f"{path}: size {shape[1]}x{shape[0]} differs from normals.npy "
            f"({expected[1]}x{expected[0]})"
        )


def _truth_for(metrics: dict, shape: tuple[int, int]) -> np.ndarray | None:
    dataset = metrics.get("dataset")
    if not isinstance(dataset, str) or not _is_dir(Path(dataset)):
        return None
    try:
        truth = open_normal_gt(Path(dataset), shape)
        return None if truth is None else truth.rows(0, shape[0])
    except (ValueError, TypeError, OSError) as exc:  # a ground truth of strings, unreadable
        raise DatasetError(f"{dataset}: unreadable ground-truth normals ({exc})") from None


def _angular_error_deg(normals: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    valid = mask & (np.linalg.norm(truth, axis=2) > 0.5)
    cosine = np.einsum("hwc,hwc->hw", normals.astype(np.float64), truth)
    norms = np.linalg.norm(normals, axis=2) * np.linalg.norm(truth, axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        error = np.degrees(np.arccos(np.clip(cosine / norms, -1.0, 1.0)))
    return np.where(valid, error, np.nan).astype(np.float32)


def read_view_mesh(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Read a PLY mesh for the 3-D view: vertices, unit vertex normals, colours, triangles.

    Vertex normals are the file's (``nx ny nz``) or, when it has none (or a non-finite one),
    area-weighted face normals; a mesh over :data:`MAX_VIEW_TRIANGLES` is decimated
    (:func:`decimate_mesh`). The file is checked as it is read (:func:`mesh_elements`).

    Raises
    ------
    DatasetError
        The file is not a PLY triangle mesh the viewer can show (the message says why).
    """
    vertex, faces = mesh_elements(path)
    names = vertex.dtype.names or ()
    vertices = _mesh_vertices(path, vertex)
    if all(c in names for c in ("red", "green", "blue")):
        colours = _mesh_colours(vertex)
    else:
        colours = np.full(vertices.shape, 200, np.uint8)
    triangles = mesh_triangles(path, faces, len(vertices))
    if len(triangles) > MAX_VIEW_TRIANGLES:
        vertices, colours, triangles = decimate_mesh(
            vertices, colours, triangles, MAX_VIEW_TRIANGLES
        )
        normals = vertex_normals(vertices, triangles)
    else:
        normals = _file_normals(vertex)
        if normals is None:
            normals = vertex_normals(vertices, triangles)
    return vertices, normals, colours, triangles.astype(np.uint32)


# ---- the mesh file, checked ------------------------------------------------------------------

#: The largest coordinate the 3-D view takes (float32 range, with room for its sums).
MAX_COORDINATE = 1e30


def mesh_elements(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The ``vertex`` and ``face`` records of a PLY file, its header checked against its size.

    Each element's count must fit in the file (every element takes at least one byte), so a
    forged count cannot make the reader allocate what the header claims.
    """
    with open_regular(path, "mesh") as stream:
        head = stream.read(1 << 16)
        file_size = os.fstat(stream.fileno()).st_size
        _check_ply_counts(path, head, file_size)
        stream.seek(0)
        try:
            with warnings.catch_warnings():
                # plyfile wraps an ASCII file's stream in a TextIOWrapper it does not close;
                # freed on return, while the file is still open, it warns.
                warnings.simplefilter("ignore", ResourceWarning)
                ply = PlyData.read(stream)
            elements = {element.name: element for element in ply.elements}
            if "vertex" not in elements or "face" not in elements:
                missing = "vertex" if "vertex" not in elements else "face"
                raise DatasetError(f"{path}: the PLY file has no {missing} element")
            return elements["vertex"].data, elements["face"].data
        except DatasetError:
            raise
        except Exception as exc:  # noqa: BLE001 - plyfile raises many types for a broken file
            raise DatasetError(f"{path}: corrupt or unreadable PLY mesh ({exc})") from None


def _check_ply_counts(path: Path, head: bytes, file_size: int) -> None:
    """Refuse a PLY header whose element counts the file's size cannot hold."""
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise DatasetError(
            f"{path}: not a PLY file (no header from 'ply' to 'end_header' in its first 64 KiB)"
        )
    for line in head[:end].decode("latin-1").splitlines():
        words = line.split()
        if len(words) == 3 and words[0] == "element":
            count = words[2]
            if not (count.isascii() and count.isdigit()) or len(count) > 18:
                raise DatasetError(f"{path}: PLY header gives {words[1]!r} a count of {count!r}")
            if int(count) > file_size:
                raise DatasetError(
                    f"{path}: PLY header claims {count} {words[1]} elements, more than the "
                    f"file's {file_size} bytes can hold (truncated or forged)"
                )


def _numeric_columns(vertex: np.ndarray, columns: tuple[str, ...]) -> np.ndarray | None:
    """The vertex properties ``columns`` as float64 (N, k), or None when one is absent.

    A property that is a list, not a number, counts as absent.
    """
    names = vertex.dtype.names or ()
    if not all(c in names and vertex.dtype[c].kind in "biuf" for c in columns):
        return None
    with np.errstate(all="ignore"):
        return np.stack([np.asarray(vertex[c], np.float64) for c in columns], axis=1)


def _mesh_vertices(path: Path, vertex: np.ndarray) -> np.ndarray:
    xyz = _numeric_columns(vertex, ("x", "y", "z"))
    if xyz is None:
        raise DatasetError(f"{path}: the PLY vertices have no numeric x, y, z properties")
    bad = ~np.all(np.isfinite(xyz) & (np.abs(xyz) <= MAX_COORDINATE), axis=1)
    if bad.any():
        index = int(np.argmax(bad))
        raise DatasetError(
            f"{path}: vertex {index} has a non-finite or out-of-range coordinate "
            f"({', '.join(f'{v:g}' for v in xyz[index])})"
        )
    return xyz.astype(np.float32)


def _mesh_colours(vertex: np.ndarray) -> np.ndarray:
    """``red green blue`` as uint8: integers clipped to 0..255, floats in 0..1 scaled to it."""
    rgb = _numeric_columns(vertex, ("red", "green", "blue"))
    if rgb is None:
        return np.full((len(vertex), 3), 200, np.uint8)
    rgb[~np.isfinite(rgb)] = 0
    if vertex.dtype["red"].kind == "f" and rgb.size and rgb.max() <= 1.0:
        rgb *= 255.0
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def _file_normals(vertex: np.ndarray) -> np.ndarray | None:
    """The file's ``nx ny nz`` as float32 when all are finite, else None (computed instead)."""
    normals = _numeric_columns(vertex, ("nx", "ny", "nz"))
    if normals is None or not np.all(np.isfinite(normals)) or np.abs(normals).max(initial=0) > 1e3:
        return None
    return normals.astype(np.float32)


def mesh_triangles(path: Path, faces: np.ndarray, vertex_count: int) -> np.ndarray:
    """The faces' vertex lists as int64 (T, 3), checked: triangles of existing vertices only.

    Raises
    ------
    DatasetError
        A face that is not a triangle (the viewer shows triangle meshes only), a vertex index
        that is not an integer, or one outside ``0 .. vertex_count - 1``; each named by face.
    """
    names = faces.dtype.names or ()
    lists = [n for n in names if faces.dtype[n].kind == "O"]
    preferred = [n for n in ("vertex_indices", "vertex_index") if n in lists]
    if not (preferred or lists):
        raise DatasetError(f"{path}: the PLY faces have no vertex list")
    column = faces[(preferred or lists)[0]]
    if len(column) == 0:
        return np.zeros((0, 3), np.int64)
    sizes = np.fromiter((len(face) for face in column), np.int64, len(column))
    if np.any(sizes != 3):
        index = int(np.argmax(sizes != 3))
        raise DatasetError(
            f"{path}: face {index} has {sizes[index]} vertices; the viewer shows triangle "
            "meshes only"
        )
    triangles = np.stack(list(column))
    if triangles.dtype.kind not in "iu":
        raise DatasetError(f"{path}: the PLY faces' vertex indices are not integers")
    triangles = triangles.astype(np.int64)
    bad = np.any((triangles < 0) | (triangles >= vertex_count), axis=1)
    if bad.any():
        index = int(np.argmax(bad))
        raise DatasetError(
            f"{path}: face {index} refers to vertex "
            f"{triangles[index][(triangles[index] < 0) | (triangles[index] >= vertex_count)][0]}, "
            f"but the file has {vertex_count} vertices"
        )
    return triangles


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
