"""A calibration target for the synthetic world: a ChArUco board seen through a known camera.

:func:`render_charuco` draws OpenCV's own board image (``cv2.aruco.CharucoBoard.generateImage``)
on a plane at a known pose, through the camera matrix and lens of a
:class:`~ps_lab.io.camera.CameraModel`: every recorded sub-pixel is traced back through the lens
(:func:`ps_lab.render.lens.lens_source_positions`), through the pinhole onto the board plane, and
reads the board image there (bilinear on a board image finer than the frame's pixels); sub-pixels
are averaged. :func:`board_poses` gives seeded poses that fill the frame, tilted up to ~35 deg,
the views a calibration needs. :func:`board_corners_truth` projects the true corners.

Board frame (OpenCV's): origin at the board's top-left corner, x along the columns, y along the
rows, z into the board; units as ``square`` (e.g. mm).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ps_lab.errors import OutputError
from ps_lab.io.camera import CameraModel
from ps_lab.io.codecs import imwrite
from ps_lab.render.lens import lens_source_positions


@dataclass(frozen=True)
class CharucoTarget:
    """A ChArUco board: squares across and down, square and marker sides, ArUco dictionary."""

    cols: int = 9
    rows: int = 6
    square: float = 20.0
    marker: float = 15.0
    dictionary: str = "DICT_5X5_100"

    def board(self) -> cv2.aruco.CharucoBoard:
        """OpenCV's board object."""
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square, self.marker, dictionary)

    @property
    def size(self) -> tuple[float, float]:
        """(width, height) of the board in its units."""
        return self.cols * self.square, self.rows * self.square


def board_picture(target: CharucoTarget, pixels_per_square: int = 48) -> np.ndarray:
    """The board as OpenCV draws it, (rows*pps, cols*pps) float32 in [0, 1] (no margin)."""
    size = (target.cols * pixels_per_square, target.rows * pixels_per_square)
    picture = target.board().generateImage(size, marginSize=0, borderBits=1)
    return picture.astype(np.float32) / 255.0


def render_charuco(
    target: CharucoTarget,
    camera: CameraModel,
    rvec: np.ndarray,
    tvec: np.ndarray,
    *,
    supersample: int = 3,
    pixels_per_square: int = 48,
    background: float = 0.35,
    margin: float = 0.5,
    picture: np.ndarray | None = None,
) -> np.ndarray:
    """Render the board at pose ``(rvec, tvec)`` as the camera records it.

    Parameters
    ----------
    target : CharucoTarget
    camera : CameraModel
        Intrinsics, distortion and frame size.
    rvec, tvec : ndarray of shape (3,)
        Board-to-camera pose (Rodrigues vector, translation in board units).
    supersample : int
        Sub-pixels per pixel side.
    pixels_per_square : int
        Resolution of the board image sampled.
    background : float
        Grey level beyond the board.
    margin : float
        White border around the printed squares, in squares.
    picture : ndarray, optional
        :func:`board_picture` (computed when omitted).

    Returns
    -------
    ndarray of shape (H, W), float32 in [0, 1]
    """
    w, h = camera.image_size
    pic = board_picture(target, pixels_per_square) if picture is None else picture
    map_x, map_y = lens_source_positions(camera, (h, w), supersample)
    x = (map_x.astype(np.float64) - camera.cx) / camera.fx
    y = (map_y.astype(np.float64) - camera.cy) / camera.fy
    rotation, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3))
    plane = np.column_stack([rotation[:, 0], rotation[:, 1], np.asarray(tvec, float).reshape(3)])
    inverse = np.linalg.inv(plane)  # ray (x, y, 1) -> board (X, Y, 1) up to scale
    bx = inverse[0, 0] * x + inverse[0, 1] * y + inverse[0, 2]
    by = inverse[1, 0] * x + inverse[1, 1] * y + inverse[1, 2]
    bw = inverse[2, 0] * x + inverse[2, 1] * y + inverse[2, 2]
    front = bw > 0  # the plane in front of the camera
    scale = pixels_per_square / target.square
    u = np.where(front, bx / np.where(front, bw, 1.0), -1e9) * scale - 0.5
    v = np.where(front, by / np.where(front, bw, 1.0), -1e9) * scale - 0.5
    squares = cv2.remap(pic, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=1.0)
    pad = margin * pixels_per_square
    ph, pw = pic.shape
    on_board = front & (u > -pad) & (v > -pad) & (u < pw + pad) & (v < ph + pad)
    fine = np.where(on_board, squares, np.float32(background)).astype(np.float32)
    s = int(supersample)
    return fine.reshape(h, s, w, s).mean(axis=(1, 3)).astype(np.float32)


