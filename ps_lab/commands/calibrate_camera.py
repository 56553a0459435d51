"""`ps-lab calibrate-camera`: intrinsics and lens distortion from photographs of a board."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ps_lab._cli_util import lab_command, progress_bar
from ps_lab.calibration import calibrate_camera_files, parse_board


@lab_command
def calibrate_camera(
    frames: Annotated[
        list[Path],
        typer.Argument(
            help="Photos of the board (PNG, JPEG, TIFF, DNG...), one camera, one image size; "
            "10-20 views, tilted up to ~40 deg, the board reaching the frame's corners.",
            show_default=False,
        ),
    ],
    board: Annotated[
        str,
        typer.Option(
            metavar="<spec>",
            help="charuco:COLSxROWS:SQUARE:MARKER[:DICT] (squares across x down, 3 to 200 a "
            "side; square and marker side in mm, 0.01 to 10000, the marker 0.1 to 1 x the "
            "square; ArUco dictionary, default DICT_5X5_100) or chessboard:COLSxROWS:SQUARE "
            "(squares, not inner corners, at least 4x4).",
            show_default=False,
        ),
    ],
    out: Annotated[
        Path,
        typer.Option(help="Folder for camera.json and camera.png (created if needed)."),
    ] = Path("."),
) -> None:
    """Calibrate the camera: 3x3 matrix, 5 distortion coefficients (k1 k2 p1 p2 k3), RMS.

    Writes camera.json (OpenCV's calibrateCamera on the sub-pixel corners: overall and per-frame
    reprojection RMS, the frames refused and why) and camera.png (the corners in green, the
    residuals in red, magnified). Name camera.json in the rig file ([lens] camera) or copy it
    into a dataset folder: calibrate, reconstruct and integrate then undistort the frames.

    Refused: a reprojection RMS above 2 px (a wrong --board or bent board), fewer than 3
    distinct views, views whose board planes are all parallel (tilt spread under 5 deg), a
    standard deviation of f or of the principal point above 5 % (of f, of the frame); weak views
    (tilt spread under 15 deg, sigma f over 1 %, sigma c over 2 %) get one warning line. The
    1-sigma uncertainties of fx, fy, cx, cy are printed and written to camera.json.
    """
    spec = parse_board(board)
    with progress_bar(len(frames), "board corners") as advance:
        result, written = calibrate_camera_files(frames, spec, out, progress=advance)
    cam = result.camera
    k1, k2, p1, p2, k3 = cam.distortion
    used = len(frames) - len(result.refused)
    sd = result.sigma
    typer.echo(
        f"fx {cam.fx:.2f} +/- {sd['fx']:.2f} fy {cam.fy:.2f} +/- {sd['fy']:.2f} px, principal "
        f"point ({cam.cx:.2f} +/- {sd['cx']:.2f}, {cam.cy:.2f} +/- {sd['cy']:.2f}) (1 sigma); "
        f"k1 {k1:.5f} k2 {k2:.5f} p1 {p1:.6f} p2 {p2:.6f} k3 {k3:.5f}"
    )
    views = result.views
    typer.echo(
        f"reprojection RMS {cam.rms_px:.4f} px over {used} of {len(frames)} frames"
        + (f" ({views.distinct_views} distinct views, tilt spread {views.tilt_spread_deg:.1f} deg)"
           if views is not None else "")
    )
    for k, reason in sorted(result.refused.items()):
        typer.secho(f"warning: refused {frames[k]}: {reason}", fg=typer.colors.YELLOW, err=True)
    if result.warning is not None:
        typer.secho(f"warning: {result.warning}", fg=typer.colors.YELLOW, err=True)
    for path in written.values():
        typer.echo(f"wrote {path}")


def register(app: typer.Typer) -> None:
    """Add ``calibrate-camera`` to the app."""
    app.command("calibrate-camera")(calibrate_camera)
