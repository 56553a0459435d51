"""Straightforward per-pixel references of the solvers: test oracle and benchmark baseline.

Each oracle handles ONE pixel with plain numpy, exactly as the method is written in its paper
(for SBL the n x n matrices of Ikehata et al. Eq. 13 are formed explicitly). Dropped
observations are removed from the pixel's problem. The update and stopping rules are the ones
the vectorised solvers document, so results agree as far as ``tolerances.py`` derives.

Each pixel oracle returns ``(x, statistic, iterations)``: ``statistic`` is what the method compares
with ``outlier_threshold`` to flag an observation (``|residual|`` for L1, the corruption estimate
``|e|`` for SBL and the PL models (in intensity units), 0 for least squares).
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2


ORACLE_PARAMS = ("max_iter", "tol", "delta", "outlier_threshold", "sigma_x2", "gamma_floor",
                 "gamma_start", "lam_sparse", "rho", "segments", "sbl_max_iter", "gate_noise",
                 "gate_false_alarm")


def oracle_params(sol) -> dict:
    """The parameters a solution ``sol`` was solved with, as :func:`solve_oracle` takes them."""
    p = {k: v for k, v in sol.params.items() if k in ORACLE_PARAMS}
    if "lambda" in sol.params:
        p["lam"] = sol.params["lambda"]
        if p["lam"] is None:  # SBL's per-pixel default
            p["noise_sigma"] = sol.params["noise_sigma"]
            p["noise_floor"] = sol.params["noise_floor"]
            p["light_noise"] = sol.params["light_noise"]
            if "noise_sigma_pl" in sol.params:
                p["noise_sigma_pl"] = sol.params["noise_sigma_pl"]
    return p


def pixel_scale(y: np.ndarray) -> float:
    """Median of |y| over a pixel's usable observations (mean if the median is 0)."""
    if y.size == 0:
        return 0.0
    med = float(np.median(np.abs(y)))
    return med if med > 0 else float(np.mean(np.abs(y)))


def solvable(a: np.ndarray, scale: float, rel_det: float = 1e-6) -> bool:
    m = a.T @ a
    tr = np.trace(m) / 3.0
    return a.shape[0] >= 3 and scale > 0 and tr > 0 and np.linalg.det(m) > rel_det * tr**3


def ls_pixel(y, a):
    return np.linalg.lstsq(a, y, rcond=None)[0], np.zeros(y.size), 1


def l1_pixel(y, a, *, max_iter=100, tol=1e-6, delta=1e-6):
    x = np.linalg.lstsq(a, y, rcond=None)[0]
    it = max_iter
    for k in range(1, max_iter + 1):
        wts = 1.0 / np.maximum(np.abs(y - a @ x), delta)
        x_new = np.linalg.solve(a.T @ (wts[:, None] * a), a.T @ (wts * y))
        step = np.abs(x_new - x).max()
        x = x_new
        if step < tol:
            it = k
            break
    return x, np.abs(y - a @ x), it


def sbl_pixel(y, a, *, lam, sigma_x2=1e6, max_iter=100, tol=1e-4, gamma_floor=1e-10,
              gamma_start=1e3, out=None):
    """SBL of one pixel: (x, |e|, iterations); ``out`` (a dict) receives the final ``gamma``."""
    n = y.size
    gamma = np.full(n, float(gamma_start))
    z_old = np.zeros(n)
    it = max_iter
    for k in range(1, max_iter + 1):
        big_d = np.diag(1.0 / (gamma + lam))
        m = np.eye(3) / sigma_x2 + a.T @ big_d @ a
        s = big_d - big_d @ a @ np.linalg.inv(m) @ a.T @ big_d  # Sigma_y^-1 (Eq. 13's "S")
        g = np.diag(gamma)
        z = g @ s @ y
        u = np.diag(g - g @ s @ g)
        gamma = np.maximum(z**2 + u, gamma_floor)
        step = np.abs(z - z_old).max()
        z_old = z
        if step < tol:
            it = k
            break
    big_d = np.diag(1.0 / (gamma + lam))
    m = np.eye(3) / sigma_x2 + a.T @ big_d @ a
    x = np.linalg.solve(m, a.T @ big_d @ y)
    e = gamma * np.diag(big_d) * (y - a @ x)
    if out is not None:
        out["gamma"] = gamma
    return x, np.abs(e), it


