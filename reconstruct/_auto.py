"""The default method ``auto`` over tiles: SBL, a score test, PL-SBL where SBL fails it, then a
last choice between SBL and least squares.

Two passes (docs/solvers.md, "The default `auto`", rule 0):

1. every pixel is solved by SBL (its own kernel, iterations and tolerance) and its fit is tested
   against the bent response of the PL model by a robust score test
   (:func:`._pl_model._bend_score`: chi^2 with ``K - 1`` degrees of freedom), weighted by the
   noise variance of the larger model (the PL model's noise, never below ``GATE_NOISE``): a
   test of fit measures the smaller model's misfit against the pure error, not against its own
   residuals, which hold that misfit. The PL noise is not known yet, so this pass tests with its
   lower bound (the noise floor alone): a pixel that passes it passes the real test too;
2. only if some pixels fail, the PL model's noise is measured on a sample of *them*
   (:func:`._noise.pl_noise_level`), and those pixels are tested again at that noise and,
   where they still fail, fitted by PL-SBL and compared with SBL by their left-out residuals
   (:func:`._pl_model._choose`). SBL's fit of the first pass is reused, not repeated, and so
   are the test's break points (order statistics of SBL's fitted values: ``gate_breaks``).
   Then every pixel's SBL fit is compared with least squares (:func:`last_choice`: truncated
   left-out residuals, both in closed form), and LS is kept where it predicts better by more
   than one standard error.

Not with lights in rings of equal elevation (an RTI dome, :func:`light_rings`): PL-SBL's break
points are order statistics of the pixel's observations, and on a dome they fall inside a ring
(SynthRTI Object1: the first at the 16th of 48, inside the 18 lights at 10 degrees), so the
ring's brightest lights get another slope than the rest; a ring's lights differ only in azimuth,
and that variation is what carries the normal's tilt. PL-SBL was worse than SBL on 14 of the 17
SynthRTI Object1 collections, by up to 5 degrees (docs/results.md), and dropping the 10 degree
ring turned it around (Multi/material4: SBL 6.8, PL-SBL 4.4 deg), so the default keeps the
Lambertian models there. One albedo for every pixel, whichever model gave its normal: the
Lambertian-equivalent reflectance on the observations SBL keeps.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import _pl_kernels, _pl_model
from ._linalg import SINGULAR_REL_DET, inverse3
from ._pl_model import GATE_NOISE, gate_variance
from ._tiles import _finish_solution, _prepare_tile, _store_tile, sbl_lambda


def light_rings(lights: np.ndarray) -> float:
    """Share of the lights in rings of equal elevation (an RTI dome); 0 for scattered lights.

    Parameters
    ----------
    lights : ndarray of shape (n, 3)

    Returns
    -------
    float
        The share of the lights with at least ``RING_MIN_LIGHTS`` lights (itself included) within
        ``RING_TOLERANCE_DEG`` of its elevation (``asin(l_z / |l|)``). DiLiGenT's 96 lights on
        a plane grid: 0; SynthRTI's dome (5 rings): 1.
    """
    v = np.asarray(lights, dtype=np.float64)
    length = np.linalg.norm(v, axis=1)
    good = length > 0
    if not good.any():
        return 0.0
    elevation = np.sort(np.degrees(np.arcsin(np.clip(v[good, 2] / length[good], -1.0, 1.0))))
    near = (np.searchsorted(elevation, elevation + RING_TOLERANCE_DEG, side="right")
            - np.searchsorted(elevation, elevation - RING_TOLERANCE_DEG, side="left"))
    return float(np.count_nonzero(near >= RING_MIN_LIGHTS) / v.shape[0])


def auto_tiles(obs, lights, usable, params, used, starts, tile, mapper, progress, pl_noise_of):
    """Solve the tiles starting at ``starts`` with ``auto`` (module docstring); the Solution.

    ``pl_noise_of(columns)``: the PL model's noise on those pixels (``_noise.pl_noise_level``).
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
    rings = light_rings(lights)
    used["lights_in_rings"] = rings
    dome = rings >= DOME_SHARE  # PL-SBL is not used (module docstring)
    failing = [np.flatnonzero(t[5] & (t[6].gate > 0.0)) for t in tiles]
    count = int(sum(f.size for f in failing))
    used["gate_false_alarm"] = _pl_model.GATE_FALSE_ALARM
    used["gate_noise"] = GATE_NOISE
    used["pixels_failing_lambertian_test"] = count
    if dome:
        failing = [f[:0] for f in failing]
    if count and not dome and sigma_pl is None and per_pixel:
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

    per_model = np.zeros(len(MODELS), np.int64)

    def pl_stage(t, rows, z):
        """PL-SBL (and its choice against SBL at ``z`` standard errors) on rows of tile t."""
        a, b, y, w, scale, ok, res = t
        part = _pl_kernels.PLTileResult(res.x[rows], res.outliers[rows],
                                        res.iterations[rows], res.segments[rows],
                                        sbl_weights=res.sbl_weights[rows],
                                        gate_breaks=res.gate_breaks[rows])
        lam = noise(scale[rows], used.get("noise_sigma", 0.0))
        lam_pl = noise(scale[rows], sigma_pl) if per_pixel else None
        return _pl_kernels.pl_tile(y[rows], w[rows], lights, choose=True,
                                   sbl_max_iter=sbl_max_iter, lam=lam, lam_pl=lam_pl,
                                   lam_test=gate_variance(lam if lam_pl is None else lam_pl),
                                   stage="pl", sbl_fit=part, choice_z=z, **kernel_params)

    def second(job):
        (a, b, y, w, scale, ok, res), rows = job
        x_sbl, flags_sbl = res.x.copy(), res.outliers.copy()
        pl = np.zeros(b - a, bool)
        if rows.size:
            out = pl_stage((a, b, y, w, scale, ok, res), rows, PL_CHOICE_Z)
            res.x[rows], res.outliers[rows] = out.x, out.outliers
            res.iterations[rows], res.segments[rows] = out.iterations, out.segments
            pl[rows] = out.segments > 1
        lam = noise(scale, used.get("noise_sigma", 0.0))
        model, x = last_choice(y, w, lights, lam, x_sbl, res.sbl_weights, res.x, pl)
        res.x = x
        res.outliers = np.where((model == 2)[:, None], res.outliers,
                                flags_sbl & (model == 1)[:, None])
        res.segments = np.where(model == 2, res.segments, 1)
        per_model[:] += np.bincount(model[ok], minlength=len(MODELS))
        _store_tile(a, b, y, w, scale, ok, res, lights, normals, albedo, outliers, iterations,
                    segments, albedo_flags=flags_sbl, albedo_x=x_sbl if ALBEDO_FROM_SBL else None)
        return b - a

    for done in mapper(second, list(zip(tiles, failing, strict=True))):
        if progress is not None:
            progress(done)
    used["pixels_per_model"] = {name: int(c) for name, c in zip(MODELS, per_model, strict=True)}
    return _finish_solution(used, normals, albedo, outliers, iterations, segments)


