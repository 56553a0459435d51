"""First-run benchmark: ``ps-lab reconstruct`` with an empty numba cache, and after the install.

Renders one capture (``ps-lab simulate --scene relief``, ``--size`` x ``--size`` pixels,
``--lights`` lights, png16; 400 x 72 is the issue's 0.16 MP x 72-light case), then, ``--repeat``
times, each time in an empty numba cache (``NUMBA_CACHE_DIR`` set to a new temporary folder):

- ``cold``: ``ps-lab reconstruct`` twice, with nothing compiled beforehand (first and second run);
- ``installed``: ``python -m ps_lab.reconstruct._warm_up`` (what ``make demo``/``make test`` and
  the documented ``pip install`` step run), then ``ps-lab reconstruct`` twice;
- ``kernels``: every kernel compiled alone in a fresh process (:func:`_warm_up.warm_all`): wall
  and CPU seconds per kernel.

Each command is its own process (as a user runs it); wall seconds, the children's CPU seconds and
the 1-minute load average before each command are reported (the development machine is shared:
compare CPU seconds, and repeat). ``--before`` skips the ``installed`` scenario and the kernels
(for a checkout without ``_warm_up.main``; run it with that checkout on ``PYTHONPATH``). Usage::

    python benchmarks/first_run.py [--size 400] [--lights 72] [--method auto] [--repeat 2]
                                   [--before] [--markdown FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

_KERNELS = """
import json
from ps_lab.reconstruct._warm_up import warm_all
print(json.dumps(warm_all(say=lambda line: None)))
"""


def _timed(args: list[str], env: dict[str, str]) -> dict[str, float]:
    """Run ``args``; its wall and CPU seconds and the load average before it."""
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    done = subprocess.run(args, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode:
        sys.exit(f"{' '.join(args)} failed:\n{done.stderr}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall": wall, "cpu": cpu, "load": load, "stdout": done.stdout}


def _env(cache: Path) -> dict[str, str]:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    env.pop("NUMBA_DISABLE_JIT", None)
    return env


def _reconstruct(data: Path, out: Path, method: str) -> list[str]:
    return [sys.executable, "-m", "ps_lab", "reconstruct", str(data), "--out", str(out),
            "--method", method]


def run(size: int, lights: int, method: str, repeat: int, before: bool) -> dict:
    rows: dict[str, list[dict[str, float]]] = {}
    kernels: list[list] = []
    with tempfile.TemporaryDirectory(prefix="ps-lab-first-run-") as tmp:
        root = Path(tmp)
        data = root / "capture"
        subprocess.run([sys.executable, "-m", "ps_lab", "simulate", str(data), "--scene",
                        "relief", "--size", str(size), "--lights", str(lights), "--specular",
                        "0.3"], check=True, capture_output=True)
        scenarios = ["cold"] if before else ["kernels", "installed", "cold"]
        for rep in range(repeat):
            for scenario in scenarios:
                cache = root / f"numba-{scenario}-{rep}"
                env = _env(cache)
                if scenario == "kernels":
                    timed = _timed([sys.executable, "-c", _KERNELS], env)
                    kernels.append(json.loads(timed["stdout"]))
                    print(f"kernels {rep}: {kernels[-1]} (load {timed['load']:.1f})",
                          file=sys.stderr, flush=True)
                    continue
                out = root / f"out-{scenario}-{rep}"
                steps = [("first reconstruct", _reconstruct(data, out / "first", method)),
                         ("second reconstruct", _reconstruct(data, out / "second", method))]
                if scenario == "installed":
                    steps.insert(0, ("warm-up", [sys.executable, "-m",
                                                 "ps_lab.reconstruct._warm_up"]))
                for step, args in steps:
                    timed = _timed(args, env)
                    rows.setdefault(f"{scenario}: {step}", []).append(timed)
                    print(f"{scenario} {rep} {step}: wall {timed['wall']:.1f} s, CPU "
                          f"{timed['cpu']:.1f} s, load {timed['load']:.1f}", file=sys.stderr,
                          flush=True)
    return {"rows": rows, "kernels": kernels}


def markdown(result: dict, args: argparse.Namespace) -> str:
    lines = [
        f"`python benchmarks/first_run.py --size {args.size} --lights {args.lights} --method "
        f"{args.method} --repeat {args.repeat}{' --before' if args.before else ''}`, "
        f"{time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores, numba cache empty at the start of "
        "each scenario:",
        "",
        "| step | wall s (each run) | CPU s (each run) | load average before |",
        "|---|---|---|---|",
    ]
    for name, runs in result["rows"].items():
        walls = " / ".join(f"{r['wall']:.1f}" for r in runs)
        cpus = " / ".join(f"{r['cpu']:.1f}" for r in runs)
        loads = " / ".join(f"{r['load']:.1f}" for r in runs)
        lines.append(f"| {name} | {walls} | {cpus} | {loads} |")
    rows = result["rows"]
    for scenario in ("cold", "installed"):
        first = rows.get(f"{scenario}: first reconstruct", [])
        second = rows.get(f"{scenario}: second reconstruct", [])
        if first and len(first) == len(second):
            pairs = list(zip(first, second, strict=True))
            ratio = statistics.median(f["cpu"] / s["cpu"] for f, s in pairs)
            wall = statistics.median(f["wall"] / s["wall"] for f, s in pairs)
            lines.append(f"| {scenario}: first / second | {wall:.2f} | {ratio:.2f} | |")
    if result["kernels"]:
        lines += ["", "| kernel (compiled alone) | wall s | CPU s |", "|---|---|---|"]
        names = [k[0] for k in result["kernels"][0]]
        for i, name in enumerate(names):
            walls = " / ".join(f"{rep[i][1]:.1f}" for rep in result["kernels"])
            cpus = " / ".join(f"{rep[i][2]:.1f}" for rep in result["kernels"])
            lines.append(f"| `{name}` | {walls} | {cpus} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=400)
    parser.add_argument("--lights", type=int, default=72)
    parser.add_argument("--method", default="auto")
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--before", action="store_true",
                        help="cold runs only (a checkout without _warm_up.main)")
    parser.add_argument("--markdown", type=Path, help="also write the table here")
    args = parser.parse_args()
    table = markdown(run(args.size, args.lights, args.method, args.repeat, args.before), args)
    print(table)
    if args.markdown:
        args.markdown.write_text(table)


if __name__ == "__main__":
    main()
