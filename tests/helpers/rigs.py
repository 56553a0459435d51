"""The small simulated scene the end-to-end and PTP/IP camera tests share (a rig file's tail)."""

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
