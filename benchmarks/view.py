"""Viewer benchmark: a 12 MP result in ``ps-lab view``, relit in headless Chromium.

Writes a synthetic result folder (normals of a bumpy dome and an albedo ramp, 4000 x 3000 by
default), starts ``ps-lab view --no-browser`` on it, loads the page in headless Chromium (WebGL on
SwiftShader, the CPU renderer: a GPU browser is much faster) and reports

- ``serve_ready_s``: from the command's start to its address line (reading the result and
  building the tiled pyramid);
- ``first_picture_s``: from navigation to the first relit picture (the one-tile top level);
- ``refined_s``: until every tile the view needs at full zoom-to-fit is drawn;
- ``full_frame_ms_fit``: the interval between full-resolution frames while the light moves, as
  the page measures it to choose its reduced resolution;
- ``moving_frame_ms``: per relit frame while the light moves (60 light positions, each awaited
  until drawn, then ``gl.finish``), at fit and at 1:1 zoom, with the page's reduction.

Usage::

    python benchmarks/view.py [--width 4000] [--height 3000] [--markdown FILE]
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.helpers.browser import Browser, find_chromium  # noqa: E402


def write_result(folder: Path, width: int, height: int) -> None:
    """A result folder with unit normals of a dome with ripples, and an albedo ramp."""
    folder.mkdir(parents=True, exist_ok=True)
    normals = np.lib.format.open_memmap(folder / "normals.npy", "w+", np.float32, (height, width, 3))
    albedo = np.lib.format.open_memmap(folder / "albedo.npy", "w+", np.float32, (height, width))
    x = (np.arange(width) - width / 2) / (0.45 * min(width, height))
    for start in range(0, height, 256):
        y = ((np.arange(start, min(start + 256, height)) - height / 2) / (0.45 * min(width, height)))
        xx, yy = np.meshgrid(x, y)
        r2 = xx**2 + yy**2
        inside = r2 < 1
        gx = -xx / np.sqrt(np.maximum(1 - r2, 1e-3)) + 0.3 * np.cos(40 * xx)
        gy = -yy / np.sqrt(np.maximum(1 - r2, 1e-3)) + 0.3 * np.sin(30 * yy)
        n = np.stack([-gx, gy, np.ones_like(gx)], axis=-1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        n[~inside] = 0
        normals[start : start + len(y)] = n
        albedo[start : start + len(y)] = np.where(inside, 0.4 + 0.5 * (xx + 1) / 2, 0)
    normals.flush()
    albedo.flush()
    (folder / "metrics.json").write_text(json.dumps({"method": "synthetic"}))


FRAMES_JS = """
(async () => {
  const canvas = document.getElementById('gl');
  const gl = canvas.getContext('webgl2');
  const next = () => new Promise((resolve) => requestAnimationFrame(() => resolve()));
  await next();
  const started = performance.now();
  for (let k = 0; k < 60; k++) {
    const a = (k / 60) * 2 * Math.PI;
    psView.setLight([0.6 * Math.cos(a), 0.6 * Math.sin(a), 0.8]);
    const frames = psView.stats.frames;
    while (psView.stats.frames === frames) await next();
    gl.finish();
  }
  return (performance.now() - started) / 60;
})()
"""


def main() -> None:
    """Run the benchmark and print (and optionally write) its table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=4000)
    parser.add_argument("--height", type=int, default=3000)
    parser.add_argument("--markdown", type=Path, default=None)
    args = parser.parse_args()
    executable = find_chromium()
    if executable is None:
        sys.exit("no Chromium installed (apt-get install chromium)")
    with tempfile.TemporaryDirectory() as tmp:
        result = Path(tmp) / "result"
        write_result(result, args.width, args.height)
        started = time.perf_counter()
        server = subprocess.Popen(
            [sys.executable, "-m", "ps_lab", "view", str(result), "--no-browser"],
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            line = server.stdout.readline()
            ready = time.perf_counter() - started
            url = re.search(r"http://\S+/", line).group(0)
            with Browser(executable, width=1400, height=900) as browser:
                opened = time.perf_counter()
                browser.open(url, timeout=120)
                browser.wait_for("psView.stats.tilesDrawn > 0", timeout=120)
                first = time.perf_counter() - opened
                browser.wait_for("psView.idle()", timeout=300)
                refined = time.perf_counter() - opened
                fit_ms = browser.evaluate(FRAMES_JS, timeout=300)
                fit_stats = browser.evaluate("JSON.stringify(psView.stats)")
                browser.wait_for("psView.idle()", timeout=300)
                full_ms = browser.evaluate("psView.stats.fullMs")
                browser.evaluate("psView.pixelScale(0, 1)")
                browser.wait_for("psView.idle()", timeout=300)
                one_ms = browser.evaluate(FRAMES_JS, timeout=300)
                tiles = browser.evaluate("psView.stats.tilesLoaded")
        finally:
            server.terminate()
            server.wait(timeout=10)
    rows = {
        "image": f"{args.width} x {args.height} ({args.width * args.height / 1e6:.1f} MP)",
        "serve_ready_s": round(ready, 2),
        "first_picture_s": round(first, 2),
        "refined_s": round(refined, 2),
        "full_frame_ms_fit": round(full_ms, 1),
        "moving_frame_ms_fit": round(fit_ms, 1),
        "moving_frame_ms_1to1": round(one_ms, 1),
        "tiles_loaded": tiles,
    }
    table = "| " + " | ".join(rows) + " |\n|" + "---|" * len(rows) + "\n| "
    table += " | ".join(str(v) for v in rows.values()) + " |\n"
    print(table)
    print("stats while moving at fit:", fit_stats)
    if args.markdown is not None:
        args.markdown.write_text(table)


if __name__ == "__main__":
    main()
