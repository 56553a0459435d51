"""``make demo``: the whole lab job on the simulated rig, through the real command line.

Each stage is the ``ps-lab`` command a user would type, run as its own process:

1. ``ps-lab capture --rig rigs/simulated.toml`` — the simulated protocol-v1 controller is served on a
   pseudo-terminal and driven through the OS serial layer; the simulated camera writes DNG frames;
2. ``ps-lab calibrate RUN`` — chrome sphere and highlights, no flags;
3. ``ps-lab reconstruct RUN --method sbl --refine-lights 2 --depth poisson`` (normals, then depth
   and a mesh).

Then it prints a summary against the simulator's ground truth (``RUN/simulation/``), and runs the
near-light variant (``--near-rig``, default ``rigs/simulated-near.toml``: LEDs on a dome 3x the
object, two chrome spheres): capture, calibrate (LED positions), reconstruct with near lights and,
on the same frames, with the directional model; ``--no-near`` skips it. Then the lens variant
(``--lens-rig``, default ``rigs/simulated-lens.toml``: the same rig through a lens with k1 = -0.25):
board frames (``ps-lab rig board-frames``), ``ps-lab calibrate-camera``, a capture that carries the
camera (``--camera``), calibrate and reconstruct with undistortion; ``--no-lens`` skips it.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

from ps_lab.reconstruct.metrics import angular_errors_deg, depth_error, error_summary

DEFAULT_RIG = Path("rigs/simulated.toml")
DEFAULT_OUT = Path("demo-run")
DEFAULT_NEAR_RIG = Path("rigs/simulated-near.toml")
DEFAULT_LENS_RIG = Path("rigs/simulated-lens.toml")


def _stage(title: str, args: list[str]) -> float:
    """Run ``ps-lab ARGS`` in a child process; return its wall time, exit on failure."""
    print(f"\n== {title}: ps-lab {' '.join(args)}", flush=True)
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "ps_lab", *args], check=False)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        sys.exit(f"demo: stage '{title}' failed (exit {done.returncode})")
    return seconds


def _calibration_error(run: Path) -> dict[str, float]:
    estimated = np.loadtxt(run / "light_directions.txt", ndmin=2)
    truth = np.loadtxt(run / "simulation" / "light_directions_true.txt", ndmin=2)
    return error_summary(angular_errors_deg(estimated, truth))


def _clear_previous_demo(out: Path) -> None:
    # Only ever delete a folder this demo made: it holds a capture run and nothing else.
    if not out.exists():
        return
    if not (out / "run" / "manifest.json").is_file() and any(out.iterdir()):
        sys.exit(f"demo: {out} exists and is not a demo folder; remove it or pass --out")
    foreign = sorted(p.name for p in out.iterdir()
                     if p.name not in _DEMO_ENTRIES and not _DEMO_STAGING.fullmatch(p.name))
    if foreign:  # never delete what the user put beside the demo's folders
        sys.exit(f"demo: {out / foreign[0]} was not written by the demo; move it out of {out} "
                 "or pass --out")
    shutil.rmtree(out)


#: What the demo writes in its folder (the capture run and the near-light and lens variants).
_DEMO_ENTRIES = frozenset({"run", "near", "lens"})
#: Their staging folders, left by a demo that was killed.
_DEMO_STAGING = re.compile(r"\.(?:run|near|lens)\.(?:partial|old)-\d+")


def main(argv: list[str] | None = None) -> None:
    """Capture, calibrate and reconstruct on the simulated rig, then print a summary."""
    parser = argparse.ArgumentParser(prog="python -m ps_lab.demo", description=__doc__.splitlines()[0])
    parser.add_argument("--rig", type=Path, default=DEFAULT_RIG, help="rig file (default %(default)s)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="demo folder (replaced)")
    parser.add_argument("--near-rig", type=Path, default=DEFAULT_NEAR_RIG,
                        help="near-light rig file (default %(default)s)")
    parser.add_argument("--no-near", action="store_true", help="skip the near-light variant")
    parser.add_argument("--lens-rig", type=Path, default=DEFAULT_LENS_RIG,
                        help="rig with a distorting lens (default %(default)s)")
    parser.add_argument("--no-lens", action="store_true", help="skip the lens variant")
    args = parser.parse_args(argv)
    rigs = [args.rig] + ([] if args.no_near else [args.near_rig])
    for rig in rigs + ([] if args.no_lens else [args.lens_rig]):
        if not rig.is_file():
            sys.exit(f"demo: rig file {rig} not found (run from the repository root)")

    _clear_previous_demo(args.out)
    run = args.out / "run"
    recon = run / "recon" / "sbl"
    seconds = {
        "capture": _stage("capture", ["capture", "--rig", str(args.rig), "--out", str(run)]),
        "calibrate": _stage("calibrate", ["calibrate", str(run)]),
        "reconstruct": _stage(
            "reconstruct",
            ["reconstruct", str(run), "--method", "sbl", "--refine-lights", "2",
             "--out", str(recon), "--depth", "poisson"],  # fmt: skip
        ),
    }

    calibration = _calibration_error(run)
    metrics = json.loads((recon / "metrics.json").read_text())
    normal_error = metrics["angular_error_deg"]
    print("\n== summary")
    print(
        f"calibration error vs simulator truth: mean {calibration['mean']:.3f} deg, "
        f"max {calibration['max']:.3f} deg ({len(np.loadtxt(run / 'light_directions.txt', ndmin=2))} lights)"
    )
    print(
        f"SBL normal error on the object:       mean {normal_error['mean']:.3f} deg, "
        f"median {normal_error['median']:.3f} deg, p90 {normal_error['p90']:.3f} deg "
        f"({metrics['pixels']} pixels, {metrics['lights']} lights)"
    )
    depth = depth_error(np.load(recon / "depth.npy"), np.load(run / "simulation" / "depth_gt.npy"))
    print(
        f"depth error vs simulator truth:       rmse {depth['rmse']:.3f} px "
        f"({100 * depth['relative']:.2f} % of the {depth['range']:.1f} px depth range, "
        f"{metrics['depth']['method']}, {depth['pixels']} pixels)"
    )
    print("time per stage: " + ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items()))
    print(f"total {sum(seconds.values()):.1f} s")
    print(f"normal map:      {recon / 'normal.png'}")
    print(f"calibration:     {run / 'calibration.png'}")
    print(f"depth picture:   {recon / 'depth.png'}")
    print(f"mesh:            {recon / 'mesh.ply'}")
    print(f"see it relit:    ps-lab view {recon}")
    if not args.no_near:
        _near_variant(args.near_rig, args.out / "near")
    if not args.no_lens:
        _lens_variant(args.lens_rig, args.out / "lens")


def _near_variant(rig: Path, run: Path) -> None:
    """Capture, calibrate and reconstruct the near-light rig; print its summary."""
    near, directional = run / "recon" / "near", run / "recon" / "directional"
    seconds = {
        "capture": _stage("near-light capture", ["capture", "--rig", str(rig), "--out", str(run)]),
        "calibrate": _stage("near-light calibrate", ["calibrate", str(run)]),
        "reconstruct": _stage(
            "near-light reconstruct",
            ["reconstruct", str(run), "--lights", "near", "--out", str(near)],
        ),
    }
    _stage(
        "the same frames, directional model",
        ["reconstruct", str(run), "--lights", "directional", "--out", str(directional)],
    )
    positions = np.loadtxt(run / "light_positions.txt", ndmin=2)
    truth = np.loadtxt(run / "simulation" / "light_positions_true.txt", ndmin=2)
    dome = float(np.linalg.norm(truth, axis=1).mean())
    error = 100.0 * np.linalg.norm(positions - truth, axis=1) / dome
    metrics = json.loads((near / "metrics.json").read_text())
    near_error = metrics["angular_error_deg"]
    directional_error = json.loads((directional / "metrics.json").read_text())["angular_error_deg"]
    print("\n== near-light summary")
    print(
        f"LED positions vs simulator truth:     mean {np.nanmean(error):.2f} %, "
        f"max {np.nanmax(error):.2f} % of the dome radius ({len(positions)} lights)"
    )
    print(
        f"near-light normal error ({metrics['method']}):   mean {near_error['mean']:.3f} deg, "
        f"median {near_error['median']:.3f} deg ({metrics['near']['rounds']} rounds); "
        f"directional model on the same frames: mean {directional_error['mean']:.2f} deg"
    )
    print("time per stage: " + ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items()))
    print(f"normal map:      {near / 'normal.png'}")
    print(f"calibration:     {run / 'calibration.png'}")


def _lens_variant(rig: Path, folder: Path) -> None:
    """Board frames, calibrate-camera, capture with the camera, calibrate, reconstruct."""
    board, run, recon = folder / "board", folder / "run", folder / "run" / "recon"
    seconds = {
        "board frames": _stage("lens: board frames",
                               ["rig", "board-frames", "--rig", str(rig), "--out", str(board)]),
        "calibrate-camera": _stage(
            "lens: calibrate-camera",
            ["calibrate-camera", *sorted(str(p) for p in board.glob("board_*.png")),
             "--board", "charuco:9x6:20:15:DICT_5X5_100", "--out", str(board)],
        ),
        "capture": _stage("lens: capture", ["capture", "--rig", str(rig), "--out", str(run),
                                            "--camera", str(board / "camera.json")]),
        "calibrate": _stage("lens: calibrate (undistorted frames)", ["calibrate", str(run)]),
        "reconstruct": _stage("lens: reconstruct (undistorted frames)",
                              ["reconstruct", str(run), "--out", str(recon)]),
    }
    camera = json.loads((board / "camera.json").read_text())
    (fx, _, cx), (_, fy, cy), _ = camera["camera_matrix"]
    lens = _rig_lens_truth(rig)
    normal_error = json.loads((recon / "metrics.json").read_text())["angular_error_deg"]
    print("\n== lens summary")
    print(
        f"camera vs the simulated lens:         focal "
        f"{100 * ((fx * fy) ** 0.5 / lens['f'] - 1):+.2f} %, "
        f"principal point off by ({cx - lens['cx']:+.2f}, {cy - lens['cy']:+.2f}) px, "
        f"reprojection RMS {camera['rms_px']:.3f} px"
    )
    print(
        f"normal error, undistorted frames:     mean {normal_error['mean']:.3f} deg, "
        f"median {normal_error['median']:.3f} deg, p90 {normal_error['p90']:.3f} deg"
    )
    print("time per stage: " + ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items()))
    print(f"corners and residuals: {board / 'camera.png'}")


def _rig_lens_truth(rig: Path) -> dict[str, float]:
    """The simulated lens's focal length and principal point, as the rig file states them."""
    data = tomllib.loads(rig.read_text("utf-8"))
    lens, scene = data["lens"], data["scene"]
    cx, cy = lens.get("principal_point", ((scene["width"] - 1) / 2, (scene["height"] - 1) / 2))
    return {"f": float(lens.get("focal_length", scene["width"])), "cx": cx, "cy": cy}


if __name__ == "__main__":
    main()
