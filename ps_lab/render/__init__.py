"""The synthetic world: an orthographic photometric-stereo renderer with ground-truth normals.

Used by ``ps-lab simulate``, the simulated camera, the benchmarks and the tests; a layer below the
stage packages (capture, calibration, reconstruct) and above ``ps_lab.io``. See
``docs/renderer.md``.

- :mod:`~ps_lab.render.light_sets`: random and perturbed light directions
- :mod:`~ps_lab.render.surfaces`: :class:`Surface`, :func:`sphere_surface`, :func:`relief_surface`
- :mod:`~ps_lab.render.shading`: :func:`render` (Lambert + Cook-Torrance, cast shadows),
  :func:`render_chrome_sphere`
- :mod:`~ps_lab.render.scene`: :class:`SceneObject`, :class:`Scene`, :func:`render_scene`,
  :func:`scene_ground_truth` (the simulated rig's scene)
- :mod:`~ps_lab.render.near_shading`: LEDs at a finite distance (:class:`PointLights`,
  :func:`render_near`, :func:`render_chrome_near`, :func:`dome_light_positions`)
- :mod:`~ps_lab.render.simulate`: :func:`write_simulated_dataset` behind ``ps-lab simulate``
"""

from ps_lab.render.light_sets import perturb_light_directions, random_light_directions
from ps_lab.render.near_shading import (
    PointLights,
    dome_light_positions,
    render_chrome_near,
    render_near,
)
from ps_lab.render.scene import Scene, SceneObject, render_scene, scene_ground_truth
from ps_lab.render.shading import render, render_chrome_sphere
from ps_lab.render.simulate import (
    PNG16_PEAK,
    SimulationSettings,
    check_new_dataset_folder,
    write_simulated_dataset,
)
from ps_lab.render.surfaces import Surface, relief_surface, sphere_surface

__all__ = [
    "PNG16_PEAK",
    "PointLights",
    "Scene",
    "SceneObject",
    "SimulationSettings",
    "Surface",
    "check_new_dataset_folder",
    "dome_light_positions",
    "perturb_light_directions",
    "random_light_directions",
    "relief_surface",
    "render",
    "render_chrome_near",
    "render_chrome_sphere",
    "render_near",
    "render_scene",
    "scene_ground_truth",
    "sphere_surface",
    "write_simulated_dataset",
]