def board_corners_truth(
    target: CharucoTarget, camera: CameraModel, rvec: np.ndarray, tvec: np.ndarray
) -> np.ndarray:
    """(m, 2) recorded pixel positions of the board's inner corners (OpenCV's projection)."""
    corners = target.board().getChessboardCorners().astype(np.float64)
    points, _ = cv2.projectPoints(corners, np.asarray(rvec, float), np.asarray(tvec, float),
                                  camera.matrix, camera.coefficients)
    return points.reshape(-1, 2)


def board_poses(
    target: CharucoTarget, camera: CameraModel, count: int, seed: int = 0, fill: float = 0.7
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Seeded board poses for a calibration: fronto-parallel first, then tilted and shifted.

    The board's centre is placed at a distance where it spans ``fill`` of the frame's width,
    tilted about x and y by up to 35 deg, turned about the view axis by up to 20 deg, and shifted
    so that the views together reach the frame's corners.

    Returns
    -------
    list of (rvec, tvec), each ndarray of shape (3,)
    """
    rng = np.random.default_rng(seed)
    w, h = camera.image_size
    bw, bh = target.size
    distance = camera.fx * bw / (fill * w)
    poses = []
    for k in range(count):
        if k == 0:
            angles = np.zeros(3)
            shift = np.zeros(2)
        else:
            angles = np.radians([rng.uniform(-35, 35), rng.uniform(-35, 35), rng.uniform(-20, 20)])
            shift = rng.uniform(-0.22, 0.22, 2) * np.array([w, h])
        rx, _ = cv2.Rodrigues(np.array([angles[0], 0.0, 0.0]))
        ry, _ = cv2.Rodrigues(np.array([0.0, angles[1], 0.0]))
        rz, _ = cv2.Rodrigues(np.array([0.0, 0.0, angles[2]]))
        rotation = rz @ ry @ rx
        z = distance * rng.uniform(0.9, 1.15) if k else distance
        centre_cam = np.array([shift[0] / camera.fx * z, shift[1] / camera.fy * z, z])
        # the board's centre (bw/2, bh/2, 0) lands at centre_cam
        tvec = centre_cam - rotation @ np.array([bw / 2.0, bh / 2.0, 0.0])
        rvec, _ = cv2.Rodrigues(rotation)
        poses.append((rvec.reshape(3), tvec))
    return poses


def write_board_frames(
    folder: Path,
    target: CharucoTarget,
    camera: CameraModel,
    count: int,
    *,
    seed: int = 0,
    noise_sigma: float = 0.005,
    supersample: int = 2,
) -> list[Path]:
    """Render ``count`` seeded board views and write them as 8-bit PNGs ``board_001.png``...

    Returns
    -------
    list of Path
        The files written, in pose order.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed + 1)
    picture = board_picture(target)
    paths = []
    for k, (rvec, tvec) in enumerate(board_poses(target, camera, count, seed=seed)):
        image = render_charuco(target, camera, rvec, tvec, supersample=supersample,
                               picture=picture)
        image = image + rng.normal(0.0, noise_sigma, image.shape)
        path = folder / f"board_{k + 1:03d}.png"
        if not imwrite(path, np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)):
            raise OutputError(f"{path}: OpenCV could not write the PNG")
        paths.append(path)
    return paths
