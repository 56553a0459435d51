"""Loading the compiled kernels into a process before the solve (``ps-lab reconstruct``)."""

from __future__ import annotations

import threading

import numpy as np

from ._kernels import l1_tile, sbl_tile
from ._pl_kernels import pl_tile


def warm_up(method: str) -> None:
    """Load ``method``'s compiled kernels (and L1's, used by the noise estimate) into the process.

    The first call of any numba kernel in a process initialises the compiler and loads the cached
    machine code (0.25 s on a quiet machine, over 1 s under load), although nothing is compiled.
    Running it on a one-pixel input while the images are read takes that cost off the solve.
    """
    if method not in ("l1", "sbl", "plls", "plsbl", "auto"):
        return
    lights = np.eye(3)
    y = np.ones((1, 3))
    w = np.ones((1, 3))
    if method != "plls":
        l1_tile(y, w, lights, max_iter=1, tol=1.0, delta=1e-6, outlier_threshold=np.inf)
    if method == "sbl":
        sbl_tile(y, w, lights, lam=1e-6, sigma_x2=1e6, max_iter=1, tol=1.0, gamma_floor=1e-10,
                 gamma_start=1.0, outlier_threshold=np.inf)
    elif method in ("plls", "plsbl", "auto"):
        pl_tile(y, w, lights, segments=3, lam=1e-6, max_iter=1, choose=method == "auto")


def start_warm_up(method: str) -> threading.Thread:
    """Run :func:`warm_up` on a daemon thread (join it before solving); see there for why."""
    thread = threading.Thread(target=warm_up, args=(method,), name="ps-lab-kernel-warm-up",
                              daemon=True)
    thread.start()
    return thread
