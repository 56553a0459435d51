"""Triangle meshes from depth maps, written as binary PLY (plyfile).

Vertices are the pixels with a depth, in the camera frame x right, y up, z toward the camera
(``z = -depth``), with the albedo as vertex colour and, from ps-lab's writers, the photometric
normals as vertex normals; each 2 x 2 block of pixels gives two triangles,
counter-clockwise seen from the camera, unless one of their sides crosses a depth discontinuity.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from ps_lab.errors import OutputError

__all__ = ["MAX_STEP_SLOPE", "depth_mesh", "write_ply"]

#: A side whose depth change exceeds this many pixel widths (a slope of about 84 degrees) crosses a
#: depth discontinuity: no triangle is built across it.
MAX_STEP_SLOPE = 10.0


def depth_mesh(
    depth: np.ndarray,
    colours: np.ndarray | None = None,
    *,
    pixel_size: float = 1.0,
    focal_length: float | None = None,
    principal_point: tuple[float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices, colours and triangles of the surface seen in a depth map.

    Parameters
    ----------
    depth : ndarray of shape (H, W)
        Depth along the viewing axis, away from the camera; NaN where there is no surface.
    colours : ndarray of shape (H, W, 3) or (H, W), optional
        Vertex colours in [0, 1] (the albedo); default grey.
    pixel_size : float
        Width of a pixel in the depth's unit (orthographic camera).
    focal_length : float, optional
        Perspective camera: focal length in pixels (then ``pixel_size`` is ignored: a point at
        depth d lies at ``d (col - c_x) / f`` to the right of the axis).
    principal_point : (x, y), optional
        Default the image centre.

    Returns
    -------
    vertices : ndarray of shape (V, 3), float32
    vertex_colours : ndarray of shape (V, 3), uint8
    triangles : ndarray of shape (T, 3), int32
    """
    depth = np.asarray(depth, dtype=np.float64)
    h, w = depth.shape
    valid = np.isfinite(depth)
    index = np.full((h, w), -1, dtype=np.int64)
    index[valid] = np.arange(int(valid.sum()))
    rows, cols = np.nonzero(valid)
    d = depth[valid]
    if focal_length is None:
        x = cols * pixel_size
        y = -rows * pixel_size
        footprint = np.full(d.shape, float(pixel_size))
    else:
        cx, cy = principal_point if principal_point is not None else ((w - 1) / 2, (h - 1) / 2)
        x = d * (cols - cx) / focal_length
        y = -d * (rows - cy) / focal_length
        footprint = d / focal_length
    vertices = np.stack([x, y, -d], axis=1).astype(np.float32)
    if colours is None:
        vertex_colours = np.full((d.size, 3), 200, np.uint8)
    else:
        c = np.asarray(colours, dtype=np.float64)
        c = np.repeat(c[..., None], 3, axis=2) if c.ndim == 2 else c
        vertex_colours = np.clip(np.rint(c[valid] * 255.0), 0, 255).astype(np.uint8)
    grid_footprint = np.zeros((h, w))
    grid_footprint[valid] = footprint
    limit = MAX_STEP_SLOPE * grid_footprint

    def joined(a: tuple[slice, slice], b: tuple[slice, slice]) -> np.ndarray:
        both = valid[a] & valid[b]
        step = np.abs(np.where(both, depth[a] - depth[b], np.inf))
        return both & (step <= np.minimum(limit[a], limit[b]))

    tl, tr = (slice(0, -1), slice(0, -1)), (slice(0, -1), slice(1, None))
    bl, br = (slice(1, None), slice(0, -1)), (slice(1, None), slice(1, None))
    top, bottom, left, right = joined(tl, tr), joined(bl, br), joined(tl, bl), joined(tr, br)
    diagonal = joined(tr, bl)
    # Seen from the camera (y up, rows down): tl -> bl -> tr and tr -> bl -> br turn
    # counter-clockwise, so the triangles' normals face the camera.
    first = left & diagonal & top
    second = diagonal & bottom & right
    triangles = np.concatenate(
        [
            np.stack([index[tl][first], index[bl][first], index[tr][first]], axis=1),
            np.stack([index[tr][second], index[bl][second], index[br][second]], axis=1),
        ]
    ).astype(np.int32)
    return vertices, vertex_colours, triangles


def write_ply(
    path: Path,
    vertices: np.ndarray,
    colours: np.ndarray,
    triangles: np.ndarray,
    normals: np.ndarray | None = None,
    comments: tuple[str, ...] = (),
) -> None:
    """Write a binary little-endian PLY with coloured vertices (and their normals) and triangles.

    Parameters
    ----------
    path : Path
        The ``.ply`` file.
    vertices : ndarray of shape (V, 3)
        Positions.
    colours : ndarray of shape (V, 3), uint8
        Vertex colours.
    triangles : ndarray of shape (T, 3), int
        Vertex indices, counter-clockwise seen from the front.
    normals : ndarray of shape (V, 3), optional
        Unit vertex normals, written as ``nx ny nz`` (the names MeshLab, Blender and Open3D read).
    comments : tuple of str
        Header ``comment`` lines (units, axes).
    """
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if normals is not None:
        fields += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
    fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertex = np.empty(len(vertices), dtype=fields)
    vertex["x"], vertex["y"], vertex["z"] = np.asarray(vertices, np.float32).T
    if normals is not None:
        vertex["nx"], vertex["ny"], vertex["nz"] = np.asarray(normals, np.float32).T
    vertex["red"], vertex["green"], vertex["blue"] = np.asarray(colours, np.uint8).T
    face = np.empty(len(triangles), dtype=[("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = triangles
    ply = PlyData(
        [PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face")],
        text=False,
        comments=list(comments),
    )
    try:
        ply.write(str(path))
    except OSError as exc:
        raise OutputError(f"{path}: cannot write the mesh ({exc.strerror or exc})") from None
