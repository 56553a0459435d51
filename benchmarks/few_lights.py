"""Few lights: wild normals of the default against least squares on 12-light captures.

Usage (from the repository root)::

    .venv/bin/python benchmarks/few_lights.py [FOLDER] [--methods ls sbl auto] [--subsets 2]
    .venv/bin/python benchmarks/few_lights.py --stand-ins-only

Issue 23's measure: the share of interior pixels (the mask eroded by 3x3) whose normal is more
than 20 degrees off the component-wise 3x3 median of its neighbourhood (unsolved pixels, normal 0,
count as off in every method), and the mean angular error over the mask.

- Real objects (``FOLDER``, default ../shared/data/diligent-8bit; skipped with a message when
  absent): subsets of 12 of the 96 lights, ``numpy.random.default_rng(seed).choice(96, 12)``
  for seed 0, 1, ..., inputs as ``ps-lab bench real`` makes them (the CLI's shadow rule).
- Stand-ins: a grey sphere and a relief, Lambertian or with speculars, 12 random lights
  (zenith <= 60 deg), exposed so the 99.5th percentile is at 0.8 of full scale, shot noise
  (20000 e- full well) and read noise, quantised and clipped at 0 without a dark frame; each
  with the shadow rule before issue 23's noise floor ("atom": only observations at the clipped
  black level are dropped) and with it ("floor", the default).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))

from solvers import clipped_capture  # noqa: E402

from ps_lab.bench.real import DEFAULT_FOLDER, find_objects, load_object  # noqa: E402
from ps_lab.io.dataset import load_dataset  # noqa: E402
from ps_lab.reconstruct import angular_errors_deg, solve  # noqa: E402
from ps_lab.reconstruct._shadows import black_threshold  # noqa: E402

OFF_DEG = 20.0
LIGHTS = 12


def wild_share(normals: np.ndarray, mask: np.ndarray) -> float:
    """Percent of interior pixels more than OFF_DEG off the 3x3 median of their normals.

    ``normals`` (P, 3) for the P pixels of ``mask`` (H, W), row-major.
    """
    img = np.zeros(mask.shape + (3,))
    img[mask] = normals
    med = np.stack([ndimage.median_filter(img[..., c], size=3) for c in range(3)], axis=-1)
    interior = ndimage.binary_erosion(mask, np.ones((3, 3)))
    m = med[interior]
    m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-12)
    return 100.0 * float(np.mean(angular_errors_deg(img[interior], m) > OFF_DEG))


def _cell(sol, truth, mask) -> str:
    error = angular_errors_deg(sol.normals, truth).mean()
    return f"{wild_share(sol.normals, mask):.2f} % / {error:.2f}°"


def _solve(method, obs, lights, valid, light_noise=None):
    kw = {} if method in ("ls", "plls") or light_noise is None else {"light_noise": light_noise}
    return solve(obs, lights, valid=valid, method=method, **kw)


def real_rows(folder: Path, methods, subsets: int):
    objects = find_objects(folder)
    if not objects:
        print(f"(no real objects under {folder}: skipped)")
        return
    print(f"\n12-light subsets of {folder} (wild share / mean error)\n")
    print("| object, subset | " + " | ".join(methods) + " | default - LS |")
    print("|---|" + "---|" * (len(methods) + 1))
    for path in objects:
        mask = load_dataset(path).mask
        for seed in range(subsets):
            pick = np.sort(np.random.default_rng(seed).choice(96, LIGHTS, replace=False))
            o = load_object(path, 1, pick)
            sols = {m: _solve(m, o.observations, o.light_directions, o.valid, o.light_noise)
                    for m in methods}
            diff = ""
            if "ls" in sols and "auto" in sols:
                gap = wild_share(sols["auto"].normals, mask) - wild_share(sols["ls"].normals, mask)
                diff = f"{gap:+.2f}"
            print(f"| {path.name} {seed} | "
                  + " | ".join(_cell(sols[m], o.normal_gt, mask) for m in methods)
                  + f" | {diff} |", flush=True)


def stand_in_rows(methods):
    print(f"\nStand-ins, {LIGHTS} lights, clipped at 0 without a dark frame "
          "(wild share / mean error; shadow rule: atom | floor)\n")
    print("| capture | " + " | ".join(f"{m} atom | {m} floor" for m in methods) + " |")
    print("|---|" + "---|---|" * len(methods))
    for bits, read_noise in ((16, 3.0), (8, 30.0)):
        for kind, specular in (("sphere", 0.0), ("sphere", 0.3), ("relief", 0.0),
                               ("relief", 0.3)):
            obs, lights, valid, truth, mask = clipped_capture(
                kind, LIGHTS, 3, shape=(160, 160), specular=specular, bits=bits,
                read_noise=read_noise)
            usable = {}
            for rule in ("atom", "floor"):
                black = black_threshold(obs, valid,
                                        light_directions=lights if rule == "floor" else None)
                usable[rule] = valid if black is None else valid & (obs > black[:, None])
            cells = [_cell(_solve(m, obs, lights, usable[rule]), truth, mask)
                     for m in methods for rule in ("atom", "floor")]
            print(f"| {bits}-bit, read noise {read_noise:g} e-, {kind}, specular {specular:g} | "
                  + " | ".join(cells) + " |", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folder", nargs="?", type=Path, default=DEFAULT_FOLDER)
    ap.add_argument("--methods", nargs="+", default=["ls", "sbl", "auto"])
    ap.add_argument("--subsets", type=int, default=2, help="light subsets per object (seeds)")
    ap.add_argument("--stand-ins-only", action="store_true")
    args = ap.parse_args(argv)
    if not args.stand_ins_only:
        real_rows(args.folder, args.methods, args.subsets)
    stand_in_rows(args.methods)
    return 0


if __name__ == "__main__":
    sys.exit(main())