# --- the last choice: least squares, SBL or PL-SBL, by truncated left-out residuals ----------

# Each left-out residual counts at most CHOICE_CLIP noise standard deviations (squared): an
# observation that a model calls corrupted costs it as much as any other gross miss, and no
# single observation decides between two models.
CHOICE_CLIP = 3.0
# Least squares replaces SBL (the incumbent: 3 unknowns each) only where it predicts better by
# more than this many standard errors of the paired gain (the one-standard-error rule, as in
# _pl_model._choose): with SBL preferred at no margin, LS took 4-6 % of DiLiGenT's pixels and
# cost goblet 0.2 deg.
CHOICE_Z = 1.0
# Models of the default's last choice (``Solution.params["pixels_per_model"]``).
MODELS = ("ls", "sbl", "plsbl")
# PL-SBL replaces SBL where its left-out gain exceeds this many standard errors
# (_pl_model._choose)
PL_CHOICE_Z = _pl_model.CHOICE_Z
# Lights in rings of equal elevation (an RTI dome: SynthRTI's 49 lights in 5 rings): a light is in
# a ring with RING_MIN_LIGHTS or more lights within RING_TOLERANCE_DEG of its elevation; with at
# least DOME_SHARE of the lights in rings, PL-SBL is not used (module docstring).
RING_TOLERANCE_DEG = 0.25
ALBEDO_FROM_SBL = True
RING_MIN_LIGHTS = 6
DOME_SHARE = 0.5


