"""Integration benchmark: seconds and peak memory of ``integrate`` per method and mask size.

For each size the relief of the renderer (a dome with bumps and ridges, its disc mask holding the
requested number of pixels) is rendered once into ``normals.npy`` (float32); each (size, method)
then runs in its own process, which loads the normals and integrates them, so that its peak
resident memory is the integration's: ``VmHWM`` of ``/proc/self/status`` on Linux (the high-water
mark of the process's own memory; ``ru_maxrss`` is not used there, because a child started by
``fork``/``vfork`` and ``exec`` inherits the parent's peak in it: 3.51 GiB reported for a 2.47 GiB
12 MP solve right after the parent had rendered the normals), ``ru_maxrss`` elsewhere. Reports wall and CPU seconds, peak RSS,
iterations and the depth error against the relief's height. Usage::

    python benchmarks/integrate.py [--sizes 0.25,1,4,12] [--methods poisson,bilateral]
                                   [--bilateral-up-to 4] [--timeout S] [--folder DIR]
                                   [--markdown FILE]

The children run with the caller's environment (no BLAS thread limit), as ``ps-lab integrate`` does:
the solver makes no threaded BLAS call (``ps_lab.reconstruct._multigrid``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DISC_SHARE = math.pi * 0.45**2  # the relief's mask: a disc of radius 0.45 x the side


def _render(megapixels: float, folder: Path) -> Path:
    from ps_lab.render import relief_surface

    side = int(round(math.sqrt(megapixels * 1e6 / DISC_SHARE)))
    path = folder / f"relief-{megapixels:g}mp"
    if not (path / "normals.npy").is_file():
        path.mkdir(parents=True, exist_ok=True)
        surface = relief_surface((side, side), seed=1)
        np.save(path / "normals.npy", surface.normals.astype(np.float32))
        depth = np.where(surface.mask, -surface.height, np.nan).astype(np.float32)
        np.save(path / "depth.npy", depth)
    return path


def _peak_bytes() -> int:
    """This process's peak resident memory in bytes (see the module docstring)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    scale = 1 if sys.platform == "darwin" else 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale


def _child(path: Path, method: str) -> None:
    from ps_lab.reconstruct.integrate import integrate
    from ps_lab.reconstruct.metrics import depth_error

    normals = np.load(path / "normals.npy", mmap_mode="r")
    wall, cpu = time.perf_counter(), time.process_time()
    result = integrate(normals, None, method)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    peak = _peak_bytes()
    error = depth_error(result.depth, np.load(path / "depth.npy"))
    print(json.dumps({
        "pixels": result.pixels, "wall_s": wall, "cpu_s": cpu, "peak_bytes": peak,
        "iterations": result.iterations, "solver_iterations": result.solver_iterations,
        "converged": result.converged, "relative_error": error["relative"],
    }))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="0.25,1,4,12", help="mask sizes in megapixels")
    parser.add_argument("--methods", default="poisson,bilateral")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per run")
    parser.add_argument(
        "--bilateral-up-to", type=float, default=4.0,
        help="largest size (MP) for bilateral (12 MP: about 10 min)",
    )
    parser.add_argument("--folder", type=Path, default=None, help="where the normals are kept")
    parser.add_argument("--markdown", type=Path, default=None, help="also write the table here")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(Path(args.child[0]), args.child[1])
        return
    folder = args.folder or Path(tempfile.mkdtemp(prefix="ps-lab-integrate-"))
    rows = [
        f"integrate benchmark, {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cores, python {platform.python_version()}",
        "",
        "| mask | method | wall s | CPU s | peak RSS | iterations (CG) | depth error |",
        "|---|---|---|---|---|---|---|",
    ]
    print("\n".join(rows), flush=True)
    for megapixels in (float(s) for s in args.sizes.split(",")):
        path = _render(megapixels, folder)
        for method in args.methods.split(","):
            if method == "bilateral" and megapixels > args.bilateral_up_to:
                continue
            command = [sys.executable, __file__, "--child", str(path), method]
            try:
                done = subprocess.run(
                    command, capture_output=True, text=True, timeout=args.timeout
                )
                record = json.loads(done.stdout.strip().splitlines()[-1])
                row = (
                    f"| {record['pixels'] / 1e6:.2f} MP | {method} | {record['wall_s']:.1f} | "
                    f"{record['cpu_s']:.1f} | {record['peak_bytes'] / 2**30:.2f} GiB | "
                    f"{record['iterations']} ({record['solver_iterations']}) | "
                    f"{100 * record['relative_error']:.3f} % |"
                )
            except subprocess.TimeoutExpired:
                row = f"| {megapixels:g} MP | {method} | > {args.timeout:.0f} (stopped) | | | | |"
            except (ValueError, IndexError):
                failure = done.stderr.strip()[-200:]
                row = f"| {megapixels:g} MP | {method} | failed: {failure} | | | | |"
            rows.append(row)
            print(row, flush=True)
    if args.markdown:
        args.markdown.write_text("\n".join(rows) + "\n")


if __name__ == "__main__":
    main()
