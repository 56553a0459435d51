"""Camera calibration benchmark: rendered ChArUco boards through known lenses (issue 33).

For each k1 (with a small k2 and tangential terms, principal point off the centre) a 9 x 6 ChArUco
board is rendered at seeded poses (``ps_lab.render.board``: OpenCV's board image through the
pinhole and the lens, 2 x 2 sub-pixels, Gaussian noise of 1 % of white, 8-bit) and calibrated
(``ps_lab.calibration.calibrate_from_corners``). Reported: focal length and principal point
errors, k1 as found, the undistortion map's error over the frame (where a recorded pixel lands in
the undistorted frame, estimated camera vs true one), the RMS against OpenCV's own 5-coefficient
``calibrateCamera`` on the same corners, and normals: a Lambertian sphere and relief rendered
ideal, seen through the lens, undistorted with the *estimated* camera, solved by least squares,
against the ideal render's normals (and without undistortion). Usage::

    python benchmarks/camera.py [--size 640x480] [--views 12] [--markdown FILE]
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np

from ps_lab.calibration import calibrate_from_corners, detect_corners, grey_u8, parse_board
from ps_lab.io.camera import CameraModel, undistort_frame, undistort_points
from ps_lab.render import random_light_directions, relief_surface, render, sphere_surface
from ps_lab.render.board import CharucoTarget, board_poses, render_charuco
from ps_lab.render.lens import distort_image

K1 = (-0.3, -0.2, -0.1, 0.0, 0.1)
TARGET = CharucoTarget(9, 6, 20.0, 15.0, "DICT_5X5_100")
SPEC = parse_board("charuco:9x6:20:15:DICT_5X5_100")


def _camera(k1: float, w: int, h: int) -> CameraModel:
    f = 1.15 * w
    return CameraModel(f, f * 1.002, (w - 1) / 2 + 0.03 * w, (h - 1) / 2 - 0.02 * h,
                       (k1, 0.03, 4e-4, -3e-4, 0.0), (w, h))


def _normals(stack: np.ndarray, lights: np.ndarray) -> np.ndarray:
    n, h, w = stack.shape
    g = np.linalg.lstsq(lights, stack.reshape(n, -1), rcond=None)[0].T
    return (g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)).reshape(h, w, 3)


def _normal_errors(truth: CameraModel, estimate: CameraModel, surface, lights):
    ideal = render(surface, lights, cast_shadows=False).astype(np.float32)
    recorded = np.stack([distort_image(i, truth) for i in ideal])
    undistorted = np.stack([undistort_frame(estimate, f[..., None])[0][..., 0] for f in recorded])
    lit = (np.einsum("hwc,lc->lhw", surface.normals, lights) > 0.02).all(0) & surface.mask
    inner = cv2.erode(lit.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    reference = _normals(ideal, lights)

    def angle(n):
        return np.degrees(np.arccos(np.clip(np.sum(n * reference, -1), -1, 1)))[inner]

    a, b = angle(_normals(undistorted, lights)), angle(_normals(recorded, lights))
    return a.mean(), a.max(), b.mean(), b.max()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="640x480")
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--markdown", default=None)
    args = parser.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    rows = []
    for k1 in K1:
        started = time.perf_counter()
        truth = _camera(k1, w, h)
        rng = np.random.default_rng(7)
        detections = []
        for rvec, tvec in board_poses(TARGET, truth, args.views, seed=4):
            image = render_charuco(TARGET, truth, rvec, tvec, supersample=2)
            image = image + rng.normal(0.0, 0.01, image.shape)
            detections.append(detect_corners(grey_u8(image.astype(np.float32), 8), SPEC))
        result = calibrate_from_corners(detections, (w, h))
        est = result.camera
        grid = np.stack(np.meshgrid(np.arange(0, w, 4.0), np.arange(0, h, 4.0)), -1).reshape(-1, 2)
        seen = np.concatenate([d.image_points for d in detections]).astype(np.float64)
        hull = cv2.convexHull(seen.astype(np.float32))
        inside = np.array([cv2.pointPolygonTest(hull, (float(x), float(y)), False) >= 0
                           for x, y in grid])
        moved = np.linalg.norm(undistort_points(est, grid) - undistort_points(truth, grid), axis=1)
        lights = random_light_directions(12, np.random.default_rng(1), max_zenith_deg=45)
        sphere = sphere_surface((h, w), radius=0.4 * h)
        relief = relief_surface((h, w), seed=3, radius=0.45 * h)
        rows.append({
            "k1": k1,
            "focal_pct": 100 * (est.focal_length / truth.focal_length - 1),
            "pp_px": float(np.hypot(est.cx - truth.cx, est.cy - truth.cy)),
            "k1_found": est.distortion[0],
            "map_mean": moved[inside].mean(), "map_max_in": moved[inside].max(),
            "map_max": moved.max(),
            "rms": est.rms_px, "rms_cv": result.rms_opencv, "k3": result.k3_fitted,
            "refused": len(result.refused),
            "sphere": _normal_errors(truth, est, sphere, lights),
            "relief": _normal_errors(truth, est, relief, lights),
            "seconds": time.perf_counter() - started,
        })
        r = rows[-1]
        print(f"k1 {k1:+.1f}: f {r['focal_pct']:+.3f} %, pp {r['pp_px']:.2f} px, k1 found "
              f"{r['k1_found']:+.4f}, map {r['map_mean']:.3f}/{r['map_max_in']:.3f} px, RMS "
              f"{r['rms']:.4f} vs OpenCV {r['rms_cv']:.4f}, sphere {r['sphere'][0]:.4f}/"
              f"{r['sphere'][1]:.4f} deg (raw {r['sphere'][2]:.2f}/{r['sphere'][3]:.2f}), relief "
              f"{r['relief'][0]:.4f}/{r['relief'][1]:.4f} (raw {r['relief'][2]:.2f}/"
              f"{r['relief'][3]:.2f}), {r['seconds']:.1f} s", flush=True)
    if args.markdown:
        lines = [
            "| k1 | focal error | principal point error | k1 found | undistortion map error, "
            "mean / max where seen / max in frame | RMS (ours / OpenCV's 5-coef) | sphere normals "
            "undistorted: mean / max | without undistortion | relief normals undistorted | "
            "without |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in rows:
            s, rl = r["sphere"], r["relief"]
            lines.append(
                f"| {r['k1']:+.1f} | {r['focal_pct']:+.3f} % | {r['pp_px']:.2f} px | "
                f"{r['k1_found']:+.4f} | {r['map_mean']:.3f} / {r['map_max_in']:.3f} / "
                f"{r['map_max']:.2f} px | {r['rms']:.4f} / {r['rms_cv']:.4f} px "
                f"({100 * (r['rms'] / r['rms_cv'] - 1):+.1f} %) | {s[0]:.4f} / {s[1]:.4f}° | "
                f"{s[2]:.2f} / {s[3]:.2f}° | {rl[0]:.4f} / {rl[1]:.4f}° | {rl[2]:.2f} / "
                f"{rl[3]:.2f}° |"
            )
        with open(args.markdown, "w", encoding="utf-8") as fh:
            fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
