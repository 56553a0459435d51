"""End-to-end speed: ps-lab's default against a numpy floor and RelightLab, per stage (issue 37).

Usage (from the repository root)::

    .venv/bin/python benchmarks/speed.py [--captures jpeg4,png16-12mp] [--quick] [--check]
        [--runs default,sbl,ls,hsh3,relightlab] [--megapixels MP] [--lights N] [--repeats 3]
        [--memory-budget 1GB] [--timeout S] [--work DIR] [--synthetic] [--png16-format png]
        [--relightlab DIR] [--keep] [--no-warm-up] [--json FILE] [--markdown FILE]

Captures (made in ``--work``, default ``$TMPDIR/ps-lab-speed``, and reused while their parameters
are the same: the folder name carries a hash of them):

- ``jpeg4``: RealRTI item3 (``../shared/data/realrti-3/item3``: 72 sRGB JPEGs of 402 x 395 and
  ``dirs.lp``) upscaled 5x (OpenCV, cubic) to 2010 x 1975 (4 MP), JPEG quality 95, ``.lp`` copied;
- ``png16-12mp``: DiLiGenT cat (``../shared/data/diligent-8bit/cat``, 96 lights) upscaled in float
  to 12 MP and written as 16-bit colour PNG (``--png16-format tiff``: 16-bit TIFF), with its
  light files, mask and a ``dirs.lp`` for RelightLab.

When the shared data is absent (or with ``--synthetic``) a capture of the same size is rendered in
closed form instead (a textured, glossy colour sphere; the output says so). ``--megapixels`` and
``--lights`` resize both captures (small versions for development and the test).

Per capture: the **floor** (a plain numpy script in its own process, as a user would write it:
``cv2.imread`` of every image as stored, grey = channel mean in float32 (added channel by channel:
numpy's ``mean(axis=2)`` over three values is 5x slower), normals = ``pinv(L) @ I`` for all pixels,
normalised) runs ``--repeats`` times before and after the ps-lab runs (the median
of all is the floor); then each **run** (``python -m ps_lab reconstruct CAPTURE --out OUT`` with
the run's options, a fresh OUT each time; RelightLab's ``relight-cli -b hsh -p 27``) is timed in a
subprocess: wall and CPU (user + sys, from ``os.wait4``) seconds, peak RSS (VmRSS polled every
0.1 s, VmHWM, ``ru_maxrss``) and the ratio of wall to the floor's median. The default run's
``metrics.json`` gives the **per-stage** table (``timings["stages"]``, ``timings["files"]``; older
results: the flat ``read/solve/write/surface_seconds`` and the appearance fit), beside the floor's
own decode / grey / least-squares seconds.

``--quick``: the 4 MP capture only, one floor run before and after, runs default, sbl, ls and
RelightLab. ``--check``: exit 1 if a target fails (default <= 15x floor; ``--method ls
--appearance none`` <= 3x floor; default solve <= 2x SBL's solve; peak RSS <= 4 GiB at 4 MP; 12 MP
default <= 300 s); each target is printed with its measured value. ``--json FILE``: everything.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import json
import math
import os
import platform
import shutil
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
DEFAULT_WORK = Path(os.environ.get("TMPDIR", "/tmp")) / "ps-lab-speed"
RELIGHTLAB = SHARED / "tools" / "relightlab"
GIB = 2**30


def _load_scale():
    """benchmarks/scale.py as a module (its RssMonitor, sphere_rows and light_directions)."""
    spec = importlib.util.spec_from_file_location("ps_lab_bench_scale", Path(__file__).with_name(
        "scale.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


scale = _load_scale()

# name -> what it is made from; base_shape (H, W) is the source's (or, synthetic, the same size)
CAPTURES = {
    "jpeg4": {
        "kind": "jpeg",
        "source": SHARED / "data" / "realrti-3" / "item3",
        "base_shape": (395, 402),
        "scale": 5.0,
        "lights": 72,
    },
    "png16-12mp": {
        "kind": "png16",
        "source": SHARED / "data" / "diligent-8bit" / "cat",
        "base_shape": (512, 612),
        "megapixels": 12.0,
        "lights": 96,
    },
}
CAPTURE_VERSION = 1  # bump when what a capture holds changes (its cache key changes with it)

# name -> (label, ps-lab reconstruct options); "relightlab" is RelightLab's relight-cli
RUNS = {
    "default": ("default", []),
    "sbl": ("sbl, no appearance", ["--method", "sbl", "--appearance", "none"]),
    "ls": ("ls, no appearance", ["--method", "ls", "--appearance", "none"]),
    "hsh3": ("default, hsh3 appearance", ["--appearance", "hsh3"]),
    "relightlab": ("RelightLab HSH 27", None),
}
ALL_RUNS = "default,sbl,ls,hsh3,relightlab"
QUICK_RUNS = "default,sbl,ls,relightlab"
RELIGHTLAB_ARGS = ["-b", "hsh", "-p", "27"]

# The stages of metrics["timings"]["stages"], in the order printed (others follow in theirs), and
# the floor's step each compares with.
STAGES = ("decode", "linearise", "stage", "noise", "solve", "albedo", "outputs", "appearance",
          "surface")
FLOOR_STEP = {"decode": "decode", "linearise": "grey", "solve": "solve"}
# Results without "stages": (label, where in metrics, floor step)
LEGACY_STAGES = (
    ("read + stage", ("timings", "read_seconds"), "decode+grey"),
    ("solve", ("timings", "solve_seconds"), "solve"),
    ("outputs + appearance", ("timings", "write_seconds"), None),
    ("  of which appearance fit", ("appearance", "timings", "fit_seconds"), None),
    ("surface", ("timings", "surface_seconds"), None),
)

# The plain numpy script of the floor: argv[1] is a JSON file {"files": [...], "directions": [...]}
FLOOR_SCRIPT = '''\
import json, sys, time
started = time.perf_counter()
import cv2
import numpy as np
spec = json.load(open(sys.argv[1]))
lights = np.asarray(spec["directions"], np.float64)
imported = time.perf_counter() - started
decode = grey = 0.0
stack = None
for i, name in enumerate(spec["files"]):
    t0 = time.perf_counter()
    image = cv2.imread(name, cv2.IMREAD_UNCHANGED)
    t1 = time.perf_counter()
    if stack is None:
        height, width = image.shape[:2]
        stack = np.empty((len(spec["files"]), height * width), np.float32)
    row = stack[i]
    if image.ndim == 3:  # the channels' mean, channel by channel (mean(axis=2) is 5x slower)
        flat = image.reshape(height * width, -1)
        np.add(flat[:, 0], flat[:, 1], out=row, dtype=np.float32)
        for channel in range(2, flat.shape[1]):
            row += flat[:, channel]
        row *= np.float32(1.0 / flat.shape[1])
    else:
        row[:] = image.reshape(-1)
    decode += t1 - t0
    grey += time.perf_counter() - t1
t0 = time.perf_counter()
normals = np.linalg.pinv(lights).astype(np.float32) @ stack
length = np.sqrt((normals * normals).sum(axis=0))
normals /= np.maximum(length, np.float32(1e-12))
solve = time.perf_counter() - t0
print(json.dumps({"import": imported, "decode": decode, "grey": grey, "solve": solve,
                  "pixels": int(stack.shape[1]), "images": int(stack.shape[0]),
                  "bytes_decoded": int(stack.shape[1]) * (image.nbytes // (height * width))
                  * int(stack.shape[0])}))
'''


# ---------------------------------------------------------------------------------------------
# captures


def capture_plan(name: str, megapixels: float | None, lights: int | None, synthetic: bool,
                 png16_format: str = "png") -> dict:
    """What capture ``name`` will hold: size, lights, source (a folder or "synthetic")."""
    spec = CAPTURES[name]
    source = spec["source"]
    real = not synthetic and source.is_dir()
    base_h, base_w = spec["base_shape"]
    if real and spec["kind"] == "jpeg":
        first = cv2.imread(str(_lp_rows(source)[0][0]), cv2.IMREAD_UNCHANGED)
        base_h, base_w = first.shape[:2]
    if real and spec["kind"] == "png16":
        base_h, base_w = cv2.imread(str(source / "mask.png"), cv2.IMREAD_UNCHANGED).shape[:2]
    if megapixels is not None:
        factor = math.sqrt(megapixels * 1e6 / (base_h * base_w))
    elif "scale" in spec:
        factor = spec["scale"]
    else:
        factor = math.sqrt(spec["megapixels"] * 1e6 / (base_h * base_w))
    height, width = max(8, round(base_h * factor)), max(8, round(base_w * factor))
    available = None
    if real:
        listed = _lp_rows(source) if spec["kind"] == "jpeg" else _diligent_files(source)
        available = len(listed)
    wanted = lights if lights is not None else spec["lights"]
    notes = []
    if available is not None and wanted > available:
        notes.append(f"{wanted} lights asked, the source has {available}")
        wanted = available
    if not real:
        notes.append("synthetic render" + ("" if synthetic else f" ({source} is absent)"))
    return {
        "name": name,
        "kind": spec["kind"],
        "source": str(source) if real else "synthetic",
        "height": height,
        "width": width,
        "scale": factor,
        "lights": wanted,
        "format": "jpg" if spec["kind"] == "jpeg" else png16_format,
        "version": CAPTURE_VERSION,
        "notes": notes,
    }


def capture_folder(work: Path, plan: dict) -> Path:
    key_fields = {k: v for k, v in plan.items() if k != "notes"}
    key = hashlib.sha1(json.dumps(key_fields, sort_keys=True).encode()).hexdigest()[:10]
    return work / "captures" / f"{plan['name']}-{plan['width']}x{plan['height']}-{key}"


def make_capture(work: Path, plan: dict) -> dict:
    """Make (or reuse) the capture of ``plan`` under ``work``; return its record."""
    folder = capture_folder(work, plan)
    record_file = folder / "capture.json"
    if record_file.is_file():
        record = json.loads(record_file.read_text())
        record["reused"] = True
        return record
    partial = folder.with_name(folder.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    started = time.perf_counter()
    make = {("jpeg", True): _jpeg_from_rti, ("png16", True): _png16_from_diligent,
            ("jpeg", False): _synthetic, ("png16", False): _synthetic}
    files, directions = make[plan["kind"], plan["source"] != "synthetic"](partial, plan)
    record = dict(plan)
    record.update(
        folder=str(folder),
        files=files,
        directions=np.asarray(directions).tolist(),
        bytes=sum(p.stat().st_size for p in partial.iterdir() if p.is_file()),
        generate_seconds=time.perf_counter() - started,
        reused=False,
    )
    (partial / "capture.json").write_text(json.dumps(record, indent=1) + "\n")
    shutil.rmtree(folder, ignore_errors=True)
    partial.rename(folder)
    return record


def _lp_rows(folder: Path) -> list[tuple[Path, np.ndarray]]:
    from ps_lab.io.light_files import find_lp, read_lp

    lp = find_lp(folder)
    names, directions = read_lp(lp)
    return [(folder / name, d) for name, d in zip(names, directions, strict=True)]


def _diligent_files(folder: Path) -> list[str]:
    listed = folder / "filenames.txt"
    if listed.is_file():
        return listed.read_text().split()
    return sorted(p.name for p in folder.glob("[0-9][0-9][0-9].png"))


def _chosen(available: int, wanted: int) -> np.ndarray:
    """``wanted`` indices spread evenly over ``available`` (all of them when equal)."""
    return np.unique(np.linspace(0, available - 1, wanted).round().astype(int))


def _write_lp(folder: Path, names: list[str], directions: np.ndarray) -> None:
    lines = [f"{len(names)}"] + [
        f"{name} {x:.9f} {y:.9f} {z:.9f}" for name, (x, y, z) in zip(names, directions, strict=True)
    ]
    (folder / "dirs.lp").write_text("\n".join(lines) + "\n")


def _jpeg_from_rti(folder: Path, plan: dict) -> tuple[list[str], np.ndarray]:
    """RealRTI item3's JPEGs resized (cubic) to the plan's size, quality 95, with a ``.lp``."""
    rows = _lp_rows(Path(plan["source"]))
    rows = [rows[i] for i in _chosen(len(rows), plan["lights"])]
    names = []
    for path, _ in rows:
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        resized = cv2.resize(image, (plan["width"], plan["height"]), interpolation=cv2.INTER_CUBIC)
        cv2.imwrite(str(folder / path.name), resized, [cv2.IMWRITE_JPEG_QUALITY, 95])
        names.append(path.name)
    directions = np.array([d for _, d in rows])
    _write_lp(folder, names, directions)
    return names, directions


def _png16_from_diligent(folder: Path, plan: dict) -> tuple[list[str], np.ndarray]:
    """A DiLiGenT object upscaled in float (cubic) and written as 16-bit colour, one at a time."""
    source = Path(plan["source"])
    files = _diligent_files(source)
    chosen = _chosen(len(files), plan["lights"])
    directions = np.loadtxt(source / "light_directions.txt")[chosen]
    np.savetxt(folder / "light_directions.txt", directions, fmt="%.9f")
    if (source / "light_intensities.txt").is_file():
        intensities = np.loadtxt(source / "light_intensities.txt")[chosen]
        np.savetxt(folder / "light_intensities.txt", intensities, fmt="%.9f")
    size = (plan["width"], plan["height"])
    if (source / "mask.png").is_file():
        mask = cv2.imread(str(source / "mask.png"), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(folder / "mask.png"), cv2.resize(mask, size,
                                                         interpolation=cv2.INTER_NEAREST))
    names = []
    for number, index in enumerate(chosen, start=1):
        image = cv2.imread(str(source / files[index]), cv2.IMREAD_UNCHANGED)
        peak = 255.0 if image.dtype == np.uint8 else 65535.0
        value = cv2.resize(image.astype(np.float32) / np.float32(peak), size,
                           interpolation=cv2.INTER_CUBIC)
        names.append(_write16(folder, number, value, plan["format"]))
    _write_lp(folder, names, directions)
    return names, directions


def _write16(folder: Path, number: int, bgr: np.ndarray, fmt: str) -> str:
    """Write linear values (BGR, 0..1) as frame ``number`` in 16 bits; return its file name."""
    image = np.clip(np.rint(bgr * np.float32(65535.0)), 0, 65535).astype(np.uint16)
    name = f"{number:03d}.{fmt}"
    if fmt == "png":
        cv2.imwrite(str(folder / name), image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    else:
        import tifffile

        tifffile.imwrite(folder / name, np.ascontiguousarray(image[..., ::-1]), photometric="rgb")
    return name


def _synthetic(folder: Path, plan: dict) -> tuple[list[str], np.ndarray]:
    """A textured, glossy colour sphere rendered in closed form, one frame at a time."""
    from ps_lab.io.encoding import linear_to_srgb

    shape = (plan["height"], plan["width"])
    normals, inside, albedo = scale.sphere_rows(shape, 0, shape[0])
    tint = np.array([0.45, 0.7, 0.95], np.float32)  # B, G, R as OpenCV writes them
    colour = albedo[..., None] * tint
    colour[~inside] = 0.05
    directions = scale.light_directions(plan["lights"], seed=37)
    halfway = directions + np.array([0.0, 0.0, 1.0])
    halfway /= np.linalg.norm(halfway, axis=1, keepdims=True)
    names = []
    for number, (light, half) in enumerate(zip(directions, halfway, strict=True), start=1):
        shade = np.clip(normals @ light.astype(np.float32), 0.0, None)
        shade[~inside] = 0.3
        gloss = np.clip(normals @ half.astype(np.float32), 0.0, None) ** 60 * inside
        value = colour * (0.8 * shade)[..., None] + (0.4 * gloss)[..., None]
        if plan["kind"] == "jpeg":
            name = f"image{number:03d}.jpg"
            encoded = np.rint(linear_to_srgb(value) * 255).astype(np.uint8)
            cv2.imwrite(str(folder / name), encoded, [cv2.IMWRITE_JPEG_QUALITY, 95])
            names.append(name)
        else:
            names.append(_write16(folder, number, value, plan["format"]))
    if plan["kind"] == "png16":
        np.savetxt(folder / "light_directions.txt", directions, fmt="%.9f")
        cv2.imwrite(str(folder / "mask.png"), inside.astype(np.uint8) * 255)
    _write_lp(folder, names, directions)
    return names, directions


# ---------------------------------------------------------------------------------------------
# measuring a process


def measure(command: list[str], timeout: float | None = None, env: dict | None = None) -> dict:
    """Run ``command``; its wall and CPU seconds, peak RSS, exit code, stdout and stderr's tail.

    CPU time and ``ru_maxrss`` are the child's own (``os.wait4``, its threads and the descendants
    it waited for); RSS is also polled from /proc (VmRSS, VmHWM) while it runs. At ``timeout``
    the child gets SIGINT (ps-lab removes its staged output), then SIGKILL a minute later.
    """
    started = time.perf_counter()
    child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             env=env)
    monitor = scale.RssMonitor(child.pid, period=0.1)
    monitor.start()
    streams: dict[str, str] = {}
    readers = [
        threading.Thread(target=lambda n=n, s=s: streams.__setitem__(n, s.read()), daemon=True)
        for n, s in (("stdout", child.stdout), ("stderr", child.stderr))
    ]
    for reader in readers:
        reader.start()
    timed_out = threading.Event()

    def stop() -> None:
        timed_out.set()
        child.send_signal(signal.SIGINT)
        killer = threading.Timer(60.0, lambda: child.returncode is None and child.kill())
        killer.daemon = True
        killer.start()

    timer = None
    if timeout is not None:
        timer = threading.Timer(timeout, stop)
        timer.daemon = True
        timer.start()
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - started
    child.returncode = os.waitstatus_to_exitcode(status)
    if timer is not None:
        timer.cancel()
    monitor.stopped.set()
    monitor.join()
    for reader in readers:
        reader.join(timeout=10)
    child.stdout.close()
    child.stderr.close()
    return {
        "command": [str(c) for c in command],
        "exit_code": child.returncode,
        "timed_out": timed_out.is_set(),
        "wall_seconds": wall,
        "cpu_seconds": usage.ru_utime + usage.ru_stime,
        "user_seconds": usage.ru_utime,
        "sys_seconds": usage.ru_stime,
        "peak_rss": max(usage.ru_maxrss * 1024, monitor.hwm, monitor.peak()),
        "stdout": streams.get("stdout", "").strip(),
        "stderr_tail": streams.get("stderr", "").strip().splitlines()[-5:],
    }


def child_env() -> dict:
    """The environment of the runs: this checkout's ps_lab first on PYTHONPATH."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p
    )
    return env


