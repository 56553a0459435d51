"""Compiling and loading the numba kernels ahead of the solve, and saying so while it compiles.

The tile kernels are compiled by numba on their first call and the machine code is cached on disk
(``__pycache__`` next to the sources, or ``NUMBA_CACHE_DIR``; where the package folder is not
writable numba falls back to the user's cache folder, ``~/.cache/numba``). An entry is keyed by
the source file's path, size and mtime, the argument types, and the CPU name and features. With an
empty cache the first ``ps-lab reconstruct`` compiles for about a minute of CPU time (mostly the
piecewise-linear kernel, whose helpers are inlined into it), so:

- the install (``make demo``/``make test``, or ``python -m ps_lab.reconstruct._warm_up`` after a
  ``pip install``) fills the cache with every kernel, for every argument type the library passes
  (one per kernel: the tile wrappers hand over C-contiguous, writable float64 arrays);
- a compile that still happens (a new CPU, an edited kernel) announces itself: one line on stderr
  when stderr is a terminal, else an info log line (``ps-lab -v``), with its rough cost;
- the test suite warms up once before its first test (tests/conftest.py), so that no test pays
  the compile against its timeout.

See docs/results.md (Speed: the first run) for the measurements.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba.core import event

from ps_lab.io.coding import Coding, float_coding, observe_block, observe_rule

from ._kernels import TileResult, l1_tile, sbl_tile
from ._near_kernels import l1_tile_pp, sbl_tile_pp
from ._colour import colour_albedo
from ._auto import last_choice
from ._pl_kernels import pl_tile
from .methods import SOLVERS
from ._tiles import _prepare_tile, _store_tile, ls_tiles

log = logging.getLogger(__name__)

#: CPU seconds to compile each kernel (thread CPU time on a Xeon, Emerald Rapids, numba 0.68;
#: benchmarks/first_run.py measures them), for the "~N s" of the compile line.
COMPILE_SECONDS = {
    "_ls_direct": 0.5,
    "_l1_kernel": 2.0,
    "_sbl_kernel": 2.0,
    "_pl_kernel": 34.0,
    "_last_choice_kernel": 2.0,
    "_l1_kernel_pp": 1.5,
    "_sbl_kernel_pp": 1.6,
    "_march_point_lights": 1.0,
    "_observe": 1.5,
    "_prepare_kernel": 1.0,
    "_store_kernel": 0.5,
    "_far_kernel": 2.5,
    "_near_kernel": 2.5,
    "_masked_kernel": 1.0,
    "_ps_kernel": 8.0,  # per dtype (float32, float64); 10 and 6 s on the AMD EPYC (Zen 4)
}


def _one_pixel() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.ones((1, 3)), np.ones((1, 3)), np.eye(3)


def _ls() -> None:
    _, _, lights = _one_pixel()
    for dtype in (np.float32, np.float64):  # least squares straight from the observations
        ls_tiles(np.ones((3, 1), dtype), np.ones((3, 1), bool), lights, 0, 1, np.zeros((1, 3)),
                 np.zeros(1), np.zeros(1, np.int64))


def _l1() -> None:
    y, w, lights = _one_pixel()
    l1_tile(y, w, lights, max_iter=1, tol=1.0, delta=1e-6, outlier_threshold=np.inf)


def _sbl() -> None:
    y, w, lights = _one_pixel()
    sbl_tile(y, w, lights, lam=1e-6, sigma_x2=1e6, max_iter=1, tol=1.0, gamma_floor=1e-10,
             gamma_start=1.0, outlier_threshold=np.inf)


def _pl(choose: bool) -> Callable[[], None]:
    def run() -> None:
        y, w, lights = _one_pixel()
        pl_tile(y, w, lights, segments=3, lam=1e-6, max_iter=1, choose=choose)
        if choose:  # the default's last choice among LS, SBL and PL-SBL
            last_choice(y, w, lights, np.ones((1, 1)), np.ones((1, 3)), w, np.ones((1, 3)),
                        np.zeros(1, bool))
    return run


def _near() -> None:
    y, w, lights = _one_pixel()
    per_pixel = np.ascontiguousarray(lights[None])
    l1_tile_pp(y, w, per_pixel, max_iter=1, tol=1.0, delta=1e-6, outlier_threshold=np.inf)
    sbl_tile_pp(y, w, per_pixel, lam=1e-6, sigma_x2=1e6, max_iter=1, tol=1.0,
                gamma_floor=1e-10, gamma_start=1.0, outlier_threshold=np.inf)


def _render() -> None:
    # the near-light renderer's shadow march (ps-lab simulate, the simulated camera)
    from ps_lab.render.near_shading import _march_point_lights

    one = np.zeros(1)
    _march_point_lights(np.zeros((2, 2)), np.ones((2, 2), bool), np.ones((1, 2, 2), bool), one,
                        one, one + 1.0, 0.0, 0.0, np.zeros((1, 2, 2), bool))


def _tiles() -> None:
    # the tile ends of every solver, on the store's float32 observations and on float64 ones
    for dtype in (np.float32, np.float64):
        obs = np.ones((3, 1), dtype)
        y, w, scale, ok = _prepare_tile(obs, np.ones((3, 1), bool), np.eye(3), 0, 1)
    res = TileResult(np.ones((1, 3)), np.zeros((1, 3), bool), np.ones(1, np.int64))
    _store_tile(0, 1, y, w, scale, ok, res, np.eye(3), np.zeros((1, 3)), np.zeros(1),
                np.zeros((3, 1), bool), np.zeros(1, np.int64), None)


def _store() -> None:
    # the observation store's read of 8- and 16-bit codes and of float values
    rule = observe_rule(np.ones((1, 3)))
    for dtype in (np.uint8, np.uint16):
        coding = Coding(np.dtype(dtype), 3, np.zeros((2, 3), np.float32), 1)
        observe_block(np.zeros((1, 1, 3), dtype), None, coding, rule, np.zeros(1, np.int64), True)
    observe_block(np.zeros((1, 1, 3), np.float32), np.zeros((1, 1), bool), float_coding(3), rule,
                  np.zeros(1, np.int64), True)


def _colour() -> None:
    # the colour albedo of colour frames: directional lights and per-pixel light vectors
    normals, inliers = np.array([[0.0, 0.0, 1.0]]), np.ones((3, 1), bool)
    observations = np.ones((3, 1, 3), np.float32)
    colour_albedo(normals, inliers, observations, np.eye(3))
    per_pixel = np.ascontiguousarray(np.broadcast_to(np.eye(3)[None], (1, 3, 3)))
    colour_albedo(normals, inliers, observations, per_pixel.transpose(1, 0, 2))


def _appearance() -> None:
    # the ps appearance fit (ps-lab reconstruct --appearance ps): float32 from the observation
    # store, float64 from whole arrays (fit_appearance: ps-lab bench relight)
    from ps_lab.appearance.blocks import fit_block

    for dtype in (np.float32, np.float64):
        fit_block("ps", np.ones((3, 1, 3), dtype), np.eye(3), normals=np.array([[0.0, 0.0, 1.0]]),
                  albedo=np.ones(1))
    # the smoothers' (rbf, bln, gp) least squares where observations are missing
    missing = np.ones((3, 1, 1), np.float32)
    missing[0] = np.nan
    fit_block("rbf", missing, np.eye(3), rbf_basis=np.eye(3)[None, :, :2])


@dataclass(frozen=True)
class Group:
    """Kernels warmed together: a label for the progress lines and the call that warms them."""

    label: str
    run: Callable[[], None]


#: Every cached kernel of the package, by the solver methods that use it.
GROUPS = {
    "store": Group("observation store", _store),
    "tiles": Group("tile kernels", _tiles),
    "colour": Group("colour albedo", _colour),
    "ls": Group("least-squares kernel", _ls),
    "l1": Group("L1 kernel", _l1),
    "sbl": Group("SBL kernel", _sbl),
    "pl": Group("piecewise-linear kernel", _pl(choose=True)),
    "near": Group("near-light kernels", _near),
    "render": Group("renderer's shadow march", _render),
    "appearance": Group("appearance kernel", _appearance),
}
#: The groups ``ps-lab reconstruct --method M`` needs: the solver table's ``warm_up``.
METHOD_GROUPS = {row.name: row.warm_up for row in SOLVERS}


def _estimate(name: str) -> int:
    """Rough wall seconds to compile kernel ``name`` now: its CPU seconds, stretched by the load.

    The stretch is ``(load / cores) ** 0.6`` (at least 1): on the 2-core development machine at a
    load average of 7-14 the compiles took 3-3.5x their CPU time, not the 4-7x that the load
    alone suggests.
    """
    cpus = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except OSError:  # not on this platform
        load = 0.0
    return max(1, round(COMPILE_SECONDS.get(name, 5.0) * max(1.0, load / cpus) ** 0.6))


def _announce(line: str) -> None:
    """A progress line: printed on stderr when it is a terminal, else an info log line (``-v``)."""
    if sys.stderr.isatty():
        print(line, file=sys.stderr, flush=True)
    else:
        log.info(line)


class CompileNotice(event.Listener):
    """Says when numba compiles a kernel (a cache miss) and how long it took.

    Numba fires ``numba:compile`` only for a signature not found in its cache, around the
    compile; a kernel compiled inside another's compile (a helper that is not inlined) is part of
    the outer one's line.
    """

    def __init__(self, say: Callable[[str], None] = _announce):
        self.say = say
        self.compiled: list[tuple[str, float, float]] = []  # name, wall and CPU seconds
        self._local = threading.local()

    def on_start(self, ev: event.Event) -> None:
        """A compile begins: say so (the outermost one of this thread)."""
        depth = getattr(self._local, "depth", 0)
        self._local.depth = depth + 1
        if depth == 0:
            func = getattr((ev.data or {}).get("dispatcher"), "py_func", None)
            name = getattr(func, "__name__", "kernel")
            self._local.started = (name, time.perf_counter(), time.thread_time())
            self.say(f"compiling solver kernels (first run only, ~{_estimate(name)} s): {name}…")

    def on_end(self, ev: event.Event) -> None:
        """A compile ends: log its time (``-v``)."""
        depth = getattr(self._local, "depth", 0)
        if depth <= 0:  # began before this listener was installed
            return
        self._local.depth = depth - 1
        if depth == 1:
            name, started, cpu = self._local.started
            seconds = time.perf_counter() - started
            self.compiled.append((name, seconds, time.thread_time() - cpu))
            log.info("compiled %s in %.1f s (cached for the next run)", name, seconds)


_NOTICE: CompileNotice | None = None
_NOTICE_LOCK = threading.Lock()


def announce_compiles() -> None:
    """From now on, announce in this process every kernel compile (:class:`CompileNotice`)."""
    global _NOTICE
    with _NOTICE_LOCK:
        if _NOTICE is None:
            _NOTICE = CompileNotice()
            event.register("numba:compile", _NOTICE)


def warm_up(method: str) -> None:
    """Load ``method``'s compiled kernels (and L1's, used by the noise estimate) into the process.

    The first call of any numba kernel in a process initialises the compiler and loads the cached
    machine code (0.25 s on a quiet machine, over 1 s under load), although nothing is compiled.
    Running it on a one-pixel input while the images are read takes that cost off the solve. With
    an empty cache this compiles them, announced (:func:`announce_compiles`).
    """
    for key in METHOD_GROUPS.get(method, ()):
        GROUPS[key].run()


def start_warm_up(method: str) -> threading.Thread:
    """Run :func:`warm_up` on a daemon thread (join it before solving); see there for why."""
    announce_compiles()
    thread = threading.Thread(target=warm_up, args=(method,), name="ps-lab-kernel-warm-up",
                              daemon=True)
    thread.start()
    return thread


def warm_all(say: Callable[[str], None] | None = None) -> list[tuple[str, float, float]]:
    """Compile (or load) every cached kernel of the package for this CPU; return what compiled.

    ``say`` gets the progress lines (default: stderr). Returns ``(kernel, wall seconds, CPU
    seconds)`` per kernel compiled; empty when the cache already held them all.
    """
    say = say if say is not None else (lambda line: print(line, file=sys.stderr, flush=True))
    notice = CompileNotice(say)
    with event.install_listener("numba:compile", notice):
        for group in GROUPS.values():
            group.run()
    return notice.compiled


def cache_folder() -> str:
    """Where numba keeps this package's kernels (for the messages; '?' if numba hides it)."""
    from ._kernels import _l1_kernel

    try:
        return str(_l1_kernel._cache._cache_path)
    except AttributeError:
        return "?"


def main() -> None:
    """``python -m ps_lab.reconstruct._warm_up``: fill numba's cache (the install step)."""
    started = time.perf_counter()
    compiled = warm_all()
    seconds = time.perf_counter() - started
    if compiled:
        print(f"compiled {len(compiled)} solver kernels in {seconds:.0f} s, cached in "
              f"{cache_folder()}", file=sys.stderr)
    else:
        print(f"solver kernels already compiled (cache: {cache_folder()}; loaded in "
              f"{seconds:.1f} s)", file=sys.stderr)


if __name__ == "__main__":
    main()
