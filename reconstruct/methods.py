"""The solver table: every photometric-stereo method, its kernels, options, warm-up and help.

One :class:`SolverMethod` row per method of :func:`ps_lab.reconstruct.solve`. Everything that
names the methods reads this table: the command line's ``--method`` choices and help
(``ps_lab/commands/reconstruct.py``), which ``--lambda``/``--segments``/... flags apply
(:mod:`ps_lab.reconstruct.options`), the parameters and their defaults (``solve``), the noise
estimate of a banded run (``_passes.py``), near lights (:mod:`ps_lab.reconstruct.near`), the
kernels compiled ahead of a run (``_warm_up.py``) and the benchmarks' columns and labels
(``ps_lab/bench``). Adding a solver is one row here and its tile kernel (docs/solvers.md,
"Adding a solver").
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from . import _kernels, _near_kernels, _pl_kernels
from ._pl_model import gate_variance
from ._solution import SolverInputError
from ._tiles import LAMBDA_FLOOR, ls_tiles

__all__ = [
    "DEFAULT_METHOD", "METHODS", "SOLVERS", "SolverMethod", "method_help", "methods_with", "solver",
]

# SBL's iterations; also those of the default method's SBL candidate.
SBL_MAX_ITER = 100


def _pl_ls_tile(y, w, lights, *, segments):
    """PL-LS: the piecewise-linear model by least squares (no corruption model)."""
    return _pl_kernels.pl_tile(y, w, lights, segments=segments, lam=LAMBDA_FLOOR, sigma_x2=1e12,
                               sbl=False, learn_tau=False)


def _pl_sbl_tile(y, w, lights, **params):
    """PL-SBL: the piecewise-linear model with SBL's sparse corruptions."""
    return _pl_kernels.pl_tile(y, w, lights, **params)


def _auto_tile(y, w, lights, *, sbl_max_iter=SBL_MAX_ITER, **params):
    """The default: SBL, and PL-SBL where its score test and evidence pick it (``_auto.py``)."""
    lam_test = gate_variance(params.get("lam_pl", params["lam"]))  # the score test's (_auto)
    return _pl_kernels.pl_tile(y, w, lights, choose=True, sbl_max_iter=sbl_max_iter,
                               lam_test=lam_test, **params)


@dataclass(frozen=True)
class SolverMethod:
    """One solver method: what the command line, ``solve``, near lights and the bench need.

    Attributes
    ----------
    name : str
        ``--method`` value and ``solve(method=...)``.
    help : str
        The method's words in ``ps-lab reconstruct --help`` (after its name, in parentheses).
    defaults : Mapping
        Every parameter ``solve`` accepts for it and its default (units of the pixel's robust
        scale; ``None``: estimated from the data).
    options : Mapping
        The :class:`~ps_lab.reconstruct.options.ReconstructOptions` solver fields
        (``--lambda`` ...) that apply, each to the ``solve`` keyword it sets.
    warm_up : tuple of str
        ``_warm_up.GROUPS`` whose kernels a run of it uses (compiled/loaded while images load).
    tile : callable or None
        Tile kernel with directional lights: ``tile(y, w, lights, **params)`` on (m, n)
        scaled observations, weights and (n, 3) lights, returning a ``_kernels.TileResult``.
        None: the method fits a band at once (``one_light_matrix``).
    near_tile : callable or None
        The same with per-pixel lights (m, n, 3); None: not available with near lights.
    label : str
        Its name in the bench's tables.
    estimates_noise : bool
        Takes a noise level (``noise_sigma``) and an outlier threshold derived from it.
    sbl_noise : bool
        Has SBL's noise variance ``lam``, by default per observation from the noise level, noise
        floor and each light's share (``noise_floor``, ``light_noise``).
    pl_noise : bool
        Fits the piecewise-linear model with its own noise level (``noise_sigma_pl``).
    one_light_matrix : bool
        Fits a whole band at once with one light matrix (R-PCA): not with near lights, bands not
        capped in size.
    chooses : bool
        Chooses per pixel between models (the default method, ``_auto.py``): its SBL candidate
        keeps SBL's iterations; with near lights it solves as ``near_fallback``.
    near_fallback : str or None
        The method near lights solve with instead (see ``chooses``).
    direct_tiles : callable or None
        A faster whole-tile path used instead of ``tile`` for directional lights (least squares:
        a few sums per pixel, ``_tiles.ls_tiles``).
    fixed : Mapping
        Kernel arguments the method always passes (not parameters of ``solve``).
    """

    name: str
    help: str
    defaults: Mapping = field(default_factory=dict)
    options: Mapping = field(default_factory=dict)
    warm_up: tuple[str, ...] = ("store", "tiles", "colour")
    tile: Callable | None = None
    near_tile: Callable | None = None
    label: str = ""
    estimates_noise: bool = True
    sbl_noise: bool = False
    pl_noise: bool = False
    one_light_matrix: bool = False
    chooses: bool = False
    near_fallback: str | None = None
    direct_tiles: Callable | None = None
    fixed: Mapping = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "defaults", MappingProxyType(dict(self.defaults)))
        object.__setattr__(self, "options", MappingProxyType(dict(self.options)))
        object.__setattr__(self, "fixed", MappingProxyType(dict(self.fixed)))
        if not self.label:
            object.__setattr__(self, "label", self.name)

    @property
    def segments(self) -> bool:
        """Piecewise-linear: reports each pixel's segment count."""
        return "segments" in self.defaults


