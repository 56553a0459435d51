"""Scale benchmark: reconstruct a synthetic 50 MP x 100-light capture in bounded memory.

Generates a capture on disk (16-bit grey PNG, one per light; ``mask.png``, ``normal_gt.npy``,
``light_directions.txt``), rendering it band by band so that generation itself fits in memory, then
runs ``ps-lab reconstruct`` in a subprocess and reports wall time and peak resident memory (RSS) per
stage as a table. Usage::

    python benchmarks/scale.py [--megapixels 50] [--lights 100] [--method sbl] [--folder DIR]
                               [--memory-budget 1GB] [--timeout S] [--keep] [--markdown FILE]

The scene is a Lambertian sphere (textured albedo, attached shadows) with sparse Blinn-Phong
highlights and Gaussian noise, in closed form. Peak RSS is polled from ``/proc/<pid>/status``
(VmRSS every 0.2 s, VmHWM at the end) and checked against ``getrusage(RUSAGE_CHILDREN)``. With
``--timeout`` a solve that would take too long is stopped; the table then gives the measured solve
rate and the projected total.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np

RENDER_BAND_ROWS = 256
SHADOW_THRESHOLD = 0.002


def image_size(megapixels: float) -> tuple[int, int]:
    """(H, W) with a 3:2 aspect ratio and about ``megapixels`` million pixels."""
    width = int(round(math.sqrt(megapixels * 1e6 * 1.5)))
    return int(round(megapixels * 1e6 / width)), width


def light_directions(n: int, seed: int) -> np.ndarray:
    """``n`` unit directions, zenith up to 60 degrees, from a seeded generator."""
    rng = np.random.default_rng(seed)
    zenith = np.arccos(rng.uniform(np.cos(np.radians(60.0)), 1.0, n))
    azimuth = rng.uniform(0.0, 2 * np.pi, n)
    return np.stack(
        [np.sin(zenith) * np.cos(azimuth), np.sin(zenith) * np.sin(azimuth), np.cos(zenith)], axis=1
    )


def sphere_rows(shape, start, stop):
    """Normals (rows, W, 3), mask (rows, W) and albedo (rows, W) of rows start:stop (float32)."""
    height, width = shape
    cx, cy, radius = (width - 1) / 2.0, (height - 1) / 2.0, 0.45 * min(height, width)
    x = ((np.arange(width) - cx) / radius).astype(np.float32)
    y = (-(np.arange(start, stop) - cy) / radius).astype(np.float32)  # y up
    nx, ny = np.meshgrid(x, y)
    r2 = nx * nx + ny * ny
    mask = r2 < 0.98
    nz = np.sqrt(np.clip(1.0 - r2, 0.0, None))
    normals = np.stack([nx, ny, nz], axis=-1)
    normals[~mask] = 0.0
    cols = np.arange(width, dtype=np.float32)[None, :]
    rows = np.arange(start, stop, dtype=np.float32)[:, None]
    albedo = 0.55 + 0.25 * np.sin(cols / 97.0) * np.cos(rows / 131.0)
    return normals, mask, albedo


def generate(folder: Path, megapixels: float, lights: int, seed: int = 0) -> dict:
    """Write the synthetic capture into ``folder``; return its size and timing."""
    started = time.perf_counter()
    shape = image_size(megapixels)
    height, width = shape
    folder.mkdir(parents=True, exist_ok=True)
    directions = light_directions(lights, seed)
    np.savetxt(folder / "light_directions.txt", directions, fmt="%.9f")
    truth = np.lib.format.open_memmap(
        folder / "normal_gt.npy", mode="w+", dtype=np.float32, shape=(height, width, 3)
    )
    mask = np.zeros(shape, np.uint8)
    # The geometry of every band (float32, about 17 bytes per pixel) is kept for all the lights.
    geometry = []
    for start in range(0, height, RENDER_BAND_ROWS):
        stop = min(start + RENDER_BAND_ROWS, height)
        normals, inside, albedo = sphere_rows(shape, start, stop)
        truth[start:stop] = normals
        mask[start:stop] = inside * 255
        geometry.append((start, stop, normals, inside, albedo))
    truth.flush()
    del truth
    cv2.imwrite(str(folder / "mask.png"), mask)
    pixels = int(np.count_nonzero(mask))
    del mask
    halfway = directions + np.array([0.0, 0.0, 1.0])
    halfway /= np.linalg.norm(halfway, axis=1, keepdims=True)
    image = np.empty(shape, np.uint16)
    for i, light in enumerate(directions):
        for start, stop, normals, inside, albedo in geometry:
            value = 0.8 * albedo * np.clip(normals @ light.astype(np.float32), 0.0, None)
            cosine = normals @ halfway[i].astype(np.float32)
            glossy = cosine > 0.97  # the highlight (cos^200) is negligible elsewhere
            value[glossy] += 0.5 * cosine[glossy] ** 200
            rng = np.random.default_rng([seed, i, start])
            value += rng.standard_normal(value.shape, dtype=np.float32) * np.float32(0.002)
            value[~inside] = 0.0
            image[start:stop] = np.clip(np.rint(value * 65535.0), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(folder / f"{i:03d}.png"), image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if (i + 1) % 10 == 0 or i + 1 == lights:
            elapsed = time.perf_counter() - started
            print(f"  rendered {i + 1}/{lights} in {elapsed:.0f} s", file=sys.stderr, flush=True)
    size = sum(p.stat().st_size for p in folder.iterdir() if p.is_file())
    return {
        "width": width,
        "height": height,
        "pixels": pixels,
        "lights": lights,
        "bytes": size,
        "seconds": time.perf_counter() - started,
    }


class RssMonitor(threading.Thread):
    """Poll a process's VmRSS, keeping (time, rss bytes) samples and the kernel's VmHWM."""

    def __init__(self, pid: int, period: float = 0.2) -> None:
        super().__init__(daemon=True)
        self.pid, self.period = pid, period
        self.samples: list[tuple[float, int]] = []
        self.hwm = 0
        self.stopped = threading.Event()

    def run(self) -> None:
        status = Path(f"/proc/{self.pid}/status")
        while not self.stopped.is_set():
            try:
                text = status.read_text()
            except OSError:
                return
            fields = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
            if "VmRSS" in fields:
                self.samples.append((time.perf_counter(), int(fields["VmRSS"].split()[0]) * 1024))
            if "VmHWM" in fields:
                self.hwm = int(fields["VmHWM"].split()[0]) * 1024
            time.sleep(self.period)

    def peak(self, since: float = -math.inf, until: float = math.inf) -> int:
        return max((rss for t, rss in self.samples if since <= t <= until), default=0)


def reconstruct(folder: Path, out: Path, args) -> dict:
    """Run ``ps-lab -v reconstruct`` on ``folder``; return stage timings and memory."""
    command = [
        sys.executable, "-m", "ps_lab", "-v", "reconstruct", str(folder), "--method", args.method,
        "--out", str(out), "--memory-budget", args.memory_budget,
        "--shadow-threshold", str(SHADOW_THRESHOLD),
    ]  # fmt: skip
    if args.threads:
        command += ["--threads", str(args.threads)]
    if args.refine_lights:
        command += ["--refine-lights", str(args.refine_lights)]
    started = time.perf_counter()
    child = subprocess.Popen(command, stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    monitor = RssMonitor(child.pid)
    monitor.start()
    lines: list[tuple[float, str]] = []

    def read_stderr() -> None:
        for line in child.stderr:
            lines.append((time.perf_counter(), line.rstrip()))

    reader = threading.Thread(target=read_stderr, daemon=True)
    reader.start()
    timed_out = False
    try:
        child.wait(timeout=args.timeout)
    except subprocess.TimeoutExpired:
        timed_out = True
        child.send_signal(signal.SIGINT)  # Ctrl-C: the run removes its staged folder and store
        try:
            child.wait(timeout=60)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
    ended = time.perf_counter()
    monitor.stopped.set()
    monitor.join()
    reader.join(timeout=5)
    stdout = child.stdout.read()
    children_maxrss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024
    read_end = next((t for t, line in lines if " read " in line and "images" in line), None)
    band_lines = [(t, line) for t, line in lines if ": band " in line and " done (" in line]
    result = {
        "exit_code": child.returncode,
        "timed_out": timed_out,
        "wall_seconds": ended - started,
        # getrusage covers the whole life of the child (the last poll may miss its final moments)
        "peak_rss": max(monitor.hwm, monitor.peak(), children_maxrss),
        "children_maxrss": children_maxrss,
        "stdout": stdout.strip(),
        "log_tail": [line for _, line in lines[-5:]],
    }
    if read_end is not None:
        result["read_seconds"] = read_end - started
        result["read_peak_rss"] = monitor.peak(until=read_end)
        result["solve_peak_rss"] = monitor.peak(since=read_end)
    if band_lines:
        pixels = sum(int(line.split(" done (")[1].split()[0]) for _, line in band_lines)
        result["bands_done"] = len(band_lines)
        result["pixels_solved"] = pixels
        if read_end is not None:
            result["solve_rate"] = pixels / max(band_lines[-1][0] - read_end, 1e-9)
    metrics_file = out / "metrics.json"
    if child.returncode == 0 and metrics_file.is_file():
        metrics = json.loads(metrics_file.read_text())
        result["metrics"] = metrics
        result["solve_seconds"] = metrics["timings"]["solve_seconds"]
        result["write_seconds"] = metrics["timings"]["write_seconds"]
        result["read_seconds"] = metrics["timings"]["read_seconds"]
    return result


def gb(value: float) -> str:
    return f"{value / 2**30:.2f}"


def table(generated: dict, run: dict, args) -> str:
    """The results as a Markdown table with the machine."""
    pixels = generated["pixels"]
    rows = [
        ("generate capture (benchmark itself)",
         "reused" if math.isnan(generated["seconds"]) else f"{generated['seconds']:.0f}", "-"),
    ]
    read_seconds = run.get("read_seconds", float("nan"))
    rows.append(("reconstruct: read + stage (pass 1)", f"{read_seconds:.0f}",
                 gb(run.get("read_peak_rss", 0))))  # fmt: skip
    if "metrics" in run:
        rows.append((f"reconstruct: {args.method} solve + banded outputs",
                     f"{run['solve_seconds']:.0f}", gb(run.get("solve_peak_rss", 0))))  # fmt: skip
        rows.append(("reconstruct: pictures + metrics", f"{run['write_seconds']:.0f}", "-"))
    elif "solve_rate" in run:
        projected = pixels * (args.refine_lights + 1) / run["solve_rate"]
        rows.append((f"reconstruct: {args.method} solve (stopped after {run['bands_done']} bands, "
                     f"{run['pixels_solved']} px)", f"{run['wall_seconds'] - read_seconds:.0f}",
                     gb(run.get("solve_peak_rss", 0))))  # fmt: skip
        rows.append((f"reconstruct: {args.method} solve, projected for all pixels",
                     f"{projected:.0f}", "-"))  # fmt: skip
    rows.append(
        ("reconstruct: total (subprocess)", f"{run['wall_seconds']:.0f}", gb(run["peak_rss"]))
    )
    cpu = platform.processor() or platform.machine()
    try:
        cpuinfo = Path("/proc/cpuinfo").read_text().splitlines()
        model = next(
            line.split(":", 1)[1].strip() for line in cpuinfo if line.startswith("model name")
        )
        cpu = model
    except (OSError, StopIteration):
        pass
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    lines = [
        f"Capture: {generated['width']} x {generated['height']} "
        f"({generated['width'] * generated['height'] / 1e6:.1f} MP), {generated['lights']} lights "
        f"(16-bit grey PNG, {generated['bytes'] / 1e9:.2f} GB on disk), {pixels} mask pixels; "
        f"method {args.method}"
        + (f" with --refine-lights {args.refine_lights}" if args.refine_lights else "")
        + f", memory budget {args.memory_budget}.",
        f"Machine: {cpu}, {os.cpu_count()} cores, {memory / 2**30:.0f} GiB RAM, "
        f"Python {platform.python_version()}, numpy {np.__version__}.",
        "",
        "| stage | wall s | peak RSS GiB |",
        "|---|---:|---:|",
        *[f"| {a} | {b} | {c} |" for a, b, c in rows],
        "",
        f"Peak RSS of the reconstruct process: {gb(run['peak_rss'])} GiB "
        f"(getrusage of the child: {gb(run['children_maxrss'])} GiB; stage peaks are polled "
        f"every 0.2 s); exit code {run['exit_code']}"
        + (", stopped by --timeout" if run["timed_out"] else "") + ".",
    ]
    if "solve_rate" in run:
        lines.append(f"Solve rate: {run['solve_rate']:.0f} pixels/s.")
    errors = run.get("metrics", {}).get("angular_error_deg")
    if errors:
        lines.append(f"Normal error: mean {errors['mean']:.3f} deg, median {errors['median']:.3f} "
                     f"deg, p90 {errors['p90']:.3f} deg.")  # fmt: skip
    streaming = run.get("metrics", {}).get("streaming")
    if streaming:
        staged = streaming["staging_bytes"] / 1e9
        lines.append(f"Bands: {streaming['bands']} of at most {streaming['max_band_pixels']} "
                     f"pixels; staging {streaming['staging']} ({staged:.2f} GB).")  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--megapixels", type=float, default=50.0)
    parser.add_argument("--lights", type=int, default=100)
    parser.add_argument("--method", default="sbl", choices=("ls", "l1", "sbl", "rpca"))
    parser.add_argument("--memory-budget", default="1GB")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--refine-lights", type=int, default=0, help="K refinement iterations")
    parser.add_argument("--folder", type=Path, default=None, help="capture folder (default: temp)")
    parser.add_argument("--reuse", action="store_true", help="reuse a capture already in --folder")
    parser.add_argument("--timeout", type=float, default=None, help="stop the solve after S s")
    parser.add_argument("--keep", action="store_true", help="keep the capture afterwards")
    parser.add_argument("--markdown", type=Path, default=None, help="also write the table here")
    args = parser.parse_args(argv)
    folder = args.folder or Path(os.environ.get("TMPDIR", "/tmp")) / (
        f"ps-lab-scale-{args.megapixels:g}mp-{args.lights}"
    )
    try:
        if args.reuse and (folder / "light_directions.txt").is_file():
            mask = cv2.imread(str(folder / "mask.png"), cv2.IMREAD_UNCHANGED)
            generated = {
                "width": mask.shape[1], "height": mask.shape[0],
                "pixels": int(np.count_nonzero(mask)), "lights": args.lights,
                "bytes": sum(p.stat().st_size for p in folder.iterdir() if p.is_file()),
                "seconds": float("nan"),
            }  # fmt: skip
        else:
            print(f"generating {folder} ...", file=sys.stderr)
            generated = generate(folder, args.megapixels, args.lights)
        out = folder / "recon" / args.method
        print(f"reconstructing into {out} ...", file=sys.stderr)
        run = reconstruct(folder, out, args)
        text = table(generated, run, args)
        print(text)
        if run["exit_code"] not in (0, None) and not run["timed_out"]:
            print("\n".join(run["log_tail"]), file=sys.stderr)
        if args.markdown:
            args.markdown.write_text(text + "\n")
    finally:
        if not args.keep and folder.exists() and args.folder is None:
            shutil.rmtree(folder, ignore_errors=True)
    return 0 if run["exit_code"] == 0 or run["timed_out"] else 1


if __name__ == "__main__":
    sys.exit(main())