def run_floor(record: dict, work: Path, timeout: float | None = None) -> dict:
    """One run of the numpy floor script on the capture (its own process)."""
    script = work / "floor.py"
    if not script.is_file() or script.read_text() != FLOOR_SCRIPT:
        script.write_text(FLOOR_SCRIPT)
    spec = work / f"floor-{Path(record['folder']).name}.json"
    folder = Path(record["folder"])
    spec.write_text(json.dumps({"files": [str(folder / f) for f in record["files"]],
                                "directions": record["directions"]}))
    result = measure([sys.executable, str(script), str(spec)], timeout=timeout)
    if result["exit_code"] == 0:
        result["steps"] = json.loads(result["stdout"].splitlines()[-1])
    return result


def floor_summary(before: list[dict], after: list[dict]) -> dict:
    """The median of the floor runs (wall, CPU, peak RSS, each step), and each run's wall."""
    runs = [r for r in before + after if r["exit_code"] == 0]
    if not runs:
        return {"ok": False, "before": before, "after": after}
    steps = {}
    for key in ("import", "decode", "grey", "solve"):
        steps[key] = statistics.median(r["steps"][key] for r in runs)
    steps["decode+grey"] = steps["decode"] + steps["grey"]
    return {
        "ok": True,
        "wall_seconds": statistics.median(r["wall_seconds"] for r in runs),
        "cpu_seconds": statistics.median(r["cpu_seconds"] for r in runs),
        "peak_rss": max(r["peak_rss"] for r in runs),
        "steps": steps,
        "bytes_decoded": runs[0]["steps"]["bytes_decoded"],
        "walls_before": [r["wall_seconds"] for r in before],
        "walls_after": [r["wall_seconds"] for r in after],
        "before": before,
        "after": after,
    }


