"""The default method ``auto`` over tiles: SBL, a score test, PL-SBL where SBL fails it.

Two passes (docs/solvers.md, "The default `auto`", rule 0):

1. every pixel is solved by SBL (its own kernel, iterations and tolerance) and its fit is tested
   against the bent response of the PL model by a robust score test
   (:func:`._pl_algebra._bend_score`: chi^2 with ``K - 1`` degrees of freedom), weighted by the
   noise variance of the larger model (the PL model's noise, never below ``GATE_NOISE``): a
   test of fit measures the smaller model's misfit against the pure error, not against its own
   residuals, which hold that misfit. The PL noise is not known yet, so this pass tests with its
   lower bound (the noise floor alone): a pixel that passes it passes the real test too;
2. only if some pixels fail, the PL model's noise is measured on a sample of *them*
   (:func:`._solve.pl_noise_level`), and those pixels are tested again at that noise and,
   where they still fail, fitted by PL-SBL and compared with SBL by their left-out residuals
   (:func:`._pl_kernels._choose`). SBL's fit of the first pass is reused, not repeated, and so
   are the test's break points (order statistics of SBL's fitted values: ``gate_breaks``).
"""

from __future__ import annotations

import numpy as np

from . import _pl_kernels
from ._pl_algebra import GATE_NOISE, gate_variance
from ._tiles import _finish_solution, _prepare_tile, _store_tile, sbl_lambda


def auto_tiles(obs, lights, usable, params, used, starts, tile, mapper, progress, pl_noise_of):
    """Solve the tiles starting at ``starts`` with ``auto`` (module docstring); the Solution.

    ``pl_noise_of(columns)``: the PL model's noise on those pixels (``_solve.pl_noise_level``).
    """
    n, p = obs.shape
    per_pixel = params["lam"] is None
    floor, factors = params.get("noise_floor"), params.get("light_noise")
    kernel_params = {k: v for k, v in params.items()
                     if k not in ("noise_floor", "light_noise", "noise_sigma_pl", "lam",
                                  "sbl_max_iter")}
    sbl_max_iter = params["sbl_max_iter"]
    sigma_pl = params.get("noise_sigma_pl")

    def noise(scale, sigma):
        return sbl_lambda(scale, sigma, floor, factors) if per_pixel else params["lam"]

    def first(a):
        b = min(a + tile, p)
        y, w, scale, ok = _prepare_tile(obs, usable, lights, a, b)
        lower = gate_variance(noise(scale, 0.0 if sigma_pl is None else sigma_pl))
        res = _pl_kernels.pl_tile(y, w, lights, choose=True, sbl_max_iter=sbl_max_iter,
                                  lam=noise(scale, used.get("noise_sigma", 0.0)),
                                  lam_test=lower, stage="sbl", **kernel_params)
        return a, b, y, w, scale, ok, res

    tiles = list(mapper(first, starts))
    failing = [np.flatnonzero(t[5] & (t[6].gate > 0.0)) for t in tiles]
    count = int(sum(f.size for f in failing))
    used["gate_false_alarm"] = _pl_kernels.GATE_FALSE_ALARM
    used["gate_noise"] = GATE_NOISE
    used["pixels_failing_lambertian_test"] = count
    if count and sigma_pl is None and per_pixel:
        columns = np.concatenate([t[0] + f for t, f in zip(tiles, failing, strict=True)])
        sigma_pl = pl_noise_of(columns)
    if sigma_pl is not None:
        used["noise_sigma_pl"] = float(sigma_pl)
    elif per_pixel:
        used["noise_sigma_pl"] = None  # not measured: every pixel kept the Lambertian model

    normals = np.zeros((p, 3))
    albedo = np.zeros(p)
    outliers = np.zeros((n, p), bool)
    iterations = np.zeros(p, np.int64)
    segments = np.zeros(p, np.int64)

    def second(job):
        (a, b, y, w, scale, ok, res), rows = job
        if rows.size:
            part = _pl_kernels.PLTileResult(res.x[rows], res.outliers[rows],
                                            res.iterations[rows], res.segments[rows],
                                            sbl_weights=res.sbl_weights[rows],
                                            gate_breaks=res.gate_breaks[rows])
            lam = noise(scale[rows], used.get("noise_sigma", 0.0))
            lam_pl = noise(scale[rows], sigma_pl) if per_pixel else None
            out = _pl_kernels.pl_tile(y[rows], w[rows], lights, choose=True,
                                      sbl_max_iter=sbl_max_iter, lam=lam, lam_pl=lam_pl,
                                      lam_test=gate_variance(lam if lam_pl is None else lam_pl),
                                      stage="pl", sbl_fit=part, **kernel_params)
            res.x[rows], res.outliers[rows] = out.x, out.outliers
            res.iterations[rows], res.segments[rows] = out.iterations, out.segments
        _store_tile(a, b, y, w, scale, ok, res, lights, normals, albedo, outliers, iterations,
                    segments)
        return b - a

    for done in mapper(second, list(zip(tiles, failing, strict=True))):
        if progress is not None:
            progress(done)
    return _finish_solution(used, normals, albedo, outliers, iterations, segments)
