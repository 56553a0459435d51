"""The default (``auto``) against each of its parts (LS, SBL, PL-SBL), per case.

Cases: every SynthRTI collection under a folder (default ``../shared/data/synthrti-object1``:
``Dome/`` images, ``dirs.lp`` and ``normals.png``, loaded as ``ps-lab reconstruct`` loads them),
the DiLiGenT-style objects under ``../shared/data/diligent-8bit`` and simulated stand-ins.
Each case is solved with the same usable observations (saturation and the default shadow rule:
:func:`ps_lab.bench.real.load_object`'s) by ``auto``, ``ls``, ``sbl`` and ``plsbl``; the table
gives the mean angular error (deg) of each, the better of SBL and LS, the per-object choice in
hindsight (the best part), the albedo speckle (share of pixels more than 30 % off their 3 x 3
median, where the image grid is known) and the default's solve time over SBL's.

Usage::

    python benchmarks/default_parts.py [--synthrti FOLDER] [--diligent FOLDER] [--every N]
        [--only SUBSTRING] [--no-synthrti] [--no-diligent] [--no-sim] [--threads T]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from ps_lab.bench.real import find_objects, load_object
from ps_lab.io.dataset import load_dataset
from ps_lab.io.images import read_image
from ps_lab.reconstruct import angular_errors_deg, light_noise_factors, solve
from ps_lab.reconstruct._shadows import black_threshold
from ps_lab.reconstruct._noise import NOISE_SAMPLE_PIXELS

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
METHODS = ("sbl", "ls", "plsbl", "auto")  # SBL first: its kernels are warm when auto is timed
SPECKLE_OFF = 0.3


def _black_valid(obs, unsaturated, factors, lights):
    sample = np.unique(np.linspace(0, obs.shape[1] - 1, min(obs.shape[1], NOISE_SAMPLE_PIXELS))
                       .round().astype(np.int64))
    black = black_threshold(obs[:, sample], unsaturated[:, sample], factors,
                            light_directions=lights)
    return unsaturated if black is None else unsaturated & (obs > black[:, None])


def synthrti_case(folder: Path, every: int):
    """One SynthRTI collection: observations (n, P), valid, lights, truth (P, 3), grid shape."""
    data = load_dataset(folder / "Dome")
    raw = np.asarray(read_image(folder / "Dome" / "normals.png", "linear").data, np.float64)
    truth = raw[..., :3] * 2.0 - 1.0
    truth /= np.linalg.norm(truth, axis=-1, keepdims=True)
    images = data.images[:, ::every, ::every]
    shape = images.shape[1:]
    obs = images.reshape(images.shape[0], -1)
    unsat = data.valid[:, ::every, ::every].reshape(obs.shape)
    factors = light_noise_factors(data.light_intensities)
    valid = _black_valid(obs, unsat, factors, data.light_directions)
    return obs, valid, data.light_directions, truth[::every, ::every].reshape(-1, 3), factors, \
        shape


def speckle(albedo: np.ndarray, shape) -> float:
    """Share (%) of solved pixels more than SPECKLE_OFF off their 3 x 3 median."""
    a = albedo.reshape(shape)
    pad = np.pad(a, 1, mode="edge")
    stack = np.stack([pad[i:i + shape[0], j:j + shape[1]] for i in range(3) for j in range(3)])
    med = np.median(stack, axis=0)
    ok = med > 0
    return 100.0 * float(np.mean(np.abs(a[ok] / med[ok] - 1.0) > SPECKLE_OFF))


def run_case(name, obs, valid, lights, truth, factors, shape=None, threads=None):
    row = {"case": name}
    for method in METHODS:
        kw = {"light_noise": factors} if method in ("auto", "sbl", "plsbl") else {}
        started = time.perf_counter()
        sol = solve(obs, lights, method=method, valid=valid, threads=threads, **kw)
        row[f"{method}_s"] = time.perf_counter() - started
        row[method] = float(angular_errors_deg(sol.normals, truth).mean())
        if shape is not None:
            row[f"{method}_speckle"] = speckle(sol.albedo, shape)
        if method == "auto":
            row["share"] = sol.params.get("pixels_per_model")
            row["rings"] = sol.params.get("lights_in_rings")
    row["valid_share"] = float(valid.mean())
    return row


def simulated_cases(every: int, dome: np.ndarray | None = None):
    """Stand-ins unlike both: glossy spheres and reliefs, 12 and 48 lights (ps-lab render), and
    with ``dome`` (n, 3) (SynthRTI's dome lights) a relief with a broad lobe under it."""
    from ps_lab.render import (random_light_directions, relief_surface, render,
                               sphere_surface)
    cases = []
    size = max(32, 128 // every)
    specs = [("sim sphere glossy 48", 48, "sphere", 0.6, 0.15, 1),
             ("sim relief glossy 48", 48, "relief", 0.4, 0.3, 2),
             ("sim relief matte 12", 12, "relief", 0.0, 0.5, 3),
             ("sim sphere glossy 12", 12, "sphere", 0.5, 0.2, 4)]
    if dome is not None:
        specs.append(("sim relief broad lobe, dome 49", 0, "relief", 0.5, 0.6, 1))
    for name, n_lights, surface_kind, spec, rough, seed in specs:
        rng = np.random.default_rng(seed)
        lights = dome if n_lights == 0 else random_light_directions(n_lights, rng,
                                                                    max_zenith_deg=70.0)
        n_lights = lights.shape[0]
        surf = sphere_surface((size, size)) if surface_kind == "sphere" else \
            relief_surface((size, size), seed=seed)
        images = render(surf, lights, rng=rng, specular=spec, roughness=rough,
                        noise_sigma=0.005, noise_fraction=1.0)
        images = np.clip(images, 0.0, 1.0)
        obs = images[:, surf.mask]
        unsat = obs < 1.0
        factors = np.ones(n_lights)
        valid = _black_valid(obs, unsat, factors, lights)
        cases.append((name, obs, valid, lights, surf.normals[surf.mask], factors, None))
    return cases


def _share(row) -> str:
    counts = np.array(list((row.get("share") or {}).values()), dtype=float)
    parts = "/".join(f"{100 * c / max(counts.sum(), 1):.0f}" for c in counts)
    return parts


def speckle_case(folder: Path, threads=None) -> dict:
    """Albedo speckle (%) of the default and SBL on a whole image (mask pixels), e.g. a real RTI
    panel without ground truth or a DiLiGenT object."""
    data = load_dataset(folder)
    mask = data.mask
    obs = data.images[:, mask]
    factors = light_noise_factors(data.light_intensities)
    valid = _black_valid(obs, data.valid[:, mask], factors, data.light_directions)
    row = {"case": folder.name}
    for method in ("sbl", "auto"):
        started = time.perf_counter()
        sol = solve(obs, data.light_directions, method=method, valid=valid, threads=threads,
                    light_noise=factors)
        row[f"{method}_s"] = time.perf_counter() - started
        image = np.zeros(mask.shape)
        image[mask] = sol.albedo
        a = np.pad(image, 1, mode="edge")
        stack = np.stack([a[i:i + mask.shape[0], j:j + mask.shape[1]]
                          for i in range(3) for j in range(3)])
        med = np.median(stack, axis=0)
        ok = mask & (med > 0)
        row[method] = 100.0 * float(np.mean(np.abs(image[ok] / med[ok] - 1.0) > SPECKLE_OFF))
        if method == "auto":
            row["share"] = sol.params.get("pixels_per_model")
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--synthrti", type=Path, default=DATA / "synthrti-object1")
    ap.add_argument("--diligent", type=Path, default=DATA / "diligent-8bit")
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--only", default="")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--no-synthrti", action="store_true")
    ap.add_argument("--no-diligent", action="store_true")
    ap.add_argument("--no-sim", action="store_true")
    ap.add_argument("--speckle", type=Path, nargs="*", default=None,
                    help="only the albedo speckle of these folders (default and SBL)")
    args = ap.parse_args(argv)
    rows = []
    if args.speckle is not None:
        print("| case | speckle % default | speckle % SBL | time default / SBL | LS/SBL/PL % |")
        print("|---|---|---|---|---|")
        for folder in args.speckle or [DATA / "realrti-3" / "item3", args.diligent / "cat"]:
            row = speckle_case(folder, args.threads)
            print(f"| {row['case']} | {row['auto']:.2f} | {row['sbl']:.2f} | "
                  f"{row['auto_s'] / row['sbl_s']:.2f} | {_share(row)} |", flush=True)
        return 0

    def report(row):
        rows.append(row)
        better = min(row["sbl"], row["ls"])
        best = min(row[m] for m in METHODS if m != "auto")
        speck = " ".join(f"{row.get(m + '_speckle', float('nan')):.2f}"
                         for m in ("auto", "sbl"))
        print(f"| {row['case']} | {row['auto']:.2f} | {row['ls']:.2f} | {row['sbl']:.2f} | "
              f"{row['plsbl']:.2f} | {better:.2f} | {best:.2f} | {row['auto'] - better:+.2f} | "
              f"{speck} | {row['auto_s'] / row['sbl_s']:.2f} | {row['valid_share']:.2f} | "
              f"{_share(row)} |",
              flush=True)

    print("| case | default | LS | SBL | PL-SBL | better of SBL/LS | best part (hindsight) | "
          "default - better | speckle % default SBL | time / SBL | valid share | "
          "default's LS/SBL/PL pixels % |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    if not args.no_synthrti:
        for folder in sorted(args.synthrti.glob("*/*/material*")):
            name = "/".join(folder.parts[-3:])
            if args.only not in name:
                continue
            obs, valid, lights, truth, factors, shape = synthrti_case(folder, args.every)
            report(run_case(name, obs, valid, lights, truth, factors, shape, args.threads))
    if not args.no_diligent:
        for path in find_objects(args.diligent):
            if args.only not in path.name:
                continue
            obj = load_object(path, args.every)
            report(run_case(obj.name, obj.observations, obj.valid, obj.light_directions,
                            obj.normal_gt, obj.light_noise, None, args.threads))
    if not args.no_sim:
        dome_folder = args.synthrti / "Single" / "Object1" / "material1" / "Dome"
        dome = load_dataset(dome_folder).light_directions if dome_folder.is_dir() else None
        for case in simulated_cases(args.every, dome):
            if args.only in case[0]:
                report(run_case(*case, threads=args.threads))
    if rows:
        for group in ("Single", "Multi", ""):
            pick = [r for r in rows if r["case"].startswith(group)] if group else rows
            if not pick:
                continue
            mean = {m: np.mean([r[m] for r in pick]) for m in METHODS}
            better = np.mean([min(r["sbl"], r["ls"]) for r in pick])
            worse = sum(r["auto"] > min(r["sbl"], r["ls"]) + 0.5 for r in pick)
            print(f"mean {group or 'all'} ({len(pick)}): default {mean['auto']:.2f} ls "
                  f"{mean['ls']:.2f} sbl {mean['sbl']:.2f} plsbl {mean['plsbl']:.2f} "
                  f"better-of {better:.2f}; > 0.5 worse: {worse}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