@njit(inline="always")
def _weighted_fit(y, v, lights):
    """Weighted least squares of one pixel, ``x = M^-1 sum v_i y_i l_i``, ``M = sum v_i l_i
    l_i^T``: ``(ok, x0, x1, x2, i00, i11, i22, i01, i02, i12)`` (``M^-1``; zeros when singular,
    :func:`._linalg.inverse3`)."""
    xx = yy = zz = xy = xz = yz = t0 = t1 = t2 = 0.0
    for i in range(y.shape[0]):
        vi = v[i]
        l0, l1, l2 = lights[i, 0], lights[i, 1], lights[i, 2]
        xx += vi * l0 * l0
        yy += vi * l1 * l1
        zz += vi * l2 * l2
        xy += vi * l0 * l1
        xz += vi * l0 * l2
        yz += vi * l1 * l2
        t0 += vi * y[i] * l0
        t1 += vi * y[i] * l1
        t2 += vi * y[i] * l2
    ok, i00, i11, i22, i01, i02, i12 = inverse3(xx, yy, zz, xy, xz, yz, SINGULAR_REL_DET)
    return (ok, i00 * t0 + i01 * t1 + i02 * t2, i01 * t0 + i11 * t1 + i12 * t2,
            i02 * t0 + i12 * t1 + i22 * t2, i00, i11, i22, i01, i02, i12)


@njit(nogil=True, cache=True, error_model="numpy")
def _loo_terms(y, fw, use, lights, lam, clip2, out):
    """Truncated left-out terms of the weighted Lambertian fit of one pixel; their sum.

    ``fw`` (n,) the fit's weights (LS: 1 on usable observations, SBL: its final ``d``), ``use``
    (n,) the scored observations, ``lam`` (n,) their noise variance. The fit is linear in ``y``
    (``x = M^-1 sum fw_i y_i l_i``), so observation i left out has the residual ``r_i / (1 -
    h_i)``, ``h_i = fw_i l_i^T M^-1 l_i``; its term is ``min(e_i^2 / lam_i, clip2)``. Infinity
    when ``M`` is singular.
    """
    n = y.shape[0]
    ok, x0, x1, x2, i00, i11, i22, i01, i02, i12 = _weighted_fit(y, fw, lights)
    if not ok:
        return math.inf
    total = 0.0
    for i in range(n):
        out[i] = 0.0
        if use[i] > 0.0:
            l0, l1, l2 = lights[i, 0], lights[i, 1], lights[i, 2]
            r = y[i] - (x0 * l0 + x1 * l1 + x2 * l2)
            q = (i00 * l0 * l0 + i11 * l1 * l1 + i22 * l2 * l2
                 + 2.0 * (i01 * l0 * l1 + i02 * l0 * l2 + i12 * l1 * l2))
            h = fw[i] * q
            e2 = r * r / (lam[i] * (1.0 - h) ** 2) if h < 1.0 else clip2
            out[i] = e2 if e2 < clip2 else clip2
            total += out[i]
    return total


@njit(inline="always")
def _gain(small, large, use, z):
    """Paired gain of the larger model less ``z`` standard errors: > 0 keeps the larger."""
    n = small.shape[0]
    k = 0
    s = 0.0
    for i in range(n):
        if use[i] > 0.0:
            s += small[i] - large[i]
            k += 1
    if k < 2:
        return -math.inf
    mean = s / k
    var = 0.0
    for i in range(n):
        if use[i] > 0.0:
            dv = small[i] - large[i] - mean
            var += dv * dv
    return s - z * math.sqrt(k * var / (k - 1))