# ---------------------------------------------------------------------------------------------
# the runs


def relightlab_command(tool: Path, capture: Path, out: Path) -> list[str] | None:
    """relight-cli's command line (the binary, past the installing wrapper), or None if absent."""
    binary = tool / "relight-cli"
    if not (binary.is_file() and os.access(binary, os.X_OK)):
        return None
    return ["env", "QT_QPA_PLATFORM=offscreen", str(binary), *RELIGHTLAB_ARGS, str(capture),
            str(out)]


def prepare_relightlab(tool: Path) -> str | None:
    """Install the tool's libraries once (its ``run`` wrapper); None, or why it cannot run."""
    wrapper = tool / "run"
    if not (tool / "relight-cli").is_file() or not wrapper.is_file():
        return f"not found ({tool})"
    done = subprocess.run([str(wrapper), "relight-cli", "-h"], capture_output=True, text=True,
                          check=False)
    if done.returncode not in (0, 1) or "Usage" not in done.stdout + done.stderr:
        return f"does not run here (exit {done.returncode}: {done.stderr.strip()[-200:]})"
    return None


def run_one(name: str, record: dict, work: Path, args, relightlab_problem: str | None) -> dict:
    """Run ``name`` on the capture in a fresh output folder; its measures and metrics."""
    label, options = RUNS[name]
    capture = Path(record["folder"])
    out = work / "runs" / capture.name / name
    shutil.rmtree(out, ignore_errors=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    result: dict = {"name": name, "label": label}
    if options is None:
        command = relightlab_command(args.relightlab, capture, out)
        if relightlab_problem or command is None:
            result["skipped"] = f"relight-cli {relightlab_problem or 'not found'}"
            return result
        if not list(capture.glob("*.lp")):
            result["skipped"] = "the capture has no .lp file"
            return result
        if not all(f.lower().endswith((".jpg", ".jpeg")) for f in record["files"]):
            # it counts only the JPEGs of a folder ("Number of lights in dome needs to be equal
            # to the number of images" for PNG and TIFF frames)
            result["skipped"] = "relight-cli reads JPEG frames only"
            return result
        result["options"] = " ".join(["relight-cli", *RELIGHTLAB_ARGS])
        result.update(measure(command, timeout=args.timeout))
    else:
        extra = list(options)
        if args.memory_budget:
            extra += ["--memory-budget", args.memory_budget]
        command = [sys.executable, "-m", "ps_lab", "reconstruct", str(capture), "--out", str(out),
                   *extra]
        result["options"] = " ".join(extra) or "(none)"
        result.update(measure(command, timeout=args.timeout, env=child_env()))
        metrics_file = out / "metrics.json"
        if result["exit_code"] == 0 and metrics_file.is_file():
            result["metrics"] = json.loads(metrics_file.read_text())
    if out.is_dir():
        result["files"] = {
            str(p.relative_to(out)): p.stat().st_size for p in sorted(out.rglob("*")) if p.is_file()
        }
    if not args.keep:
        shutil.rmtree(out, ignore_errors=True)
    return result


def solve_seconds(metrics: dict | None) -> float | None:
    """The solve's wall seconds of a ps-lab result (new layout, then the older keys)."""
    if not metrics:
        return None
    timings = metrics.get("timings", {})
    stage = timings.get("stages", {}).get("solve")
    if stage is not None:
        return float(stage["wall_seconds"])
    value = timings.get("solve_seconds", metrics.get("solve_seconds"))
    return None if value is None else float(value)


def _dig(mapping: dict, path: tuple[str, ...]):
    for key in path:
        if not isinstance(mapping, dict) or key not in mapping:
            return None
        mapping = mapping[key]
    return mapping


def stage_rows(metrics: dict | None, floor_steps: dict | None = None) -> list[dict]:
    """Per-stage rows of a result: stage, wall and CPU seconds, bytes, the floor's seconds.

    From ``metrics["timings"]["stages"]`` in :data:`STAGES` order (then any others), else from
    the flat keys of older results (CPU and bytes then unknown: None).
    """
    floor_steps = floor_steps or {}
    timings = (metrics or {}).get("timings", {})
    stages = timings.get("stages")
    rows = []
    if isinstance(stages, dict) and stages:
        names = [s for s in STAGES if s in stages] + [s for s in stages if s not in STAGES]
        for stage in names:
            entry = stages[stage]
            step = FLOOR_STEP.get(stage)
            rows.append({
                "stage": stage,
                "wall_seconds": entry.get("wall_seconds"),
                "cpu_seconds": entry.get("cpu_seconds"),
                "bytes": entry.get("bytes"),
                "floor_step": step,
                "floor_seconds": floor_steps.get(step),
            })
        return rows
    for label, path, step in LEGACY_STAGES:
        value = _dig(metrics or {}, path)
        if value is None:
            continue
        rows.append({"stage": label, "wall_seconds": float(value), "cpu_seconds": None,
                     "bytes": None, "floor_step": step, "floor_seconds": floor_steps.get(step)})
    return rows


def file_rows(metrics: dict | None, sizes: dict | None) -> list[dict]:
    """Per output file: bytes (on disk, else from metrics) and wall seconds (when recorded)."""
    files = (metrics or {}).get("timings", {}).get("files") or {}
    names = list(files) + [n for n in (sizes or {}) if n not in files]
    return [{
        "file": name,
        "bytes": (sizes or {}).get(name, files.get(name, {}).get("bytes")),
        "wall_seconds": files.get(name, {}).get("wall_seconds"),
    } for name in names]


# ---------------------------------------------------------------------------------------------
# targets


def check_targets(captures: list[dict]) -> list[dict]:
    """The issue's targets with the measured values: (target, measured, limit, passed or None)."""
    checks = []

    def add(target: str, value: float | None, limit: float, unit: str, failed: bool) -> None:
        # a run that failed fails its targets; one not run (or skipped) is "not measured"
        passed = False if failed else None if value is None else value <= limit
        checks.append({"target": target, "measured": value, "limit": limit, "unit": unit,
                       "passed": passed, "run_failed": failed})

    for entry in captures:
        name = entry["capture"]["name"]
        runs = entry["runs"]
        floor = entry["floor"]
        floor_wall = floor["wall_seconds"] if floor.get("ok") else None

        def ran(key: str) -> dict | None:
            run = runs.get(key)
            return None if run is None or "skipped" in run else run

        def bad(run: dict | None) -> bool:
            return run is not None and run.get("exit_code") != 0

        default, sbl, ls = ran("default"), ran("sbl"), ran("ls")
        for run, limit, what in ((default, 15.0, "default"),
                                 (ls, 3.0, "--method ls --appearance none")):
            if run is None:
                continue
            value = run["wall_seconds"] / floor_wall if floor_wall and not bad(run) else None
            add(f"{name}: {what} <= {limit:g}x floor", value, limit, "x", bad(run))
        if default is not None and sbl is not None:
            a, b = solve_seconds(default.get("metrics")), solve_seconds(sbl.get("metrics"))
            value = a / b if a is not None and b else None
            add(f"{name}: default solve <= 2x SBL's solve", value, 2.0, "x",
                bad(default) or bad(sbl))
        kind = entry["capture"]["kind"]
        if kind == "jpeg":
            measured = [r for r in (ran(k) for k in RUNS if RUNS[k][1] is not None) if r]
            if measured:
                peak = max(r["peak_rss"] for r in measured) / GIB
                add(f"{name}: peak RSS of every ps-lab run <= 4 GiB", peak, 4.0, "GiB", False)
        if kind == "png16" and default is not None:
            value = None if bad(default) else default["wall_seconds"]
            add(f"{name}: default <= 300 s", value, 300.0, "s", bad(default))
    return checks


# ---------------------------------------------------------------------------------------------
# report


def machine() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "usable_cores": usable,
        "memory_bytes": os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "openblas_coretype": os.environ.get("OPENBLAS_CORETYPE"),
        "load_average": list(os.getloadavg()),
    }


