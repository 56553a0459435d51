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
            help="charuco:COLSxROWS:SQUARE:MARKER[:DICT] (squares across x down, square and "
            "marker side in mm, ArUco dictionary, default DICT_5X5_100) or "
            "chessboard:COLSxROWS:SQUARE (squares, not inner corners).",
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
    """
    spec = parse_board(board)
    with progress_bar(len(frames), "board corners") as advance:
        result, written = calibrate_camera_files(frames, spec, out, progress=advance)
    cam = result.camera
    k1, k2, p1, p2, k3 = cam.distortion
    used = len(frames) - len(result.refused)
    typer.echo(
        f"fx {cam.fx:.2f} fy {cam.fy:.2f} px, principal point ({cam.cx:.2f}, {cam.cy:.2f}); "
        f"k1 {k1:.5f} k2 {k2:.5f} p1 {p1:.6f} p2 {p2:.6f} k3 {k3:.5f}"
    )
    typer.echo(f"reprojection RMS {cam.rms_px:.4f} px over {used} of {len(frames)} frames")
    for k, reason in sorted(result.refused.items()):
        typer.secho(f"warning: refused {frames[k]}: {reason}", fg=typer.colors.YELLOW, err=True)
    for path in written.values():
        typer.echo(f"wrote {path}")


def register(app: typer.Typer) -> None:
    """Add ``calibrate-camera`` to the app."""
    app.command("calibrate-camera")(calibrate_camera)
