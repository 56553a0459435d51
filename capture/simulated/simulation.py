"""The truth behind a simulated rig: its renderer scene, its true lights, and their files.

:func:`build_simulation` turns a rig file's ``[scene]`` (plain data, :class:`~ps_lab.capture.rig.
SceneConfig`) into the renderer's :class:`~ps_lab.render.Scene` and the true light layout;
:func:`write_truth` writes what a run's ``simulation/`` folder holds (normals, depth, mask, the
true lights in plan order). Real capture never reaches this module: :mod:`ps_lab.capture.connect`
imports it only when a rig selects a simulator, and hands the session :func:`write_truth` as a
hook.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ps_lab import render
from ps_lab.errors import DatasetError, RigError
from ps_lab.io.files import write_bytes_atomic
from ps_lab.io.light_files import light_table_bytes
from ps_lab.io.run import SIMULATION_DIR


@dataclass(frozen=True)
class Simulation:
    """The true scene and lights behind a simulated rig."""

    scene: render.Scene
    light_directions: np.ndarray  # (N, 3) true unit directions (from the scene origin for LEDs)
    light_intensities: np.ndarray  # (N, 3) true per-channel intensities (at the scene origin)
    point_lights: render.PointLights | None = None  # N LEDs on a near-light rig, else None


def build_simulation(rig: Any) -> Simulation:
    """Build the renderer scene and the true light layout of a simulated rig (a ``Rig``)."""
    if rig.scene is None:
        raise RigError(f"rig {rig.name!r} has no [scene] to simulate")
    sc = rig.scene
    scene = render.Scene(
        width=sc.width,
        height=sc.height,
        objects=tuple(
            render.SceneObject(o.kind, o.center, o.radius, o.albedo, o.specular, o.roughness,
                               o.seed)
            for o in sc.objects
        ),
        background=sc.background,
    )
    n = rig.n_lights
    layout = sc.lights
    if layout.directions is not None:
        directions = np.asarray(layout.directions, dtype=np.float64)
    else:
        directions = render.random_light_directions(
            n, np.random.default_rng(layout.seed), max_zenith_deg=layout.max_zenith_deg
        )
    point_lights = None
    if layout.dome_radius is not None:
        point_lights = render.PointLights(
            layout.dome_radius * directions, rig.controller.anisotropy, layout.led_radius
        )
    if layout.intensities is not None:
        intensities = np.asarray(layout.intensities, dtype=np.float64)
    else:
        rng = np.random.default_rng([layout.seed, 1])
        scale = 1.0 + layout.intensity_spread * rng.uniform(-1.0, 1.0, size=(n, 1))
        color = 1.0 + layout.color_spread * rng.uniform(-1.0, 1.0, size=(n, 3))
        intensities = scale * color
    return Simulation(
        scene=scene,
        light_directions=directions,
        light_intensities=intensities,
        point_lights=point_lights,
    )


def write_truth(simulation: Simulation, run_dir: Path, lights: Sequence[int]) -> None:
    """Write the simulator's ground truth into ``run_dir/simulation/``.

    Normals, depth and mask of the scene, and the true light directions, intensities (and LED
    positions on a near-light rig) of ``lights`` (1-based, in plan order), one row each.
    """
    folder = Path(run_dir) / SIMULATION_DIR
    folder.mkdir(exist_ok=True)
    truth = render.scene_ground_truth(simulation.scene)
    rows = [i - 1 for i in lights]
    write_bytes_atomic(folder / "normal_gt.npy",
                       _npy_bytes(np.asarray(truth["normals"], dtype=np.float64)))
    write_bytes_atomic(folder / "depth_gt.npy",
                       _npy_bytes(np.asarray(truth["depth"], dtype=np.float32)))
    ok, png = cv2.imencode(".png", np.where(truth["mask"], 255, 0).astype(np.uint8))
    if not ok:  # pragma: no cover - OpenCV always encodes a uint8 image
        raise DatasetError("cannot encode the ground-truth mask")
    write_bytes_atomic(folder / "mask.png", png.tobytes())
    write_bytes_atomic(folder / "light_directions_true.txt",
                       light_table_bytes(simulation.light_directions[rows]))
    write_bytes_atomic(folder / "light_intensities_true.txt",
                       light_table_bytes(simulation.light_intensities[rows]))
    if simulation.point_lights is not None:
        # the frame and units of light_positions.txt (scene frame, pixel units)
        positions = np.asarray(simulation.point_lights.positions)[rows]
        write_bytes_atomic(folder / "light_positions_true.txt", light_table_bytes(positions))


def _npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()