@njit(nogil=True, cache=True, error_model="numpy")
def _last_choice_kernel(y, w, lights, lam, x_sbl, d, x_pl, pl, clip2, z, x_out, model):
    m, n = y.shape
    t_ls = np.empty(n)
    t_sbl = np.empty(n)
    per_pixel = lights.shape[0] > 1
    for p in range(m):
        lp = lights[p if per_pixel else 0]
        s_ls = _loo_terms(y[p], w[p], w[p], lp, lam[p], clip2, t_ls)
        s_sbl = _loo_terms(y[p], d[p], w[p], lp, lam[p], clip2, t_sbl)
        if s_ls < math.inf and (not s_sbl < math.inf or _gain(t_sbl, t_ls, w[p], z) > 0.0):
            model[p] = 0
        else:
            model[p] = 1
        if pl[p] and model[p] == 1:  # PL-SBL nests SBL: the PL stage chose it over SBL
            model[p] = 2
        if model[p] == 0:
            fit = _weighted_fit(y[p], w[p], lp)
            x_out[p, 0], x_out[p, 1], x_out[p, 2] = fit[1], fit[2], fit[3]
        elif model[p] == 1:
            x_out[p, 0], x_out[p, 1], x_out[p, 2] = x_sbl[p, 0], x_sbl[p, 1], x_sbl[p, 2]
        else:
            x_out[p, 0], x_out[p, 1], x_out[p, 2] = x_pl[p, 0], x_pl[p, 1], x_pl[p, 2]


def last_choice(y, w, lights, lam, x_sbl, d, x_pl, pl, *,
                clip=CHOICE_CLIP, z=CHOICE_Z):
    """Per pixel: least squares, SBL or PL-SBL (0, 1, 2) and the chosen fit's ``x``.

    Parameters
    ----------
    y, w : ndarray of shape (m, n)
        Scaled observations and their usable mask (1/0).
    lights : ndarray of shape (n, 3) or (m, n, 3)
        The same for every pixel, or each pixel's own (near lights).
    lam : float or ndarray of shape (m, 1) or (m, n)
        SBL's noise variance of each observation (the pixel's relative units).
    x_sbl, d : ndarray of shape (m, 3), (m, n)
        SBL's fit and its final weights ``d = 1 / (gamma + lam)``.
    x_pl : ndarray of shape (m, 3)
        PL-SBL's fit where ``pl`` (m,) bool: the pixels where the PL stage kept it.
    clip, z : float
        :data:`CHOICE_CLIP`, :data:`CHOICE_Z`.

    Returns
    -------
    model : ndarray of shape (m,), int8
    x : ndarray of shape (m, 3)

    SBL is kept unless least squares' truncated left-out score is lower by more than ``z``
    standard errors of the paired differences (:func:`_gain`; :func:`_loo_terms`, SBL as the
    weighted least squares of its final ``d``); PL-SBL, where the PL
    stage chose it over SBL (:func:`._pl_model._choose`), replaces SBL where SBL was chosen.
    (Scoring PL-SBL's normal as a Lambertian image instead rejected it on DiLiGenT, where it is
    6-8 deg better than SBL: docs/solvers.md.)
    """
    m, n = y.shape
    lam_obs = np.require(np.broadcast_to(np.asarray(lam, dtype=np.float64), (m, n)), None, "CW")
    model = np.zeros(m, np.int8)
    x = np.zeros((m, 3))
    light_stack = np.asarray(lights, dtype=np.float64)
    light_stack = np.ascontiguousarray(light_stack[None] if light_stack.ndim == 2 else light_stack)
    if m:
        _last_choice_kernel(np.require(y, np.float64, "C"), np.require(w, np.float64, "C"),
                            light_stack, lam_obs,
                            np.require(x_sbl, np.float64, "C"), np.require(d, np.float64, "C"),
                            np.require(x_pl, np.float64, "C"), np.require(pl, np.bool_, "C"),
                            float(clip) ** 2, float(z), x, model)
    return model, x