def _num(value, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _bytes(value) -> str:
    if value is None:
        return "-"
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if value >= size:
            return f"{value / size:.2f} {unit}"
    return f"{value} B"


def capture_line(capture: dict) -> str:
    made = f"made in {capture['generate_seconds']:.1f} s"
    made = f"reused, {made}" if capture["reused"] else made
    kind = ("8-bit sRGB JPEG q95" if capture["kind"] == "jpeg"
            else f"16-bit colour {capture['format'].upper()}")
    source = capture["source"]
    origin = ("synthetic render" if source == "synthetic"
              else f"{Path(source).parent.name}/{Path(source).name} upscaled "
                   f"{capture['scale']:.2f}x")
    notes = "".join(f"; {n}" for n in capture["notes"] if n != "synthetic render")
    return (f"**{capture['name']}**: {capture['width']} x {capture['height']} "
            f"({capture['width'] * capture['height'] / 1e6:.3g} MP) x {capture['lights']} lights, "
            f"{kind}, {origin} ({_bytes(capture['bytes'])} on disk, {made}){notes}.")


def runs_table(entry: dict) -> list[str]:
    floor = entry["floor"]
    floor_wall = floor["wall_seconds"] if floor.get("ok") else None
    lines = ["| run | options | wall s | CPU s | peak RSS GiB | x floor |",
             "|---|---|---:|---:|---:|---:|"]
    if floor.get("ok"):
        lines.append(f"| floor (numpy) | decode + grey + pinv | {floor_wall:.2f} | "
                     f"{floor['cpu_seconds']:.2f} | {floor['peak_rss'] / GIB:.2f} | 1.00 |")
    else:
        lines.append("| floor (numpy) | decode + grey + pinv | failed | - | - | - |")
    for run in entry["runs"].values():
        if "skipped" in run:
            lines.append(f"| {run['label']} | skipped: {run['skipped']} | - | - | - | - |")
            continue
        status = "" if run["exit_code"] == 0 else (
            " (timed out)" if run["timed_out"] else f" (exit {run['exit_code']})")
        ratio = (f"{run['wall_seconds'] / floor_wall:.1f}" if floor_wall and not status else "-")
        lines.append(f"| {run['label']} | `{run['options']}` | {run['wall_seconds']:.2f}{status} | "
                     f"{run['cpu_seconds']:.2f} | {run['peak_rss'] / GIB:.2f} | {ratio} |")
    return lines


def stages_table(entry: dict, run_name: str = "default") -> list[str]:
    run = entry["runs"].get(run_name)
    if run is None or "skipped" in run:
        return [f"(no per-stage figures: no {run_name} run)"]
    if "metrics" not in run:
        return [f"(no per-stage figures: the {run_name} run has no metrics.json)"]
    floor = entry["floor"]
    rows = stage_rows(run["metrics"], floor.get("steps"))
    lines = ["| stage | wall s | CPU s | bytes moved | floor step | floor s |",
             "|---|---:|---:|---:|---|---:|"]
    for row in rows:
        lines.append(f"| {row['stage']} | {_num(row['wall_seconds'], 2)} | "
                     f"{_num(row['cpu_seconds'], 2)} | {_bytes(row['bytes'])} | "
                     f"{row['floor_step'] or ''} | {_num(row['floor_seconds'], 2)} |")
    accounted = sum(r["wall_seconds"] or 0.0 for r in rows if not r["stage"].startswith(" "))
    rest = run["wall_seconds"] - accounted
    if rows and rest >= 0:
        lines.append(f"| rest (process start, imports: wall - stages) | {rest:.2f} | | | | |")
    lines += ["", "| output file | bytes | wall s |", "|---|---:|---:|"]
    for row in file_rows(run["metrics"], run.get("files")):
        lines.append(f"| {row['file']} | {_bytes(row['bytes'])} | {_num(row['wall_seconds'], 2)} |")
    return lines


def report(results: dict) -> str:
    """The whole result as Markdown: per capture, the runs and the default's stages; machine."""
    m = results["machine"]
    lines = []
    for entry in results["captures"]:
        floor = entry["floor"]
        lines += [capture_line(entry["capture"]), ""]
        lines += runs_table(entry)
        if floor.get("ok"):
            steps = floor["steps"]
            walls = ", ".join(f"{w:.2f}" for w in floor["walls_before"])
            after = ", ".join(f"{w:.2f}" for w in floor["walls_after"])
            lines += ["", f"Floor: median of {len(floor['walls_before'] + floor['walls_after'])} "
                      f"runs (before the ps-lab runs: {walls} s; after: {after} s); in the "
                      f"script: import {steps['import']:.2f} s, decode {steps['decode']:.2f} s, "
                      f"grey {steps['grey']:.2f} s, least squares {steps['solve']:.2f} s "
                      f"({_bytes(floor['bytes_decoded'])} decoded)."]
        lines += ["", f"Per stage, {entry['capture']['name']} default run:", ""]
        lines += stages_table(entry)
        lines.append("")
    if results.get("checks") is not None:
        lines += ["| target | measured | result |", "|---|---:|---|"]
        for c in results["checks"]:
            verdict = {True: "pass", False: "FAIL", None: "not measured"}[c["passed"]]
            verdict += " (the run failed)" if c["run_failed"] else ""
            measured = "-" if c["measured"] is None else f"{c['measured']:.2f} {c['unit']}"
            lines.append(f"| {c['target']} | {measured} | {verdict} |")
        lines.append("")
    lines.append(
        f"Machine: {m['cpu']}, {m['cores']} cores ({m['usable_cores']} usable), "
        f"{m['memory_bytes'] / GIB:.0f} GiB RAM, Python {m['python']}, numpy {m['numpy']}, "
        f"OpenCV {m['opencv']}"
        + (f", OPENBLAS_CORETYPE={m['openblas_coretype']}" if m["openblas_coretype"] else "")
        + f"; load average (1 min) at start {m['load_average'][0]:.2f}"
        + (f", at end {m['load_average_end'][0]:.2f}" if "load_average_end" in m else "") + "."
        + (f" Kernel warm-up before the runs: {results['warm_up_seconds']:.1f} s."
           if results.get("warm_up_seconds") is not None else "")
    )
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def run_benchmark(args) -> dict:
    """Make the captures, warm the kernels, then per capture: floor, runs, floor again."""
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    results = {"machine": machine(), "arguments": {
        k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}}
    runs = [r for r in args.runs.split(",") if r]
    problem = prepare_relightlab(args.relightlab) if "relightlab" in runs else None
    if args.warm_up:  # with an empty numba cache the first run would compile its kernels
        warm = measure([sys.executable, "-m", "ps_lab.reconstruct._warm_up"], env=child_env())
        results["warm_up_seconds"] = warm["wall_seconds"]
    results["captures"] = []
    for name in args.captures.split(","):
        plan = capture_plan(name, args.megapixels, args.lights, args.synthetic, args.png16_format)
        say(f"{name}: {plan['width']} x {plan['height']} x {plan['lights']} "
            f"({'synthetic' if plan['source'] == 'synthetic' else plan['source']}) ...")
        record = make_capture(work, plan)
        before = []
        for i in range(args.repeats):
            before.append(run_floor(record, work, args.timeout))
            say(f"  floor {i + 1}/{args.repeats}: {before[-1]['wall_seconds']:.2f} s")
        done = {}
        for run in runs:
            done[run] = run_one(run, record, work, args, problem)
            result = done[run]
            say(f"  {run}: " + (result["skipped"] if "skipped" in result else
                                f"{result['wall_seconds']:.2f} s, exit {result['exit_code']}"))
            if result.get("exit_code") not in (0, None):
                say("    " + "\n    ".join(result["stderr_tail"]))
        after = []
        for i in range(args.repeats):
            after.append(run_floor(record, work, args.timeout))
            say(f"  floor after {i + 1}/{args.repeats}: {after[-1]['wall_seconds']:.2f} s")
        results["captures"].append(
            {"capture": record, "floor": floor_summary(before, after), "runs": done})
    results["machine"]["load_average_end"] = list(os.getloadavg())
    if args.check:
        results["checks"] = check_targets(results["captures"])
    return results


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--captures", default=None,
                        help=f"comma-separated, of {', '.join(CAPTURES)} (default: all)")
    parser.add_argument("--runs", default=None,
                        help=f"comma-separated, of {', '.join(RUNS)} (default: {ALL_RUNS})")
    parser.add_argument("--quick", action="store_true",
                        help=f"jpeg4 only, --repeats 1, runs {QUICK_RUNS}")
    parser.add_argument("--megapixels", type=float, default=None,
                        help="resize every capture to about this size (default: 4 and 12 MP)")
    parser.add_argument("--lights", type=int, default=None, help="lights of every capture")
    parser.add_argument("--repeats", type=int, default=None,
                        help="floor runs before and again after the ps-lab runs (default 3)")
    parser.add_argument("--memory-budget", default=None, help="passed to ps-lab reconstruct")
    parser.add_argument("--timeout", type=float, default=None, help="stop a run after S seconds")
    parser.add_argument("--work", type=Path, default=DEFAULT_WORK,
                        help="captures (kept and reused) and outputs")
    parser.add_argument("--synthetic", action="store_true",
                        help="render the captures even when the shared data is there")
    parser.add_argument("--png16-format", default="png", choices=("png", "tiff"))
    parser.add_argument("--relightlab", type=Path, default=RELIGHTLAB,
                        help="folder of RelightLab's relight-cli")
    parser.add_argument("--keep", action="store_true", help="keep each run's output folder")
    parser.add_argument("--no-warm-up", dest="warm_up", action="store_false",
                        help="skip compiling (or loading) the numba kernels before the runs")
    parser.add_argument("--check", action="store_true", help="exit 1 if a target fails")
    parser.add_argument("--json", type=Path, default=None, help="write everything here")
    parser.add_argument("--markdown", type=Path, default=None, help="also write the report here")
    args = parser.parse_args(argv)
    args.captures = args.captures or ("jpeg4" if args.quick else ",".join(CAPTURES))
    args.runs = args.runs or (QUICK_RUNS if args.quick else ALL_RUNS)
    args.repeats = args.repeats or (1 if args.quick else 3)
    for name in args.captures.split(","):
        if name not in CAPTURES:
            parser.error(f"--captures: unknown capture {name!r} (known: {', '.join(CAPTURES)})")
    for name in args.runs.split(","):
        if name not in RUNS:
            parser.error(f"--runs: unknown run {name!r} (known: {', '.join(RUNS)})")
    if args.lights is not None and args.lights < 4:
        parser.error("--lights must be at least 4")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    results = run_benchmark(args)
    text = report(results)
    print(text)
    if args.markdown:
        args.markdown.write_text(text + "\n")
    if args.json:
        args.json.write_text(json.dumps(_json_safe(results), indent=1, allow_nan=False) + "\n")
    if args.check and any(c["passed"] is False for c in results["checks"]):
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