def pl_model(y, a, *, segments, lam, sigma_x2=1e6, max_iter=20, tol=1e-4, gamma_floor=1e-10,
             gamma_start=1e3, sbl=True, learn_tau=True, slope_floor=1e-3, out=None,
             lit=None, slope_noise=True):
    """Piecewise-linear model of one pixel, with the design and the constraint written out.

    Interior break points: order statistics of the observations ``lit`` (bool (n,), those the
    Lambertian fit predicts lit; all of them when None or with fewer than 4 per segment); the
    top one the largest observation. ``gamma_start`` may be an array
    (n,) in ``y``'s units (a start from SBL's fit); ``slope_noise`` False keeps ``lam / K^2``.
    Returns (x (K+2), slopes (K), breaks (K+1), segment of each observation, gamma, lambda,
    iterations, log evidence, K used); ``out`` (a dict) receives the final fit's ``design``,
    ``target``, weights ``d``, ``prior`` and ``prior_rhs``.
    """
    n = y.size
    k = max(1, min(segments, n // 4))  # at least 4 observations per segment
    lam0 = np.broadcast_to(np.asarray(lam, dtype=float), (n,)).copy()
    use = lit is not None and k > 1 and lit.sum() >= 4 * k
    srt = np.sort(y[lit] if use else y)
    c = srt.size
    breaks = np.array([0.0] + [srt[(j * c) // k] for j in range(1, k)] + [y.max()])
    phi = np.clip(y[:, None] - breaks[None, :k], 0.0, breaks[1:] - breaks[:k])
    seg = (y[:, None] > breaks[None, 1:k]).sum(axis=1)
    # f(y) = sum_k s_k phi_k = -a.l ; s_{K-1} = 1 - sum_{k<K-1} s_k eliminated
    design = np.concatenate([phi[:, :k - 1] - phi[:, k - 1:k], -a], axis=1)
    target = -phi[:, k - 1]
    u = k + 2
    lam_f = lam0 / k**2
    gamma = np.full(n, gamma_start / k**2)
    tau2 = 1.0
    z_old = np.zeros(n)
    iters = max_iter if sbl else 1
    done = not sbl
    it = 0
    q_free = np.eye(k - 1) + 1.0
    while True:
        prior = np.zeros((u, u))
        prior[:k - 1, :k - 1] = q_free / tau2
        prior[k - 1:, k - 1:] = np.eye(3) / sigma_x2
        prior_rhs = np.concatenate([np.ones(k - 1) / tau2, np.zeros(3)])
        d = 1.0 / ((gamma if sbl else 0.0) + lam_f)
        m = prior + design.T @ np.diag(d) @ design
        minv = np.linalg.inv(m)
        x = minv @ (prior_rhs + design.T @ (d * target))
        slopes = np.append(x[:k - 1], 1.0 - x[:k - 1].sum())
        if done or it == max_iter:
            if out is not None:
                out.update(design=design, target=target, d=d, prior=prior, prior_rhs=prior_rhs)
            break
        # SBL (Ikehata et al. 2012) with Sigma_t = Gamma + Lambda + design P^-1 design^T, whose
        # inverse (Woodbury) is D - D design M^-1 design^T D; the prior mean is P^-1 prior_rhs
        big_d = np.diag(d)
        s_inv = big_d - big_d @ design @ minv @ design.T @ big_d
        r0 = target - design @ np.linalg.solve(prior, prior_rhs)
        z = gamma * (s_inv @ r0)
        uu = gamma - gamma**2 * np.diag(s_inv)
        gamma = np.maximum(z**2 + uu, gamma_floor)
        moved = np.abs(z - z_old) >= tol / k
        z_old = z
        if k > 1:
            if learn_tau:
                dev = x[:k - 1] - 1.0 / k
                e2 = dev @ q_free @ dev + np.trace(q_free @ minv[:k - 1, :k - 1])
                tau2 = max(e2 / (k - 1), 1e-10)
            if slope_noise:
                lam_f = lam0 * np.maximum(slopes[seg], slope_floor / k) ** 2
        it += 1
        if not moved.any():
            iters = it
            done = True
    if not sbl:
        return x, slopes, breaks, seg, gamma, lam_f, 1, 0.0, k
    # log N(t; design P^-1 prior_rhs, Sigma_t): determinant lemma and Woodbury
    c = gamma + lam_f
    big_d = np.diag(1.0 / c)
    s_inv = big_d - big_d @ design @ minv @ design.T @ big_d
    r = target - design @ np.linalg.solve(prior, prior_rhs)
    logdet = (np.sum(np.log(c)) + np.linalg.slogdet(m)[1] - np.linalg.slogdet(prior)[1])
    loglik = -0.5 * (logdet + r @ s_inv @ r)
    with np.errstate(divide="ignore", invalid="ignore"):
        jac = np.sum(np.log(slopes[seg])) if np.all(slopes[seg] > 0) else -np.inf
    return x, slopes, breaks, seg, gamma, lam_f, iters, loglik + jac, k


def _pl_result(model, y, outlier_threshold, slope_floor=1e-3):
    x, slopes, breaks, seg, gamma, lam_f, iters, evidence, k = model
    fb = np.sum(slopes * np.diff(breaks))
    normal = x[k - 1:] * (breaks[-1] / fb if fb > 0 else 0.0)
    return normal, slopes, seg, gamma, lam_f, iters, evidence, k


def _pl_statistic(model, y, a, slope_floor=1e-3):
    """|e|: each observation's corruption estimate, in intensity units (its segment's slope)."""
    x, slopes, breaks, seg, gamma, lam_f, _, _, k = model
    phi = np.clip(y[:, None] - breaks[None, :k], 0.0, breaks[1:] - breaks[:k])
    resid = phi @ slopes - a @ x[k - 1:]  # f(y) - l.n = -(t - design x)
    e = gamma / (gamma + lam_f) * resid / np.maximum(slopes[seg], slope_floor / k)
    return np.abs(e)


def plsbl_pixel(y, a, *, lam, segments=3, sigma_x2=1e6, max_iter=20, tol=1e-4,
                gamma_floor=1e-10, gamma_start=1e3, sbl_max_iter=100):
    """PL-SBL as ps-lab runs it: the issue-23 fit (break points from all observations, the EM
    from ``gamma_start``) and, with SBL's fit (the Lambertian model), a second one (break points
    from the observations SBL's fit sees lit, the EM from SBL's final gamma); the fit of the
    higher log evidence kept."""
    common = dict(segments=segments, lam=lam, sigma_x2=sigma_x2, max_iter=max_iter, tol=tol,
                  gamma_floor=gamma_floor)
    model = pl_model(y, a, gamma_start=gamma_start, **common)
    if model[8] > 1:
        fit = {}
        x_sbl = sbl_pixel(y, a, lam=lam, sigma_x2=sigma_x2, max_iter=sbl_max_iter, tol=tol,
                          gamma_floor=gamma_floor, gamma_start=gamma_start, out=fit)[0]
        second = pl_model(y, a, gamma_start=fit["gamma"], lit=a @ x_sbl > 0.0, **common)
        model = second if second[7] >= model[7] or np.isnan(model[7]) else model
    normal, *_, iters, _, _ = _pl_result(model, y, np.inf)
    return normal, _pl_statistic(model, y, a), iters


def plls_pixel(y, a, *, segments=3):
    model = pl_model(y, a, segments=segments, lam=1e-6, sigma_x2=1e12, sbl=False,
                     learn_tau=False)
    normal = _pl_result(model, y, np.inf)[0]
    return normal, np.zeros(y.size), 1


def _left_out_terms(design, target, d, prior, prior_rhs, scored, weight, divide):
    """``weight_i ((t_i - a_i.x_(-i)) / divide_i)^2`` for the scored i, refitting without each."""
    terms = np.zeros(target.size)
    for i in np.flatnonzero(scored):
        keep = np.arange(target.size) != i
        m = prior + design[keep].T @ (d[keep, None] * design[keep])
        x = np.linalg.solve(m, prior_rhs + design[keep].T @ (d[keep] * target[keep]))
        terms[i] = weight[i] * ((target[i] - design[i] @ x) / divide[i]) ** 2
    return terms


def bend_score(y, a, x, lam_test, k, clip=3.0):
    """Score statistic of the Lambertian fit ``x`` against ``k`` segments (issue 31's gate).

    The weighted (1 / lam_test) residual sum of squares that the hinges ``max(a.x - b_j, 0)``
    (``b_j`` the ``j u / k``-th smallest fitted value) remove from the regression of the
    residuals ``y - a.x``, clipped at ``clip sqrt(lam_test)``, on the lights; NaN when it
    cannot be tested.
    """
    fit, wt = a @ x, 1.0 / lam_test
    r = np.clip(y - fit, -clip * np.sqrt(lam_test), clip * np.sqrt(lam_test))
    if k < 2 or fit.size < 4 * (k + 2):
        return np.nan
    srt = np.sort(fit)
    hinges = [np.maximum(fit - srt[(j * fit.size) // k], 0.0) for j in range(1, k)]
    full = np.column_stack([a, *hinges])

    def reduction(design):
        g = design.T @ (wt * r)
        return g @ np.linalg.solve(design.T @ (wt[:, None] * design), g)

    return reduction(full) - reduction(a)


def least_squares_wins(y, a, lam, d_sbl, clip=3.0, z=1.0):
    """Issue 42's last choice: least squares replaces SBL where its left-out terms are lower.

    Each model (LS: weights 1; SBL: its final ``d``) is refitted without each observation in
    turn; a term is ``min(r_(-i)^2 / lam_i, clip^2)``; LS wins when the paired differences (SBL
    minus LS) sum to more than ``z`` standard errors.
    """
    def terms(d):
        t = np.zeros(y.size)
        for i in range(y.size):
            keep = np.arange(y.size) != i
            x = np.linalg.solve(a[keep].T @ (d[keep, None] * a[keep]),
                                a[keep].T @ (d[keep] * y[keep]))
            t[i] = min((y[i] - a[i] @ x) ** 2 / lam[i], clip**2)
        return t

    diff = terms(d_sbl) - terms(np.ones(y.size))
    return diff.sum() - z * np.sqrt(y.size * np.var(diff, ddof=1)) > 0


def in_rings(lights, tolerance=0.25, count=6):
    """Share of the lights with ``count`` lights within ``tolerance`` degrees of elevation."""
    v = np.asarray(lights, float)
    elevation = np.degrees(np.arcsin(v[:, 2] / np.linalg.norm(v, axis=1)))
    near = (np.abs(elevation[:, None] - elevation[None, :]) <= tolerance).sum(axis=1)
    return float(np.mean(near >= count))


def auto_pixel(y, a, *, lam, lam_pl=None, segments=3, sigma_x2=1e6, max_iter=20, tol=1e-4,
               gamma_floor=1e-10, gamma_start=1e3, outlier_threshold=np.inf, choice_z=1.0,
               sbl_max_iter=100, slope_floor=1e-3, gate_noise=None, gate_false_alarm=0.01,
               out=None):
    """SBL, or PL-SBL where SBL fails the score test and PL predicts better (issue 31).

    The gate: SBL's :func:`bend_score` at the noise ``max(lam_pl, gate_noise^2)``
    exceeds the chi^2 quantile of ``1 - gate_false_alarm`` with ``k - 1`` degrees of freedom
    (``gate_noise`` None: no gate). Scored: usable observations not flagged by both fits;
    each fit's weights held at their final values and refitted without each scored
    observation (no closed form); the paired differences of the squared left-out residuals
    (in y's units, weights 1 / lam) must sum to more than ``choice_z`` standard errors.
    Where SBL is kept, least squares replaces it where :func:`least_squares_wins` (issue 42);
    ``out`` (a dict) receives SBL's fit and corruption (the albedo's normal and inliers).
    """
    lam = np.broadcast_to(np.asarray(lam, dtype=float), y.shape)
    lam_pl = lam if lam_pl is None else lam_pl
    extra = {}
    x_sbl, e_sbl, it_sbl = sbl_pixel(y, a, lam=lam, sigma_x2=sigma_x2, max_iter=sbl_max_iter,
                                     tol=tol, gamma_floor=gamma_floor, gamma_start=gamma_start,
                                     out=extra)
    if out is not None:
        out["x_sbl"], out["e_sbl"] = x_sbl, e_sbl
    if least_squares_wins(y, a, lam, 1.0 / (extra["gamma"] + lam)):
        sbl_result = np.linalg.lstsq(a, y, rcond=None)[0], np.zeros(y.size), it_sbl
    else:
        sbl_result = x_sbl, e_sbl, it_sbl
    if segments == 1:
        return sbl_result
    if gate_noise is not None:
        k = max(1, min(segments, y.size // 4))
        lam_test = np.maximum(np.broadcast_to(lam_pl, y.shape), gate_noise**2)
        score = bend_score(y, a, x_sbl, lam_test, k)
        if not score > chi2.ppf(1.0 - gate_false_alarm, k - 1):
            return sbl_result
    fit = {}
    pl = pl_model(y, a, segments=segments, lam=lam_pl, sigma_x2=sigma_x2, max_iter=max_iter,
                  tol=tol, gamma_floor=gamma_floor, gamma_start=gamma_start, out=fit)
    k = pl[8]
    if k == 1 or not np.isfinite(pl[7]):
        return sbl_result
    e_pl = _pl_statistic(pl, y, a)
    scored = ~((e_sbl > outlier_threshold) & (e_pl > outlier_threshold))
    count = int(scored.sum())
    if count < 4 * (k + 2):  # at least 4 scored observations per PL unknown
        return sbl_result
    weight = 1.0 / lam
    d_sbl = 1.0 / (extra["gamma"] + lam)
    sbl_terms = _left_out_terms(a, y, d_sbl, np.eye(3) / sigma_x2, np.zeros(3), scored, weight,
                                np.ones(y.size))
    slope = np.maximum(pl[1][pl[3]], slope_floor / k)
    pl_terms = _left_out_terms(fit["design"], fit["target"], fit["d"], fit["prior"],
                               fit["prior_rhs"], scored, weight, slope)
    diff = (sbl_terms - pl_terms)[scored]
    gain = diff.sum() - choice_z * np.sqrt(count * np.var(diff, ddof=1))
    if not gain > 0:
        return sbl_result
    return _pl_result(pl, y, np.inf)[0], e_pl, pl[6]


PIXEL_ORACLES = {"ls": ls_pixel, "l1": l1_pixel, "sbl": sbl_pixel, "plls": plls_pixel,
                 "plsbl": plsbl_pixel, "auto": auto_pixel}


def solve_oracle(observations, lights, method, valid=None, *, statistic=False, **params):
    """One pixel at a time; returns (normals (P,3), albedo (P,), outliers (n,P), iterations (P,)).

    With ``statistic``, also the (n, P) statistic each flag compares with the outlier threshold
    (scaled units; NaN for unused observations).
    """
    obs = np.asarray(observations, float)
    n, p = obs.shape
    valid = np.ones((n, p), bool) if valid is None else np.asarray(valid, bool)
    valid = valid & np.isfinite(obs)
    if method == "rpca":
        result = rpca_oracle(obs, lights, valid, **params)
        return result if statistic else result[:4]
    threshold = params.get("outlier_threshold", np.inf)
    params = {k: v for k, v in params.items() if k != "outlier_threshold"}
    normals, albedo = np.zeros((p, 3)), np.zeros(p)
    outliers, iterations = np.zeros((n, p), bool), np.zeros(p, int)
    statistics = np.full((n, p), np.nan)
    for j in range(p):
        v = valid[:, j]
        y, a = obs[v, j], lights[v]
        scale = pixel_scale(y)
        if not solvable(a, scale):
            continue
        pixel_params = params
        if method in ("sbl", "plsbl", "auto") and params.get("lam") is None:
            # SBL's default: sigma^2 relative plus the noise floor (observation units, times each
            # light's factor) / scale, per observation
            sigma, floor = params["noise_sigma"], params["noise_floor"]
            factor = params.get("light_noise")
            factor = np.ones(n) if factor is None else np.asarray(factor)
            rest = {k: v for k, v in params.items()
                    if k not in ("noise_sigma", "noise_floor", "light_noise", "noise_sigma_pl")}

            floor_term = (floor * factor[v] / scale) ** 2
            pixel_params = {**rest, "lam": np.maximum(sigma**2 + floor_term, 1e-6)}
            if method in ("plsbl", "auto"):  # the PL model's own relative noise
                # (auto: not measured when no pixel failed the gate, which then passes at 0)
                sigma_pl = params["noise_sigma_pl"] or 0.0
                lam_pl = np.maximum(sigma_pl**2 + floor_term, 1e-6)
                pixel_params["lam" if method == "plsbl" else "lam_pl"] = lam_pl
        sbl_fit: dict = {}
        if method == "auto":
            # issue 42: no PL-SBL with lights in rings of equal elevation (a dome)
            pixel_params = {**pixel_params, "outlier_threshold": threshold, "out": sbl_fit}
            if in_rings(lights) >= 0.5:
                pixel_params["segments"] = 1
        x, stat, it = PIXEL_ORACLES[method](y / scale, a, **pixel_params)
        x = x * scale
        albedo[j] = np.linalg.norm(x)
        if albedo[j] > 0:
            normals[j] = x / albedo[j]
            outliers[np.flatnonzero(v), j] = stat > threshold
            statistics[np.flatnonzero(v), j] = stat
            # the default's albedo is SBL's whichever model gave the normal (issue 42)
            shade, kept = normals[j], stat <= threshold
            if sbl_fit:
                shade = sbl_fit["x_sbl"] / np.linalg.norm(sbl_fit["x_sbl"])
                kept = sbl_fit["e_sbl"] <= threshold
            albedo[j] = lambertian_equivalent(shade, y, a, kept, albedo[j])
        iterations[j] = it
    if statistic:
        return normals, albedo, outliers, iterations, statistics
    return normals, albedo, outliers, iterations


def lambertian_equivalent(normal, y, a, inliers, fallback):
    """Least-squares scale of ``max(n.l, 0)`` on the inliers that the normal sees lit."""
    shading = a @ normal
    use = inliers & (shading > 0)
    den = float(shading[use] @ shading[use])
    return max(float(y[use] @ shading[use]) / den, 0.0) if den > 0 else fallback


def rpca_oracle(obs, lights, valid, *, lam_sparse=None, max_iter=500, tol=1e-7, rho=1.5,
                outlier_threshold=0.05):
    """Inexact ALM with a full SVD per iteration (Lin, Chen & Ma 2010; Wu et al. 2010)."""
    n, p = obs.shape
    scales = np.array([pixel_scale(obs[valid[:, j], j]) for j in range(p)])
    ok = np.array([solvable(lights[valid[:, j]], scales[j]) for j in range(p)])
    cols = np.flatnonzero(ok)
    d = np.where(valid[:, cols], obs[:, cols] / scales[cols], 0.0)
    omega = valid[:, cols]
    lam = 1.0 / np.sqrt(max(n, cols.size)) if lam_sparse is None else lam_sparse
    norm2 = np.linalg.norm(d, 2)
    mult = d / max(norm2, np.abs(d).max() / lam)
    mu, mu_max = 1.25 / norm2, 1.25e7 / norm2
    e = np.zeros_like(d)
    it = 0
    for it in range(1, max_iter + 1):
        u, s, vt = np.linalg.svd(d - e + mult / mu, full_matrices=False)
        low = (u * np.maximum(s - 1.0 / mu, 0.0)) @ vt
        t = d - low + mult / mu
        e = np.where(omega, np.sign(t) * np.maximum(np.abs(t) - lam / mu, 0.0), t)
        r = np.where(omega, d - low - e, 0.0)
        mult = mult + mu * r
        mu = min(mu * rho, mu_max)
        if np.linalg.norm(r) <= tol * np.linalg.norm(d):
            break
    normals, albedo = np.zeros((p, 3)), np.zeros(p)
    outliers = np.zeros((n, p), bool)
    x = np.linalg.lstsq(lights, low, rcond=None)[0] * scales[cols]
    albedo[cols] = np.linalg.norm(x, axis=0)
    normals[cols] = (x / albedo[cols]).T
    outliers[:, cols] = omega & (np.abs(e) > outlier_threshold)
    for c in cols:
        inl = valid[:, c] & ~outliers[:, c]
        albedo[c] = lambertian_equivalent(normals[c], np.where(valid[:, c], obs[:, c], 0.0),
                                          lights, inl, albedo[c])
    statistics = np.full((n, p), np.nan)
    statistics[:, cols] = np.where(omega, np.abs(e), np.nan)
    return normals, albedo, outliers, np.where(ok, it, 0), statistics
