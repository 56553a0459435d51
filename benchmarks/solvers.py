"""Solver benchmarks: speed against the per-pixel oracle, accuracy, the default lambda, refinement.

Usage (from the repository root):

    .venv/bin/python benchmarks/solvers.py speed [--quick] [--threads T]
    .venv/bin/python benchmarks/solvers.py accuracy      # paper-style synthetic scenes
    .venv/bin/python benchmarks/solvers.py lambda        # real-like 16-bit captures: auto vs fixed lambda
    .venv/bin/python benchmarks/solvers.py refine        # 5 degree light errors, refinement iterations
    .venv/bin/python benchmarks/solvers.py bunny   # noise-free speculars: auto vs the authors' SBL
    .venv/bin/python benchmarks/solvers.py cost    # the default's solve time / SBL's

`speed` prints, for 40 and 96 lights and 1e4, 1e5, 1e6 pixels, pixels per second per method, mean
iterations, and the speed-up of SBL and L1 over the straightforward per-pixel numpy oracle (the
default ``auto`` and the PL models: over the SBL oracle, the authors' algorithm)
(tests/helpers/solver_oracles.py, same update and stopping rules) timed on the first 200 pixels,
each oracle run right after a solve (both see the same background load): best of --repeat runs of
each (at 10⁶ pixels one solve, still --repeat oracle runs). Run it with OPENBLAS_NUM_THREADS=1:
numpy's threaded BLAS makes the oracle's small products slower.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from helpers.solver_oracles import oracle_params, sbl_pixel, solve_oracle  # noqa: E402
from helpers.solver_scenes import corrupt  # noqa: E402

from ps_lab import render as R  # noqa: E402
from ps_lab.reconstruct import (  # noqa: E402
    METHODS,
    angular_errors_deg,
    error_summary,
    refine_lights,
    solve,
)
from ps_lab.reconstruct._shadows import black_threshold  # noqa: E402


def machine() -> str:
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"load average {load:.1f} at start, numpy {np.__version__}")


def synthetic(n_lights: int, n_pixels: int, seed: int = 0):
    """Lambertian pixels with attached shadows, 10% sparse corruptions and 0.5% noise (float32)."""
    rng = np.random.default_rng(seed)
    lights = R.random_light_directions(n_lights, rng)
    obs = np.empty((n_lights, n_pixels), np.float32)
    chunk = 100_000
    for a in range(0, n_pixels, chunk):
        b = min(a + chunk, n_pixels)
        nrm = rng.normal(size=(b - a, 3))
        nrm[:, 2] = np.abs(nrm[:, 2]) + 0.3
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        y = np.maximum(lights @ nrm.T, 0.0) * rng.uniform(0.3, 1.0, b - a)
        y, _ = corrupt(y, rng, 0.0)
        y += rng.normal(0.0, 0.005, y.shape)
        obs[:, a:b] = y
    return obs, lights


# Methods timed against the SBL oracle (the authors' per-pixel SBL, issue 23's yardstick).
YARDSTICK_SBL = ("auto", "plsbl", "plls")


def _timed(run, *args, **kwargs):
    t = time.perf_counter()
    result = run(*args, **kwargs)
    return time.perf_counter() - t, result


def cmd_speed(args):
    print(f"# solver speed — {machine()}; threads={args.threads or os.cpu_count()}; "
          f"best of {args.repeat} runs of the solver (10⁶ pixels: one) and of the oracle, "
          "alternated")
    print("# NOTE: the machine may be shared with other jobs; numbers are wall-clock.")
    sizes = [10_000, 100_000] if args.quick else [10_000, 100_000, 1_000_000]
    lights_list = [40] if args.quick else [40, 96]
    print(f"{'lights':>6} {'pixels':>9} {'method':>6} {'px/s':>10} {'iter':>6} "
          f"{'oracle px/s':>11} {'speed-up':>9}")
    for n in lights_list:
        obs_all, lights = synthetic(n, max(sizes))
        for p in sizes:
            obs = obs_all[:, :p]
            for method in args.methods:
                if method == "rpca" and p > 100_000:
                    continue
                solve(obs[:, :2000], lights, method=method)  # loads the kernels (as the CLI does)
                k = args.oracle_pixels
                sub = obs[:, :k].astype(np.float64)
                if method in YARDSTICK_SBL:
                    sbl_params = oracle_params(solve(obs, lights, method="sbl", max_iter=100))
                best = best_oracle = float("inf")
                # the solve and the per-pixel oracle (first k pixels, the solve's parameters)
                # alternate, so both see the same background load; best of each
                for r in range(args.repeat):
                    if r == 0 or p <= 100_000:  # one solve of 10⁶ pixels (the oracle: all)
                        dt, sol = _timed(solve, obs, lights, method=method,
                                         threads=args.threads)
                        best = min(best, dt)
                    if method in ("l1", "sbl"):
                        dt, _ = _timed(solve_oracle, sub, lights, method,
                                       **oracle_params(sol))
                        best_oracle = min(best_oracle, dt)
                    elif method in YARDSTICK_SBL:
                        # the PL models and the default against the authors' SBL (its oracle)
                        dt, _ = _timed(solve_oracle, sub, lights, "sbl", **sbl_params)
                        best_oracle = min(best_oracle, dt)
                oracle_txt = speed_txt = ""
                if method in ("l1", "sbl", *YARDSTICK_SBL):
                    oracle = k / best_oracle
                    oracle_txt = f"{oracle:11.0f}"
                    speed_txt = f"{p / best / oracle:8.0f}x"
                print(f"{n:6d} {p:9d} {method:>6} {p / best:10.0f} {sol.iterations.mean():6.1f} "
                      f"{oracle_txt:>11} {speed_txt:>9}", flush=True)


def clipped_capture(kind, n, seed, *, shape=(96, 96), specular=0.3, full_well=20000.0,
                    read_noise=3.0, peak=0.8, bits=16):
    """A capture without a dark frame: render, expose so the 99.5th percentile sits at `peak` of
    full scale, shot noise (Poisson in electrons) + Gaussian read noise, quantise to `bits`,
    clip at 0 and full scale. Observations (n, P), lights, unsaturated (n, P), truth, mask."""
    rng = np.random.default_rng(seed)
    lights = R.random_light_directions(n, rng)
    surf = R.sphere_surface(shape) if kind == "sphere" else R.relief_surface(shape, seed=seed)
    img = R.render(surf, lights, specular=specular, roughness=0.3, rng=rng)
    img = img / np.percentile(img[:, surf.mask], 99.5) * peak
    electrons = rng.poisson(np.clip(img, 0, None) * full_well).astype(float)
    electrons += rng.normal(0.0, read_noise, electrons.shape)
    top = 2**bits - 1
    dn = np.clip(np.round(electrons / full_well * top), 0, top)
    obs = (dn / top)[:, surf.mask]
    return obs, lights, dn[:, surf.mask] < top, surf.normals[surf.mask], surf.mask


def real_like(kind, n, seed, **kwargs):
    """A 16-bit :func:`clipped_capture`: observations, lights, unsaturated, truth."""
    return clipped_capture(kind, n, seed, **kwargs)[:4]


def _lambda_row(names, obs, lights, valid, normals):
    """Mean/median error cells of each method in ``names`` and the automatic lambda."""
    cells, lam = [], None
    for name in names:
        kw = {"method": name.split()[0]}
        if name.startswith("sbl") and name != "sbl auto":
            kw["lam"] = float(name.split()[1])
        sol = solve(obs, lights, valid=valid, **kw)
        if name == "sbl auto":
            lam = sol.params["noise_sigma"] ** 2
        e = error_summary(angular_errors_deg(sol.normals, normals))
        cells.append(f"{e['mean']:5.2f}/{e['median']:5.2f}")
    return cells, lam


def cmd_lambda(args):
    print("# SBL lambda on real-like 16-bit captures (40 lights, speculars 0.3, shot+read noise, "
          "saturation dropped) — mean/median angular error in degrees")
    names = ["ls", "l1", "sbl auto", "sbl 1e-2", "sbl 1e-4", "sbl 1e-6"]
    print(f"{'scene':>12} {'auto lambda':>11} " + " ".join(f"{x:>12}" for x in names))
    for kind in ("sphere", "relief"):
        for seed in (1, 2, 3):
            cells, lam = _lambda_row(names, *real_like(kind, 40, seed))
            print(f"{kind + ' ' + str(seed):>12} {lam:11.2e} " + " ".join(f"{c:>12}" for c in cells),
                  flush=True)
    print("# exposure sweep (seed 1): peak = 99.5th percentile as a share of full scale, full well")
    for peak, full_well in ((0.8, 20000.0), (0.1, 20000.0), (0.05, 5000.0)):
        for kind in ("sphere", "relief"):
            cells, lam = _lambda_row(
                names, *real_like(kind, 40, 1, peak=peak, full_well=full_well)
            )
            label = f"{kind} {peak:g}/{full_well:g}"
            print(f"{label:>20} {lam:11.2e} " + " ".join(f"{c:>12}" for c in cells), flush=True)


def cmd_accuracy(args):
    print("# paper-style synthetic scenes (Table 3 setting): 40 lights (zenith <= 60 deg), noise-free "
          "render, Cook-Torrance speculars (strength 0.5, roughness 0.15: ~10-20% of observations), "
          "attached+cast shadows KEPT (no shadow mask), 128x128; mean/median error (deg), solve s")
    cols = list(METHODS) + ["sbl 1e-6"]
    print(f"{'scene':>10} {'spec%':>5} " + " ".join(f"{m:>20}" for m in cols))
    for kind in ("sphere", "relief"):
        for seed in (1, 2):
            rng = np.random.default_rng(seed)
            lights = R.random_light_directions(40, rng)
            surf = R.sphere_surface((128, 128)) if kind == "sphere" else R.relief_surface((128, 128), seed=seed)
            img = R.render(surf, lights, specular=0.5, roughness=0.15, rng=rng)[:, surf.mask]
            diffuse = R.render(surf, lights, rng=rng)[:, surf.mask]
            share = np.mean(np.abs(img - diffuse) > 0.01 * np.median(diffuse[diffuse > 0]))
            cells = []
            for m in cols:
                kw = {"method": "sbl", "lam": 1e-6} if m == "sbl 1e-6" else {"method": m}
                t = time.perf_counter()
                sol = solve(img, lights, **kw)
                dt = time.perf_counter() - t
                e = error_summary(angular_errors_deg(sol.normals, surf.normals[surf.mask]))
                cells.append(f"{e['mean']:5.2f}/{e['median']:5.2f} {dt:5.2f}s")
            print(f"{kind + ' ' + str(seed):>10} {100 * share:5.1f} " + " ".join(f"{c:>20}" for c in cells),
                  flush=True)


def cmd_refine(args):
    print("# light refinement: 40 lights each turned 5 deg in a random direction, specular 0.2, "
          "shadows dropped; mean normal error (deg) after k iterations; last column: mean light error")
    for method in ("sbl", "l1", "ls"):
        for kind in ("sphere", "relief"):
            for seed in (1, 2):
                rng = np.random.default_rng(seed)
                lights = R.random_light_directions(40, rng)
                surf = R.sphere_surface((96, 96)) if kind == "sphere" else R.relief_surface((96, 96), seed=seed)
                obs = R.render(surf, lights, specular=0.2, rng=rng)[:, surf.mask]
                res = refine_lights(obs, R.perturb_light_directions(lights, 5.0, rng), method=method, iterations=args.iterations,
                                    valid=obs > 0, normal_gt=surf.normals[surf.mask],
                                    light_directions_gt=lights)
                errs = [h["normal_error_deg"] for h in res.history]
                print(f"{method:>4} {kind + ' ' + str(seed):>9} " + " ".join(f"{e:5.2f}" for e in errs)
                      + f"   ratio(3)={errs[min(3, len(errs) - 1)] / errs[0]:.2f}"
                      + f"   light {res.history[0]['light_error_deg']:.2f}->{res.history[-1]['light_error_deg']:.2f}",
                      flush=True)


def cmd_bunny(args):
    """Issue 23's bunny target on stand-ins: the default against the authors' SBL, shadows dropped.

    The authors' SBL with observations <= 0 dropped reaches 0.012 deg on their synthetic bunny;
    their bunny is not here, so this measures both on noise-free renders whose specular lobe
    ranges from sharp (roughness 0.05) to broad (0.15, where speculars are no longer sparse):
    ps-lab with the CLI's shadow rule (black_threshold with the lights), the authors' SBL as
    the oracle written from the paper (lambda 1e-6, sigma_x^2 1e6, gamma_0 = 1, run to a change
    of z below 1e-8 or 1000 iterations) on the observations > 0 of the same sample of pixels.
    """
    print("# noise-free renders, 40 lights (zenith <= 60 deg), 128x128, Cook-Torrance speculars; "
          f"mean error (deg) over {args.pixels} pixels")
    cols = ("sbl", "plsbl", "auto")
    print(f"{'scene':>9} {'rough':>5} {'spec':>4} {'authors SBL':>11} "
          + " ".join(f"{c:>8}" for c in cols) + "  auto/authors")
    for kind in ("sphere", "relief"):
        for roughness in (0.05, 0.1, 0.15):
            for specular in (0.2, 0.5):
                rng = np.random.default_rng(1)
                lights = R.random_light_directions(40, rng)
                surf = (R.sphere_surface((128, 128)) if kind == "sphere"
                        else R.relief_surface((128, 128), seed=1))
                img = R.render(surf, lights, specular=specular, roughness=roughness,
                               rng=rng)[:, surf.mask]
                truth = surf.normals[surf.mask]
                sample = np.random.default_rng(5).choice(img.shape[1], args.pixels, replace=False)
                black = black_threshold(img, np.ones(img.shape, bool), light_directions=lights)
                valid = img > (0.0 if black is None else black[:, None])
                errors = {}
                for method in cols:
                    sol = solve(img, lights, valid=valid, method=method)
                    errors[method] = angular_errors_deg(sol.normals, truth)[sample].mean()
                authors = []
                for p in sample:
                    lit = img[:, p] > 0
                    x, _, _ = sbl_pixel(img[lit, p], lights[lit], lam=1e-6, max_iter=1000,
                                        tol=1e-8, gamma_start=1.0)
                    authors.append(angular_errors_deg((x / np.linalg.norm(x))[None],
                                                      truth[p][None])[0])
                ref = float(np.mean(authors))
                print(f"{kind:>9} {roughness:5.2f} {specular:4.1f} {ref:11.4f} "
                      + " ".join(f"{errors[c]:8.4f}" for c in cols)
                      + f"  {errors['auto'] / ref:11.2f}", flush=True)


def bunny_like(shape=(200, 200), seed=1, roughness=0.1, specular=0.5, noise_fraction=0.15):
    """The authors' synthetic-bunny situation: a float render, 40 lights, exact-zero attached and
    cast shadows, Cook-Torrance speculars, sparse additive Gaussian noise on ``noise_fraction`` of
    the observations (sigma 0.15 of the median lit value) that makes ~1 % of them negative.
    Observations (n, P), lights, all-True validity, truth, mask."""
    rng = np.random.default_rng(seed)
    lights = R.random_light_directions(40, rng, max_zenith_deg=70.0)
    surf = R.relief_surface(shape, seed=seed)
    clean = R.render(surf, lights, specular=specular, roughness=roughness, rng=rng)[:, surf.mask]
    hit = rng.random(clean.shape) < noise_fraction
    noise = rng.normal(0.0, 0.15 * np.median(clean[clean > 0]), clean.shape)
    obs = np.where(hit, clean + noise, clean)
    return obs, lights, np.ones(obs.shape, bool), surf.normals[surf.mask], surf.mask


_COST_CHILD = """
import sys, time, json
sys.path.insert(0, {bench!r})
import numpy as np
from solvers import bunny_like
from ps_lab.reconstruct import solve
from ps_lab.reconstruct._shadows import black_threshold
from ps_lab.reconstruct._warm_up import warm_up
obs, lights, valid, truth, mask = bunny_like()
black = black_threshold(obs, valid, light_directions=lights)
valid = valid & (obs > black[:, None])
warm_up({method!r})
t = time.perf_counter()
sol = solve(obs, lights, valid=valid, method={method!r}, threads={threads})
print(json.dumps({{"seconds": time.perf_counter() - t, "pixels": obs.shape[1]}}))
"""


def cmd_cost(args):
    """The default's solve against SBL's on the bunny-like capture, each in a fresh process.

    Each run is a new interpreter (numba's cached kernels loaded by ``warm_up`` first, as
    ``ps-lab reconstruct`` does while reading the images); the solve (noise estimates included)
    is timed. Runs alternate between the methods so that both see the same background load.
    """
    import json
    import subprocess

    bench = str(Path(__file__).resolve().parent)
    times: dict[str, list[float]] = {m: [] for m in args.methods}
    pixels = 0
    for _ in range(args.repeat):
        for method in args.methods:
            code = _COST_CHILD.format(bench=bench, method=method, threads=args.threads)
            out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                 check=True)
            row = json.loads(out.stdout.strip().splitlines()[-1])
            times[method].append(row["seconds"])
            pixels = row["pixels"]
    print(f"# {machine()}; bunny-like float capture, {pixels} pixels, 40 lights, "
          f"threads={args.threads}; solve seconds in fresh processes, {args.repeat} runs each")
    base = np.median(times["sbl"]) if "sbl" in times else None
    print("| method | median s | runs (s) | / SBL |")
    print("|---|---|---|---|")
    for method, t in times.items():
        ratio = f"{np.median(t) / base:.2f}" if base else ""
        print(f"| {method} | {np.median(t):.3f} | {' '.join(f'{x:.3f}' for x in t)} | {ratio} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd")
    sp = sub.add_parser("speed")
    sp.add_argument("--quick", action="store_true", help="40 lights, 1e4 and 1e5 pixels only")
    sp.add_argument("--threads", type=int, default=None)
    sp.add_argument("--oracle-pixels", type=int, default=200)
    sp.add_argument("--repeat", type=int, default=3, help="best of this many runs (default 3)")
    sp.add_argument("--methods", nargs="+", default=list(METHODS))
    sub.add_parser("accuracy")
    sub.add_parser("lambda")
    rp = sub.add_parser("refine")
    rp.add_argument("--iterations", type=int, default=4)
    bp = sub.add_parser("bunny")
    bp.add_argument("--pixels", type=int, default=1500, help="sampled pixels per scene")
    cp = sub.add_parser("cost")
    cp.add_argument("--repeat", type=int, default=5)
    cp.add_argument("--threads", type=int, default=2)
    cp.add_argument("--methods", nargs="+", default=["sbl", "auto", "plsbl"])
    args = ap.parse_args(argv)
    {"cost": cmd_cost, "speed": cmd_speed, "accuracy": cmd_accuracy, "lambda": cmd_lambda, "refine": cmd_refine,
     "bunny": cmd_bunny, None: cmd_speed}[args.cmd](args if args.cmd else sp.parse_args([]))


if __name__ == "__main__":
    main()
