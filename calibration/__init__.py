"""Light calibration from a chrome sphere (and intensities from a matte sphere).

Camera intrinsics and lens distortion from a board (:mod:`._camera_calibration`,
:func:`calibrate_camera_files` behind ``ps-lab calibrate-camera``; the camera file and undistortion
live in :mod:`ps_lab.io.camera`, re-exported here). Pure functions on arrays; :func:`calibrate` runs the whole chain (sphere outline → highlights →
mirror-law directions → matte-sphere intensities) and :func:`write_calibration` writes the
DiLiGenT light tables, ``calibration.json`` and ``calibration.png``. See ``docs/calibration.md``.
"""

from ps_lab.calibration._calibrate import Calibration, calibrate
from ps_lab.calibration._calibration_outputs import (
    OUTPUT_FILES,
    calibration_picture,
    calibration_record,
    write_calibration,
    zenith_azimuth_deg,
)
from ps_lab.calibration._camera_calibration import (
    BoardSpec,
    CameraCalibration,
    Detection,
    calibrate_camera_files,
    calibrate_from_corners,
    camera_picture,
    detect_corners,
    grey_u8,
    parse_board,
)
from ps_lab.calibration._circle import (
    Circle,
    CircleFit,
    circle_candidates,
    circle_inside_image,
    consensus_circle,
    fit_circle,
    refine_circle,
    summary_image,
)
from ps_lab.calibration._highlight import Highlight, locate_highlight
from ps_lab.calibration._intensity import fit_light_intensities, led_intensities_at_origin
from ps_lab.calibration._leds import LedModel, calibrate_leds, with_led_model
from ps_lab.calibration._mirror_geometry import (
    highlights_from_light_directions,
    light_directions_from_highlights,
)
from ps_lab.calibration._positions import Triangulation, reflected_rays, triangulate_lights
from ps_lab.calibration._probes import combine_probes
from ps_lab.calibration._rig_spheres import (
    rig_anisotropy,
    rig_chrome_spheres,
    rig_circles,
    rig_led_intensities,
    rig_object_outline,
)
from ps_lab.calibration._spheres import chrome_score, circle_residual
from ps_lab.io.camera import (
    CameraModel,
    distort_points,
    undistort_frame,
    undistort_points,
    undistortion_maps,
)

__all__ = [
    "BoardSpec",
    "CameraCalibration",
    "CameraModel",
    "Detection",
    "calibrate_camera_files",
    "calibrate_from_corners",
    "camera_picture",
    "detect_corners",
    "distort_points",
    "grey_u8",
    "parse_board",
    "undistort_frame",
    "undistort_points",
    "undistortion_maps",
    "OUTPUT_FILES",
    "Calibration",
    "Circle",
    "CircleFit",
    "Highlight",
    "LedModel",
    "Triangulation",
    "calibrate",
    "calibrate_leds",
    "calibration_picture",
    "calibration_record",
    "chrome_score",
    "circle_candidates",
    "circle_inside_image",
    "consensus_circle",
    "circle_residual",
    "combine_probes",
    "fit_circle",
    "fit_light_intensities",
    "highlights_from_light_directions",
    "led_intensities_at_origin",
    "light_directions_from_highlights",
    "locate_highlight",
    "reflected_rays",
    "refine_circle",
    "rig_anisotropy",
    "rig_chrome_spheres",
    "rig_circles",
    "rig_led_intensities",
    "rig_object_outline",
    "summary_image",
    "triangulate_lights",
    "with_led_model",
    "write_calibration",
    "zenith_azimuth_deg",
]
