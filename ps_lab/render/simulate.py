"""Write a rendered scene as a dataset folder in the layout ``ps-lab reconstruct`` reads."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import tifffile

from ps_lab.errors import DatasetError
from ps_lab.io.camera import CameraModel, write_camera
from ps_lab.io.codecs import imwrite
from ps_lab.io.files import staged_folder
from ps_lab.render.board import CharucoTarget, write_board_frames
from ps_lab.render.lens import distort_image
from ps_lab.render.light_sets import random_light_directions
from ps_lab.render.shading import render
from ps_lab.render.surfaces import relief_surface, sphere_surface

FORMATS = ("png16", "tiff32", "npy")
SCENES = ("sphere", "relief")
# png16: the brightest rendered value is written as this share of 65535 (headroom for noise).
PNG16_PEAK = 0.9


@dataclass(frozen=True)
class SimulationSettings:
    """Options of ``ps-lab simulate`` (see ``docs/renderer.md``)."""

    scene: str = "sphere"
    lights: int = 40
    size: int = 128
    seed: int = 0
    specular: float = 0.0
    roughness: float = 0.3
    noise_fraction: float = 0.0
    noise_sigma: float = 0.0
    cast_shadows: bool = True
    max_zenith_deg: float = 60.0
    image_format: str = "png16"
    #: Lens distortion (k1, k2, p1, p2, k3) applied to the frames, or None (an ideal lens).
    lens: tuple[float, ...] | None = None
    #: Focal length of that lens in pixels (default: the image size).
    focal_length: float | None = None
    #: ChArUco board views written to ``board/`` through the same lens (0: none).
    board_frames: int = 0

    def camera(self) -> CameraModel | None:
        """The simulated camera (principal point at the image centre), or None without a lens."""
        if self.lens is None:
            return None
        f = float(self.focal_length if self.focal_length is not None else self.size)
        c = (self.size - 1) / 2.0
        coefficients = tuple(float(v) for v in self.lens) + (0.0,) * (5 - len(self.lens))
        size = (self.size, self.size)
        return CameraModel(f, f, c, c, coefficients, size)  # type: ignore[arg-type]

    def validate(self) -> None:
        """Raise :class:`DatasetError` on settings that cannot be rendered."""
        if self.scene not in SCENES:
            raise DatasetError(f"unknown scene {self.scene!r}; choose one of {', '.join(SCENES)}")
        if self.image_format not in FORMATS:
            raise DatasetError(
                f"unknown image format {self.image_format!r}; choose one of {', '.join(FORMATS)}"
            )
        if self.lights < 3:
            raise DatasetError(f"--lights: need at least 3 lights, got {self.lights}")
        if self.size < 8:
            raise DatasetError(f"--size: image size must be at least 8 pixels, got {self.size}")
        if self.roughness <= 0:
            raise DatasetError(f"--roughness must be positive, got {self.roughness}")
        if self.specular < 0 or self.noise_sigma < 0:
            raise DatasetError("--specular and --noise-sigma must be >= 0")
        if not 0.0 <= self.noise_fraction <= 1.0:
            raise DatasetError(f"--noise-fraction must be in [0, 1], got {self.noise_fraction}")
        if self.lens is not None and not (1 <= len(self.lens) <= 5
                                          and all(np.isfinite(v) for v in self.lens)):
            raise DatasetError("--lens: give 1 to 5 finite numbers K1[,K2,P1,P2,K3]")
        if self.focal_length is not None and not self.focal_length > 0:
            raise DatasetError(f"--focal-length must be positive, got {self.focal_length}")
        if self.board_frames and self.board_frames < 3:
            raise DatasetError(f"--board-frames: at least 3 views, got {self.board_frames}")
        if not 0.0 < self.max_zenith_deg < 90.0:
            raise DatasetError(
                f"--max-zenith must be in (0, 90) degrees, got {self.max_zenith_deg}"
            )


def simulated_board(size: int) -> CharucoTarget:
    """The ChArUco board of ``ps-lab simulate --board-frames``: 9x6 squares, 20/15 mm."""
    return CharucoTarget(9, 6, 20.0, 15.0, "DICT_5X5_100")


def board_spec(target: CharucoTarget) -> str:
    """The ``--board`` option of ``ps-lab calibrate-camera`` for ``target``."""
    return (f"charuco:{target.cols}x{target.rows}:{target.square:g}:{target.marker:g}:"
            f"{target.dictionary}")


def check_new_dataset_folder(out: Path) -> None:
    """Raise :class:`DatasetError` unless ``out`` is absent or an empty folder."""
    if out.exists():
        if not out.is_dir():
            raise DatasetError(f"{out}: exists and is not a folder; choose a new output folder")
        if any(out.iterdir()):
            raise DatasetError(f"{out}: folder exists and is not empty; choose a new output folder")


def write_simulated_dataset(
    out: Path,
    settings: SimulationSettings,
    *,
    progress: Callable[[int], None] | None = None,
) -> dict:
    """Render a scene under random lights and write it as a dataset folder.

    Parameters
    ----------
    out : Path
        Target folder; must not exist or be empty. Written into a temporary sibling folder and
        renamed at the end, so a failed run leaves nothing behind.
    settings : SimulationSettings
        Scene, lights, material, noise and image format.
    progress : callable, optional
        Called with 1 after each light is rendered and again after each image is written
        (``2 * settings.lights`` calls in all).

    Returns
    -------
    dict
        What was written: ``path``, ``images``, ``shape``, ``png16_scale`` (or None), ``pixels``.
    """
    settings.validate()
    out = Path(out)
    check_new_dataset_folder(out)
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise DatasetError(f"{parent}: parent folder does not exist")

    rng = np.random.default_rng(settings.seed)
    shape = (settings.size, settings.size)
    if settings.scene == "sphere":
        surface = sphere_surface(shape)
    else:
        surface = relief_surface(shape, seed=settings.seed)
    light_directions = random_light_directions(
        settings.lights, rng, max_zenith_deg=settings.max_zenith_deg
    )
    images = render(
        surface,
        light_directions,
        cast_shadows=settings.cast_shadows,
        specular=settings.specular,
        roughness=settings.roughness,
        noise_sigma=settings.noise_sigma,
        noise_fraction=settings.noise_fraction,
        rng=rng,
        progress=progress,
    )

    camera = settings.camera()
    if camera is not None:  # the ideal render seen through the lens; truth stays undistorted
        images = np.stack([distort_image(image, camera) for image in images])

    digits = max(3, len(str(settings.lights)))
    suffix = {"png16": ".png", "tiff32": ".tiff", "npy": ".npy"}[settings.image_format]
    names = [f"{i + 1:0{digits}d}{suffix}" for i in range(settings.lights)]
    peak = float(images.max())
    scale = PNG16_PEAK * 65535.0 / peak if peak > 0 else 1.0

    with staged_folder(out, check=check_new_dataset_folder, error=DatasetError) as staging:
        for name, image in zip(names, images, strict=True):
            path = staging / name
            if settings.image_format == "png16":
                pixels = np.clip(np.rint(image * scale), 0, 65535).astype(np.uint16)
                if not imwrite(path, pixels):
                    raise DatasetError(f"{path}: OpenCV could not write the image")
            elif settings.image_format == "tiff32":
                tifffile.imwrite(path, image.astype(np.float32))
            else:
                np.save(path, image.astype(np.float32))
            if progress is not None:
                progress(1)
        (staging / "filenames.txt").write_text("".join(f"{n}\n" for n in names))
        np.savetxt(staging / "light_directions.txt", light_directions, fmt="%.9f")
        np.savetxt(staging / "light_intensities.txt", np.ones((settings.lights, 3)), fmt="%.6f")
        imwrite(staging / "mask.png", surface.mask.astype(np.uint8) * 255)
        np.save(staging / "normal_gt.npy", surface.normals.astype(np.float32))
        # Depth along the viewing axis, away from the camera, in pixels (docs/datasets.md).
        depth = np.where(surface.mask, -surface.height, np.nan).astype(np.float32)
        np.save(staging / "depth_gt.npy", depth)
        meta = {
            "format": "ps-lab-simulation",
            "version": 1,
            "settings": asdict(settings),
            "png16_scale": scale if settings.image_format == "png16" else None,
        }
        (staging / "simulation.json").write_text(json.dumps(meta, indent=2) + "\n")
        if camera is not None:
            # The truth, under a name no reader takes for the dataset's calibrated camera: the
            # ground truth (mask, normals, depth) is in undistorted pixels, the frames are not.
            write_camera(staging / "camera_truth.json", camera, truth="simulated lens")
            if settings.board_frames:
                target = simulated_board(settings.size)
                write_board_frames(staging / "board", target, camera, settings.board_frames,
                                   seed=settings.seed)
                meta["board"] = board_spec(target)
                (staging / "simulation.json").write_text(json.dumps(meta, indent=2) + "\n")
    return {
        "path": out,
        "images": settings.lights,
        "shape": shape,
        "png16_scale": meta["png16_scale"],
        "pixels": int(surface.mask.sum()),
    }
