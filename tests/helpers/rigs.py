"""Rig files the tests share: a small scene (a rig file's tail) and whole small rigs."""

from __future__ import annotations

# A chrome sphere (and its nominal position for calibration) beside a glossy relief, 192x120,
# lights within 50 deg of the view with 2 deg nominal errors.
SMALL_SCENE = """[calibration.chrome_sphere]
center = [44.0, 44.0]
radius = 38.0

[scene]
width = 192
height = 120

[scene.lights]
seed = 5
max_zenith_deg = 50.0
nominal_error_deg = 2.0

[[scene.objects]]
kind = "chrome"
center = [44.0, 44.0]
radius = 38.0
albedo = [0.9, 0.9, 0.9]

[[scene.objects]]
kind = "relief"
center = [136.0, 60.0]
radius = 52.0
albedo = [0.75, 0.65, 0.55]
specular = 0.25
roughness = 0.12
seed = 3
"""


# A 6-light simulated rig with a small scene: the hostile tables' captures (made once).
SMALL_RIG = """
name = "small"
[controller]
driver = "simulated"
lights = 6
watchdog_ms = 5000
timeout_s = 0.3
[camera]
driver = "simulated"
exposure_s = 0.05
timeout_s = 2.0
retries = 1
seed = 2012
[calibration.chrome_sphere]
center = [40.0, 40.0]
radius = 32.0
[scene]
width = 160
height = 120
[scene.lights]
seed = 7
max_zenith_deg = 50.0
[[scene.objects]]
kind = "chrome"
center = [40.0, 40.0]
radius = 32.0
albedo = [0.9, 0.9, 0.9]
[[scene.objects]]
kind = "relief"
center = [108.0, 62.0]
radius = 50.0
albedo = [0.75, 0.65, 0.55]
seed = 3
"""


# A near rig whose file lists two chrome spheres, the second of which is not on the table.
NEAR_RIG_ONE_SPHERE_MISSING = """
name = "near-small"
[controller]
driver = "simulated"
lights = 6
watchdog_ms = 5000
timeout_s = 0.3
anisotropy = 1.0
[camera]
driver = "simulated"
exposure_s = 0.05
timeout_s = 2.0
retries = 1
seed = 2015
[[calibration.chrome_spheres]]
center = [30.0, 30.0]
radius = 26.0
[[calibration.chrome_spheres]]
center = [130.0, 90.0]
radius = 26.0
[scene]
width = 160
height = 120
[scene.lights]
seed = 11
max_zenith_deg = 50.0
dome_radius = 300.0
[[scene.objects]]
kind = "chrome"
center = [30.0, 30.0]
radius = 26.0
albedo = [0.9, 0.9, 0.9]
[[scene.objects]]
kind = "relief"
center = [80.0, 70.0]
radius = 30.0
albedo = [0.75, 0.65, 0.55]
seed = 3
"""
