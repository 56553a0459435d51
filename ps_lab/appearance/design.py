"""What the training lights determine of an appearance model (pure functions on arrays).

The appearance fits (:mod:`.blocks`) fit only the terms the lights determine:
:func:`distinct_lights` counts directions closer than :data:`SAME_LIGHT` once,
:func:`determined_columns` keeps a design's columns in order while each raises its numerical
rank, :func:`determined_terms` applies both to a model and words the one warning line.
:func:`saturated_observations` is the one rule for saturated observations (dropped by every
fit). See docs/appearance.md, "What the lights determine".
"""

from __future__ import annotations

import numpy as np

from ps_lab.appearance.models import BASIS_TERMS, appearance_basis, ps_basis

__all__ = [
    "PS_PROBE",
    "RANK_RTOL",
    "SAME_LIGHT",
    "TERM_NAMES",
    "determined_columns",
    "determined_terms",
    "distinct_lights",
    "model_design",
    "saturated_observations",
]

#: Training directions closer than this (radians, about 0.06 degrees) are one light.
SAME_LIGHT = 1e-3
#: Singular values of a design (unit columns, one row per distinct light) below this share of
#: the largest do not count toward its numerical rank.
RANK_RTOL = 1e-6
#: The normal at which the ps model's design is evaluated (a generic tilt, no symmetry).
PS_PROBE = np.array([0.3, 0.2, 0.93]) / np.linalg.norm([0.3, 0.2, 0.93])
#: How the warning names the terms of the fixed bases (docs/appearance.md).
TERM_NAMES = {
    "ptm": ("1", "lx", "ly", "lx²", "lx·ly", "ly²"),
    "hsh2": tuple(f"h{i}" for i in range(4)),
    "hsh3": tuple(f"h{i}" for i in range(9)),
}


def saturated_observations(
    observations: np.ndarray, valid: np.ndarray, threshold: float | None = None, terms: int = 0
) -> np.ndarray:
    """The observations every appearance fit drops: the saturated ones.

    Saturated: not valid, and not for being at or below the shadow threshold (the solver's
    validity drops both; the appearance fits keep shadows). A pixel that would be left with
    fewer than ``terms`` observations keeps all of its own (clipped values, a lower bound, are
    a better guess than none: a pixel saturated under every light stays bright).

    Parameters
    ----------
    observations : ndarray of shape (n, P)
        The combined observations the validity was decided on.
    valid : ndarray of shape (n, P), bool
        The store's validity (False: saturated in any channel, or ``<= threshold``).
    threshold : float or None
        The shadow threshold in use (None: none).
    terms : int
        Terms per channel of the model fitted.

    Returns
    -------
    ndarray of shape (n, P), bool

    """
    saturated = ~np.asarray(valid, bool)
    if threshold is not None:
        saturated &= np.asarray(observations) > threshold
    if terms:
        saturated[:, saturated.shape[0] - saturated.sum(axis=0) < terms] = False
    return saturated


def distinct_lights(directions: np.ndarray, tolerance: float = SAME_LIGHT) -> np.ndarray:
    """The first of each group of equal training directions (closer than ``tolerance``).

    Parameters
    ----------
    directions : ndarray of shape (n, 3)
        Unit directions.
    tolerance : float
        Chord (about the angle, radians) under which two directions are one light.

    Returns
    -------
    ndarray of shape (m,), int: indices into ``directions``, increasing

    """
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    kept: list[int] = []
    for i in range(len(d)):
        if not kept or np.min(np.linalg.norm(d[kept] - d[i], axis=1)) >= tolerance:
            kept.append(i)
    return np.array(kept, np.int64)


def determined_columns(design: np.ndarray, rtol: float = RANK_RTOL) -> np.ndarray:
    """The terms a design determines: its columns in order, each kept when it raises the
    numerical rank of the kept ones (unit-normalised columns; singular values below ``rtol`` of
    the largest do not count).

    Parameters
    ----------
    design : ndarray of shape (m, K)
        The terms at the distinct training lights.
    rtol : float

    Returns
    -------
    ndarray of shape (r,), int: r = the numerical rank, the first r columns when they are
    independent

    """
    b = np.asarray(design, np.float64)
    norms = np.linalg.norm(b, axis=0)
    kept: list[int] = []
    for j in range(b.shape[1]):
        if not norms[j] > 0 or len(kept) >= b.shape[0]:
            continue
        trial = kept + [j]
        values = np.linalg.svd(b[:, trial] / norms[trial], compute_uv=False)
        if values[-1] > rtol * values[0]:
            kept = trial
    return np.array(kept, np.int64)


def model_design(model: str, directions: np.ndarray, terms: tuple) -> np.ndarray:
    """A model's terms at the distinct training lights (m, K).

    ``ptm``/``hsh*``: their basis; ``ps``: its terms (names) at the normal
    :data:`PS_PROBE` (a generic normal, about 21° from the view: at the view's own normal a
    ring of lights makes every half-vector lobe a constant, which it is not for the tilted
    pixels that hold the gloss); ``rbf``: one basis vector per distinct light at most (the
    identity's first ``len(terms)`` columns).
    """
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    d = d[distinct_lights(d)]
    if model in BASIS_TERMS:
        return appearance_basis(model, d)
    if model == "ps":
        return ps_basis(d, PS_PROBE[None], tuple(terms))[:, 0, :]
    if model == "rbf":
        return np.eye(len(d), len(terms))
    raise ValueError(f"no design for appearance model {model!r}")


def determined_terms(model: str, directions: np.ndarray, terms: tuple
                     ) -> tuple[np.ndarray, str | None]:
    """The terms of ``model`` the training lights determine, and the warning when not all.

    The rule (docs/appearance.md, "What the lights determine"): directions closer than
    :data:`SAME_LIGHT` count as one light; a model's terms are kept in their order while each
    raises the numerical rank of the design at the distinct lights (:func:`determined_columns`);
    the others are not fitted (stored as 0 for ``ptm``/``hsh*``; left out of ``ps``'s term
    list; fewer basis vectors for ``rbf``).

    Parameters
    ----------
    model : str
    directions : ndarray of shape (n, 3)
        Unit training directions.
    terms : tuple
        The model's term names (``ps``: the vocabulary's names; others: any, one per term).

    Returns
    -------
    keep : ndarray of shape (r,), int
        Indices of the determined terms.
    warning : str or None
        One line saying what was left out (None when every term is determined).

    """
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    distinct = len(distinct_lights(d))
    design = model_design(model, d, terms)
    keep = determined_columns(design)
    total = len(terms)
    if len(keep) == total:
        return keep, None
    dropped = [str(terms[k]) for k in range(total) if k not in set(keep.tolist())]
    same = f" ({len(d) - distinct} repeating another)" if distinct < len(d) else ""
    return keep, (f"appearance {model}: the {len(d)} training lights{same} determine "
                  f"{len(keep)} of its {total} terms per channel (the design's numerical rank "
                  f"at the {distinct} distinct directions); not fitted: {', '.join(dropped)}")
