"""Near lights: normal error against the dome radius, and the cost of per-pixel lights.

Usage (from the repository root):

    .venv/bin/python benchmarks/near_lights.py sweep [--ratios 2 3 5 10 20]
    .venv/bin/python benchmarks/near_lights.py speed
    .venv/bin/python benchmarks/near_lights.py table [--focal-px 1500]
    .venv/bin/python benchmarks/near_lights.py outline
    .venv/bin/python benchmarks/near_lights.py ablation [--sphere-radius 25]
    .venv/bin/python benchmarks/near_lights.py leds [--mu 0 1 2 3]

``table`` renders the second rig (``ps_lab.render.table_rig``: identical LEDs, spheres and object
on one table, no matte sphere, 16-bit PNG, and its far twin), runs ``ps-lab calibrate`` with the
two ``--sphere`` circles (plus the variants of the intensity model and the outline statement)
and ``ps-lab reconstruct`` near / directional / far, and prints the table of docs/solvers.md.
``outline`` measures the searched outline height's error on that rig over dome sizes and object
heights (default options).

``ablation`` renders the table rig at the issue-33 size (dome 660 px, object 230 px) with less
noise (300 000 e- at full scale) and replaces one factor of the near solve at a time by the truth:
the LED positions, the intensities at the origin, the outline's height, the depth itself.
``leds`` renders LEDs with ``cos^mu`` beams (axes tilted up to 8 deg, outputs 1 +- 10 %) and a flat
matte board under them, calibrates with ``--flat-field`` and reconstructs with each
``--led-model``; then a second board, 15 px higher and with other noise, reconstructed as the
object (normals against the plane's).

``sweep`` renders the scene of ``rigs/simulated-near.toml`` (400x300, a glossy relief of 200 px,
two chrome spheres and a matte sphere of radius 50) with 24 LEDs on a dome of ``ratio`` x 200 px
(zenith <= 55 deg, intensities 1 +- 10 %, cos^1 emission, LED radius 15 px) as float frames with
Gaussian noise (sigma 2e-3), calibrates them with ``ps_lab.calibration.calibrate`` (two spheres:
positions; matte sphere: intensities) and solves SBL directionally (each light's direction from
the scene centre) and with near lights; the "far rig" is the same object lit from the same
directions at infinity, calibrated from one sphere. Every solve drops observations <= 0.02
(``--shadow-threshold 0.02``); ``--no-threshold`` keeps them.

``speed`` times the SBL kernels per pixel-iteration (directional vs per-pixel light vectors, the
same problems) and the seconds per near-light round on the sweep's scene at 3x.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from ps_lab import render
from ps_lab.calibration import calibrate
from ps_lab.cli import app
from ps_lab.geometry import Circle
from ps_lab.io.light_files import read_light_positions
from ps_lab.reconstruct import angular_errors_deg, solve
from ps_lab.reconstruct._kernels import sbl_tile
from ps_lab.reconstruct._near_kernels import sbl_tile_pp
from ps_lab.reconstruct.near import NearLights, near_light_reconstruct
from ps_lab.render.table_rig import TableRig, write_table_rig

SHAPE = (300, 400)
CHROME = (Circle(55.0, 55.0, 50.0), Circle(344.0, 244.0, 50.0))
MATTE = Circle(344.0, 55.0, 50.0)
OBJECT_SIZE = 200.0
N_LIGHTS = 24
THRESHOLD = 0.02


def _scene() -> render.Scene:
    objects = [render.SceneObject("chrome", c.center, c.radius, (0.9, 0.9, 0.9)) for c in CHROME]
    objects.append(render.SceneObject("matte", MATTE.center, MATTE.radius, (0.7, 0.7, 0.7)))
    objects.append(render.SceneObject("relief", (199.5, 149.5), 100.0, (0.75, 0.65, 0.55),
                                      specular=0.25, roughness=0.12, seed=3))
    return render.Scene(SHAPE[1], SHAPE[0], tuple(objects))


def _frames(scene, directions, intensities, leds, rng) -> np.ndarray:
    frames = []
    for j in range(len(directions)):
        lit = None if leds is None else leds.select([j])
        frames.append(render.render_scene(scene, directions[j : j + 1], intensities[j : j + 1],
                                          point_lights=lit))
    frames = np.array(frames)
    return frames + rng.normal(0.0, 2e-3, frames.shape)


def _observations(frames, intensities, mask, threshold):
    images = (frames / intensities[:, None, None, :]).mean(axis=-1)
    rows, cols = np.nonzero(mask)
    obs = images[:, rows, cols]
    return obs, (obs > threshold) if threshold is not None else None


def run_ratio(ratio: float, threshold: float | None, rng_seed: int = 0) -> dict:
    scene = _scene()
    truth = render.scene_ground_truth(scene)
    mask, gt = truth["mask"], truth["normals"][truth["mask"]]
    radius = ratio * OBJECT_SIZE
    layout = np.random.default_rng(11)
    directions = render.random_light_directions(N_LIGHTS, layout, max_zenith_deg=55.0)
    intensities = np.repeat(1.0 + 0.1 * layout.uniform(-1, 1, (N_LIGHTS, 1)), 3, axis=1)
    leds = render.PointLights(radius * directions, anisotropy=1.0, radius=15.0)
    rng = np.random.default_rng(rng_seed)
    frames = _frames(scene, directions, intensities, leds, rng)
    cal = calibrate(frames, sphere=CHROME[0], extra_spheres=[CHROME[1]], matte_sphere=MATTE,
                    anisotropy=1.0)
    tri = cal.triangulation
    placed = ~tri.too_far
    position_error = np.linalg.norm(tri.positions[placed] - leds.positions[placed], axis=1)
    obs, valid = _observations(frames, cal.light_intensities, mask, threshold)
    directional = solve(obs, cal.light_directions, valid=valid)
    lights = NearLights(tri.positions, cal.light_directions, np.full(N_LIGHTS, 1.0))
    started = time.perf_counter()
    near, rounds = near_light_reconstruct(obs, mask, lights, valid=valid, threads=2)
    near_seconds = time.perf_counter() - started
    far_frames = _frames(scene, directions, intensities, None, rng)
    far_cal = calibrate(far_frames, sphere=CHROME[0], matte_sphere=MATTE)
    far_obs, far_valid = _observations(far_frames, far_cal.light_intensities, mask, threshold)
    far = solve(far_obs, far_cal.light_directions, valid=far_valid)
    return {
        "ratio": ratio,
        "dome_px": radius,
        "position_error_pct": (100 * position_error.mean() / radius,
                               100 * position_error.max() / radius) if placed.any() else None,
        "too_far": int((~placed).sum()),
        "directional": float(angular_errors_deg(directional.normals, gt).mean()),
        "near": float(angular_errors_deg(near.normals, gt).mean()),
        "far": float(angular_errors_deg(far.normals, gt).mean()),
        "rounds": len(rounds.changes),
        "seconds_per_round": float(np.mean(rounds.seconds)),
        "near_seconds": near_seconds,
    }


def sweep(ratios: list[float], threshold: float | None) -> None:
    print(f"# near-light sweep ({platform.node()}, {os.cpu_count()} cores), threshold {threshold}")
    print("| dome / object | positions: mean / max error (% of dome) | directional SBL | "
          "near SBL (rounds) | far rig SBL | near / directional | near / far |")
    print("|---|---|---|---|---|---|---|")
    for ratio in ratios:
        r = run_ratio(ratio, threshold)
        pos = ("-" if r["position_error_pct"] is None
               else "{:.2f} / {:.2f}".format(*r["position_error_pct"]))
        if r["too_far"]:
            pos += f" ({r['too_far']} too far)"
        print(f"| {ratio:g}x | {pos} | {r['directional']:.2f} | {r['near']:.3f} ({r['rounds']}) | "
              f"{r['far']:.3f} | {r['near'] / r['directional']:.3f} | "
              f"{r['near'] / r['far']:.2f} |", flush=True)


def speed() -> None:
    rng = np.random.default_rng(0)
    print("| lights | directional ns / pixel-iteration | per-pixel lights | ratio |")
    print("|---|---|---|---|")
    params = dict(lam=1e-4, sigma_x2=1e6, max_iter=100, tol=1e-4, gamma_floor=1e-10,
                  gamma_start=1e3, outlier_threshold=0.05)
    for n in (24, 40, 96):
        m = 20000
        lights = render.random_light_directions(n, rng)
        normals = render.random_light_directions(m, rng)
        y = np.clip(normals @ lights.T, 0.0, None)
        y += (rng.random(y.shape) < 0.1) * rng.random(y.shape)
        w = (y > 0).astype(float)
        y /= np.maximum(np.median(y, axis=1, keepdims=True), 1e-3)
        per_pixel = np.ascontiguousarray(np.broadcast_to(lights, (m, n, 3)))
        sbl_tile(y[:8], w[:8], lights, **params)
        sbl_tile_pp(y[:8], w[:8], per_pixel[:8], **params)
        cost = {}
        for name, kernel, a in (("dir", sbl_tile, lights), ("pp", sbl_tile_pp, per_pixel)):
            best = np.inf
            for _ in range(3):
                started = time.process_time()
                result = kernel(y, w, a, **params)
                best = min(best, time.process_time() - started)
            cost[name] = 1e9 * best / result.iterations.sum()
        print(f"| {n} | {cost['dir']:.0f} | {cost['pp']:.0f} | {cost['pp'] / cost['dir']:.2f} |")
    r = run_ratio(3.0, THRESHOLD)
    scene = _scene()
    mask = render.scene_ground_truth(scene)["mask"]
    print(f"\nnear-light rounds at 3x: {r['rounds']} rounds, {r['seconds_per_round']:.2f} s per "
          f"round, {r['near_seconds']:.1f} s in all ({int(mask.sum())} pixels, {N_LIGHTS} lights, "
          "2 threads, wall time)")


def _cli(args: list[str]) -> None:
    result = CliRunner().invoke(app, args)
    if result.exit_code != 0:
        raise SystemExit(result.output)


def _mean(folder: Path) -> tuple[float, dict]:
    metrics = json.loads((folder / "metrics.json").read_text())
    return metrics["angular_error_deg"]["mean"], metrics.get("near", {})


def table(focal_px: float | None) -> None:
    rig = replace(TableRig(), focal_px=focal_px)
    spheres = [a for c in rig.spheres for a in ("--sphere", f"{c[0]:g},{c[1]:g},{c[2]:g}")]
    lens = [] if focal_px is None else ["--focal-length", f"{focal_px / 100:g}",
                                        "--pixel-pitch", "10"]
    with tempfile.TemporaryDirectory() as tmp:
        near, far = Path(tmp) / "near", Path(tmp) / "far"
        scene = write_table_rig(near, rig)
        write_table_rig(far, rig, far=True, reference_peak=scene["raw_peak"])
        _cli(["calibrate", str(far), *spheres, *lens])
        _cli(["reconstruct", str(far), "--out", str(Path(tmp) / "f")])
        e_far, _ = _mean(Path(tmp) / "f")
        h, w = rig.shape
        truth = np.array(scene["leds"], dtype=float)
        truth += [rig.origin_px[0] - (w - 1) / 2, (h - 1) / 2 - rig.origin_px[1],
                  -rig.spheres[0][2]]
        print(f"# table rig ({platform.node()}), focal length {focal_px or 'orthographic'}")
        print("| intensities | outline | LED positions mean / max (%) | near | directional | "
              "near / directional | far twin | near / far | outline found (px) |")
        print("|---|---|---|---|---|---|---|---|---|")
        for model in ("origin", "equal"):
            for outline in ("searched", "stated (table)"):
                extra = ["--led-intensities", model]
                extra += ["--object", "table"] if outline != "searched" else []
                for name in ("object_outline.txt",):
                    (near / name).unlink(missing_ok=True)
                _cli(["calibrate", str(near), *spheres, *lens, *extra])
                positions = read_light_positions(near / "light_positions.txt")
                error = 100 * np.linalg.norm(positions - truth, axis=1) / rig.dome_radius
                _cli(["reconstruct", str(near), "--out", str(Path(tmp) / "n")])
                _cli(["reconstruct", str(near), "--lights", "directional", "--out",
                      str(Path(tmp) / "d")])
                e_near, record = _mean(Path(tmp) / "n")
                e_dir, _ = _mean(Path(tmp) / "d")
                print(f"| {model} | {outline} | {error.mean():.2f} / {error.max():.2f} | "
                      f"{e_near:.3f} | {e_dir:.2f} | {e_near / e_dir:.3f} | {e_far:.3f} | "
                      f"{e_near / e_far:.2f} | {record['outline_height_px']:.1f} |", flush=True)


def outline() -> None:
    print("| dome / object | object top (px) | outline found (truth −40) | mean height bias (px) "
          "| near SBL | directional | rounds |")
    print("|---|---|---|---|---|---|---|")
    for dome in (360.0, 540.0, 900.0):
        for top in (12.0, 30.0, 50.0):
            rig = replace(TableRig(), dome_radius=dome, object_top=top)
            spheres = [a for c in rig.spheres for a in ("--sphere", f"{c[0]:g},{c[1]:g},{c[2]:g}")]
            with tempfile.TemporaryDirectory() as tmp:
                near = Path(tmp) / "near"
                scene = write_table_rig(near, rig)
                _cli(["calibrate", str(near), *spheres])
                _cli(["reconstruct", str(near), "--out", str(Path(tmp) / "n")])
                _cli(["reconstruct", str(near), "--lights", "directional", "--out",
                      str(Path(tmp) / "d")])
                e_near, record = _mean(Path(tmp) / "n")
                e_dir, _ = _mean(Path(tmp) / "d")
                heights = np.load(Path(tmp) / "n" / "depth.npy")
                mask = scene["mask"]
                bias = np.mean(heights[mask] - (scene["height"][mask] - rig.spheres[0][2]))
                print(f"| {dome / 180:g}x | {scene['height'][mask].max():.0f} | "
                      f"{record['outline_height_px']:.1f} | {bias:+.2f} | {e_near:.3f} | "
                      f"{e_dir:.2f} | {record['rounds']} |", flush=True)


def _spheres_args(rig) -> list[str]:
    return [a for c in rig.spheres for a in ("--sphere", f"{c[0]:g},{c[1]:g},{c[2]:g}")]


def ablation(sphere_radius: float) -> None:
    import ps_lab.reconstruct.near as near_module

    rig = replace(TableRig(), dome_radius=660.0, object_radius=115.0, full_well=3e5,
                  read_noise=1.5e-5, spheres=((60.0, 296.0, sphere_radius),
                                              (420.0, 62.0, sphere_radius)))
    spheres = _spheres_args(rig)
    with tempfile.TemporaryDirectory() as tmp:
        near, far = Path(tmp) / "near", Path(tmp) / "far"
        scene = write_table_rig(near, rig)
        write_table_rig(far, rig, far=True, reference_peak=scene["raw_peak"])
        _cli(["calibrate", str(far), *spheres])
        _cli(["reconstruct", str(far), "--out", str(Path(tmp) / "f")])
        e_far, _ = _mean(Path(tmp) / "f")
        h, w = rig.shape
        truth = np.array(scene["leds"], float) + [rig.origin_px[0] - (w - 1) / 2,
                                                  (h - 1) / 2 - rig.origin_px[1], -sphere_radius]
        _cli(["calibrate", str(near), *spheres])
        found = read_light_positions(near / "light_positions.txt")
        error = 100 * np.linalg.norm(found - truth, axis=1) / rig.dome_radius
        print(f"# ablation, spheres r={sphere_radius:g}: LED positions mean {error.mean():.2f} % "
              f"max {error.max():.2f} %; far twin {e_far:.3f} deg")
        print("| truth given for | near SBL | near / far | outline (truth "
              f"{-sphere_radius:g}) |\n|---|---|---|---|")
        saved = {n: (near / n).read_text() for n in ("light_positions.txt",
                                                      "light_intensities.txt")}
        heights = np.where(scene["mask"], scene["height"] - sphere_radius, -sphere_radius)
        anchored = near_module._anchored_heights
        equal = 1.0 / np.sum(truth * truth, axis=1)
        cases = {"nothing": (), "positions": ("pos",), "intensities": ("int",),
                 "outline height": ("out",), "depth": ("depth",),
                 "positions + intensities": ("pos", "int"),
                 "positions + intensities + depth": ("pos", "int", "depth")}
        for label, given in cases.items():
            for name, text in saved.items():
                (near / name).write_text(text)
            (near / "object_outline.txt").unlink(missing_ok=True)
            if "pos" in given:
                np.savetxt(near / "light_positions.txt", truth, fmt="%.6f")
            if "int" in given:
                np.savetxt(near / "light_intensities.txt",
                           np.repeat((equal / equal.mean())[:, None], 3, axis=1), fmt="%.9f")
            if "out" in given or "depth" in given:
                np.savetxt(near / "object_outline.txt", [-sphere_radius])
            near_module._anchored_heights = ((lambda *a, **k: heights) if "depth" in given
                                             else anchored)
            try:
                _cli(["reconstruct", str(near), "--out", str(Path(tmp) / "n")])
            finally:
                near_module._anchored_heights = anchored
            e_near, record = _mean(Path(tmp) / "n")
            print(f"| {label} | {e_near:.3f} | {e_near / e_far:.2f} | "
                  f"{record['outline_height_px']:.1f} |", flush=True)


def leds(mus: list[float]) -> None:
    import shutil

    import cv2

    from ps_lab.render.table_rig import write_board_frames

    base = replace(TableRig(), dome_radius=660.0, object_radius=115.0)
    spheres = _spheres_args(base)
    print("| LEDs | no board (equal, isotropic) | isotropic (fitted outputs) | beam | flat-field "
          "| flat board 15 px up: none / beam / flat-field (mean, max deg) |")
    print("|---|---|---|---|---|---|")
    for mu in mus:
        rig = replace(base, beam_mu=mu, beam_tilt_deg=8.0 if mu else 0.0,
                      output_spread=0.1 if mu else 0.0)
        with tempfile.TemporaryDirectory() as tmp:
            near, board, test = Path(tmp) / "near", Path(tmp) / "board", Path(tmp) / "test"
            write_table_rig(near, rig)
            write_board_frames(board, rig)
            row = []
            _cli(["calibrate", str(near), *spheres, "--object", "table"])
            _cli(["reconstruct", str(near), "--out", str(Path(tmp) / "plain")])
            row.append(f"{_mean(Path(tmp) / 'plain')[0]:.3f}")
            plain = {n: (near / n).read_text() for n in ("light_intensities.txt",)}
            _cli(["calibrate", str(near), *spheres, "--object", "table", "--flat-field",
                  str(board)])
            for model in ("isotropic", "beam", "flat-field"):
                _cli(["reconstruct", str(near), "--led-model", model, "--out",
                      str(Path(tmp) / model)])
                row.append(f"{_mean(Path(tmp) / model)[0]:.3f}")
            write_board_frames(test, rig, height=15.0, noise_seed=99)
            h, w = rig.shape
            cv2.imwrite(str(test / "mask.png"), np.full((h, w), 255, np.uint8))
            for name in ("light_positions.txt", "light_directions.txt", "light_axes.txt",
                         "light_anisotropy.txt", "flat_field.npz", "light_intensities.txt"):
                shutil.copy(near / name, test / name)
            np.savetxt(test / "object_outline.txt", [15.0 - rig.spheres[0][2]])
            board_row = []
            for model in ("none", "beam", "flat-field"):
                if model == "none":  # the calibration without a board: equal isotropic LEDs
                    (test / "light_intensities.txt").write_text(plain["light_intensities.txt"])
                else:
                    shutil.copy(near / "light_intensities.txt", test / "light_intensities.txt")
                _cli(["reconstruct", str(test), "--led-model",
                      "isotropic" if model == "none" else model, "--out", str(Path(tmp) / "b")])
                normals = np.load(Path(tmp) / "b" / "normals.npy")
                err = np.degrees(np.arccos(np.clip(normals[..., 2], -1.0, 1.0)))
                board_row.append(f"{err.mean():.2f}, {err.max():.2f}")
            print(f"| mu = {mu:g}{', tilt 8, +-10 %' if mu else ''} | {' | '.join(row)} | "
                  f"{' / '.join(board_row)} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("sweep")
    p.add_argument("--ratios", type=float, nargs="+", default=[2, 3, 5, 10, 20])
    p.add_argument("--no-threshold", action="store_true")
    sub.add_parser("speed")
    p = sub.add_parser("table")
    p.add_argument("--focal-px", type=float, default=None)
    sub.add_parser("outline")
    p = sub.add_parser("ablation")
    p.add_argument("--sphere-radius", type=float, default=25.0)
    p = sub.add_parser("leds")
    p.add_argument("--mu", type=float, nargs="+", default=[0, 1, 2, 3])
    args = parser.parse_args()
    if args.command == "sweep":
        sweep(args.ratios, None if args.no_threshold else THRESHOLD)
    elif args.command == "table":
        table(args.focal_px)
    elif args.command == "outline":
        outline()
    elif args.command == "ablation":
        ablation(args.sphere_radius)
    elif args.command == "leds":
        leds(args.mu)
    else:
        speed()


if __name__ == "__main__":
    main()
