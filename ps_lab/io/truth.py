"""Ground-truth normals, read whole (:func:`read_normal_gt`) or band by band (:class:`NormalTruth`).

The file is ``normal_gt.npy``, DiLiGenT's ``Normal_gt.mat`` or a simulated run's
``simulation/normal_gt.npy``. Angular errors are reported wherever it exists.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.io

from ps_lab.errors import DatasetError
from ps_lab.io.images import read_npy_header
from ps_lab.io.run import SIMULATION_DIR


def read_normal_gt(path: Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read ground-truth normals from ``normal_gt.npy`` or DiLiGenT's ``Normal_gt.mat``.

    Returns
    -------
    ndarray of shape (H, W, 3), float64

    """
    if path.suffix.lower() == ".mat":
        try:
            content = scipy.io.loadmat(path)
        except Exception as exc:  # noqa: BLE001 - scipy raises several types for a bad .mat
            raise DatasetError(f"{path}: cannot read MATLAB file ({exc})") from None
        if "Normal_gt" not in content:
            raise DatasetError(f"{path}: no variable 'Normal_gt' in the MATLAB file")
        normals = np.asarray(content["Normal_gt"])
    else:
        try:
            normals = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise DatasetError(f"{path}: corrupt or unreadable .npy file ({exc})") from None
    _check_normal_gt_shape(path, normals.shape, shape)
    return _finite_normals(path, normals.astype(np.float64))


def _check_normal_gt_shape(path: Path, dims: tuple, shape: tuple[int, int] | None) -> None:
    """Raise DatasetError unless ``dims`` is (H, W, 3) with (H, W) == ``shape`` (when given)."""
    if len(dims) != 3 or dims[2] != 3:
        raise DatasetError(f"{path}: ground-truth normals must be H x W x 3, got {tuple(dims)}")
    if shape is not None and tuple(dims[:2]) != tuple(shape):
        raise DatasetError(
            f"{path}: ground-truth size {dims[1]}x{dims[0]} differs from the "
            f"image size {shape[1]}x{shape[0]}"
        )


def _finite_normals(path: Path, normals: np.ndarray) -> np.ndarray:
    if not np.all(np.isfinite(normals)):
        raise DatasetError(f"{path}: ground-truth normals contain NaN or infinite values")
    return normals


def _normal_gt_path(root: Path) -> Path | None:
    """The dataset's ground-truth file, or None.

    ``normal_gt.npy``, else DiLiGenT's ``Normal_gt.mat``, else the simulator's
    ``simulation/normal_gt.npy``.
    """
    for candidate in (
        root / "normal_gt.npy",
        root / "Normal_gt.mat",
        root / SIMULATION_DIR / "normal_gt.npy",
    ):
        if candidate.is_file():
            return candidate
    return None


def _find_normal_gt(root: Path, shape: tuple[int, int]) -> np.ndarray | None:
    path = _normal_gt_path(root)
    return None if path is None else read_normal_gt(path, shape)


class NormalTruth:
    """Ground-truth normals read band by band (``normal_gt.npy`` from disk, ``.mat`` in memory).

    Use :func:`open_normal_gt`. ``rows(a, b)`` returns rows ``a:b`` as (b - a, W, 3) float64.
    """

    def __init__(self, path: Path, shape: tuple[int, int]) -> None:
        self.path = path
        self.shape = shape
        self._array: np.ndarray | None = None
        self._layout: tuple[np.dtype, int] | None = None
        if path.suffix.lower() == ".npy":
            try:
                with path.open("rb") as stream:
                    dims, fortran, dtype, offset = read_npy_header(stream)
            except (OSError, ValueError) as exc:
                raise DatasetError(f"{path}: corrupt or unreadable .npy file ({exc})") from None
            _check_normal_gt_shape(path, tuple(dims), shape)
            expected = offset + int(np.prod(dims)) * dtype.itemsize
            if not fortran and dtype.kind == "f" and path.stat().st_size >= expected:
                self._layout = (dtype, offset)
        if self._layout is None:
            self._array = read_normal_gt(path, shape)

    def rows(self, start: int, stop: int) -> np.ndarray:
        """Rows ``start:stop`` of the normals, shape (stop - start, W, 3), float64."""
        if self._array is not None:
            return self._array[start:stop]
        assert self._layout is not None
        dtype, offset = self._layout
        width = self.shape[1]
        count = (stop - start) * width * 3
        with self.path.open("rb") as stream:
            stream.seek(offset + start * width * 3 * dtype.itemsize)
            data = np.fromfile(stream, dtype=dtype, count=count)
        if data.size != count:
            raise DatasetError(f"{self.path}: file is truncated")
        return _finite_normals(self.path, data.reshape(stop - start, width, 3).astype(np.float64))


def open_normal_gt(root: Path, shape: tuple[int, int]) -> NormalTruth | None:
    """The dataset's ground-truth normals for band-wise reading, or None (as in load_dataset)."""
    path = _normal_gt_path(root)
    return None if path is None else NormalTruth(path, shape)