_SBL_OPTIONS = {"lam": "lam", "sigma_x2": "sigma_x2", "max_iter": "max_iter", "tol": "tol"}
_SBL = {"lam": None, "sigma_x2": 1e6, "max_iter": SBL_MAX_ITER, "tol": None,
        "gamma_floor": 1e-10, "gamma_start": 1e3, "outlier_threshold": None,
        "noise_sigma": None, "noise_floor": None, "light_noise": None}
_PL_SBL = {"lam": None, "sigma_x2": 1e6, "max_iter": 20, "tol": None, "gamma_floor": 1e-10,
           "gamma_start": 1e3, "segments": 3, "outlier_threshold": None, "noise_sigma": None,
           "noise_floor": None, "light_noise": None, "noise_sigma_pl": None}

#: The solver table, in the order the command line lists the methods.
SOLVERS: tuple[SolverMethod, ...] = (
    SolverMethod(
        # per pixel SBL or PL-SBL, whichever predicts the pixel's kept observations better
        # (leave-one-out, docs/solvers.md); PL-SBL's options, its SBL candidate SBL's iterations
        "auto", "per pixel sbl or plsbl by evidence, default", defaults=_PL_SBL,
        options={**_SBL_OPTIONS, "segments": "segments"},
        warm_up=("store", "tiles", "colour", "l1", "pl"), tile=_auto_tile, near_tile=_auto_tile,
        sbl_noise=True, pl_noise=True, chooses=True, near_fallback="sbl"),
    SolverMethod(
        "ls", "Woodham", warm_up=("store", "tiles", "colour", "ls"), tile=_kernels.ls_tile,
        near_tile=_near_kernels.ls_tile_pp, label="LS", estimates_noise=False,
        direct_tiles=ls_tiles, fixed={"outlier_threshold": np.inf}),
    SolverMethod(
        "l1", "IRLS",
        defaults={"max_iter": 100, "tol": 1e-6, "delta": 1e-6, "outlier_threshold": None,
                  "noise_sigma": None},
        options={"max_iter": "max_iter", "tol": "tol"},
        warm_up=("store", "tiles", "colour", "l1"), tile=_kernels.l1_tile,
        near_tile=_near_kernels.l1_tile_pp, label="L1"),
    SolverMethod(
        "sbl", "robust", defaults=_SBL, options=_SBL_OPTIONS,
        # L1's kernel too: the noise estimate uses it
        warm_up=("store", "tiles", "colour", "l1", "sbl"), tile=_kernels.sbl_tile,
        near_tile=_near_kernels.sbl_tile_pp, label="SBL", sbl_noise=True),
    SolverMethod(
        "plls", "piecewise-linear diffuse", defaults={"segments": 3},
        options={"segments": "segments"}, warm_up=("store", "tiles", "colour", "pl"),
        tile=_pl_ls_tile, near_tile=_pl_ls_tile, estimates_noise=False),
    SolverMethod(
        "plsbl", "piecewise-linear diffuse, robust", defaults=_PL_SBL,
        options={**_SBL_OPTIONS, "segments": "segments"},
        warm_up=("store", "tiles", "colour", "l1", "pl"), tile=_pl_sbl_tile,
        near_tile=_pl_sbl_tile, sbl_noise=True, pl_noise=True),
    SolverMethod(
        "rpca", "low rank plus sparse, then least squares",
        defaults={"lam_sparse": None, "max_iter": 500, "tol": 1e-7, "rho": 1.5,
                  "outlier_threshold": None, "noise_sigma": None},
        options={"lam": "lam_sparse", "max_iter": "max_iter", "tol": "tol"},
        label="R-PCA", one_light_matrix=True),
)
#: The method of ``ps-lab reconstruct`` and ``ReconstructOptions`` when none is named.
DEFAULT_METHOD = "auto"
#: Every method's name, in table order.
METHODS: tuple[str, ...] = tuple(row.name for row in SOLVERS)
_BY_NAME = {row.name: row for row in SOLVERS}


def solver(name: str) -> SolverMethod:
    """The table row of method ``name``.

    Raises
    ------
    SolverInputError
        No such method.
    """
    row = _BY_NAME.get(name)
    if row is None:
        raise SolverInputError(f"unknown method {name!r}; choose one of {', '.join(METHODS)}")
    return row


def methods_with(option: str) -> tuple[str, ...]:
    """The methods (table order) that a :class:`ReconstructOptions` solver field applies to."""
    return tuple(row.name for row in SOLVERS if option in row.options)


def method_help() -> str:
    """The ``--method`` help: every method with its words."""
    return "Solver: " + ", ".join(f"{row.name} ({row.help})" for row in SOLVERS) + "."
