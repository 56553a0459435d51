"""The solver table (reconstruct/methods.py) is the one place that lists the methods.

Every row is wired through the command line, the options, ``solve``, near lights, the warm-up and
the bench; and no other module lists method names (adding a solver is one row and its kernel).
"""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from ps_lab.bench import paper, real
from ps_lab.commands.reconstruct import Method, MethodOption
from ps_lab.reconstruct import METHODS, SolverInputError, solve
from ps_lab.reconstruct._warm_up import GROUPS, METHOD_GROUPS
from ps_lab.reconstruct.methods import SOLVERS, method_help, solver
from ps_lab.reconstruct.near import solve_near
from ps_lab.reconstruct.options import SOLVER_OPTIONS, ReconstructOptions

ROOT = Path(__file__).resolve().parents[1]
# Lists of these names that are not lists of methods: the warm-up's kernel groups (named after
# the kernels), the default method's candidate models, and the paper's experiment (the four
# methods the reproduced paper compares).
NOT_METHOD_LISTS = {
    ("reconstruct/_warm_up.py", "GROUPS"),
    ("reconstruct/_auto.py", "MODELS"),
    ("ps_lab/bench/paper.py", "methods"),
    ("ps_lab/bench/paper.py", "refine_methods"),
    ("ps_lab/bench/paper.py", "base"),
}


def test_every_row_is_a_cli_choice_with_its_help() -> None:
    assert [m.value for m in Method] == list(METHODS) == [row.name for row in SOLVERS]
    assert MethodOption.__metadata__[0].help == method_help()
    for row in SOLVERS:
        assert f"{row.name} ({row.help})" in method_help()


def test_every_row_is_warmed_with_existing_groups() -> None:
    assert set(METHOD_GROUPS) == set(METHODS)
    for row in SOLVERS:
        assert set(row.warm_up) <= set(GROUPS), row.name


def test_every_row_is_in_the_bench() -> None:
    assert tuple(real.METHODS) == METHODS
    assert set(paper.METHOD_LABELS) == set(METHODS)
    assert set(real.columns()) >= set(METHODS)


def test_options_apply_as_the_table_says() -> None:
    for name, (flag, methods) in SOLVER_OPTIONS.items():
        value = 2 if name in ("max_iter", "segments") else 0.5
        for row in SOLVERS:
            if row.name in methods:
                options = ReconstructOptions(method=row.name, **{name: value})
                assert options.solver_parameters() == {row.options[name]: value}
                assert row.options[name] in row.defaults
            else:
                with pytest.raises(SolverInputError, match=f"{flag} does not apply"):
                    ReconstructOptions(method=row.name, **{name: value})


def test_every_row_solves_with_its_defaults() -> None:
    rng = np.random.default_rng(40)
    lights = rng.normal(size=(12, 3))
    lights[:, 2] = np.abs(lights[:, 2]) + 1.0
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    normal = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    obs = np.tile(np.maximum(lights @ normal, 0.0)[:, None], (1, 6))
    obs += 1e-3 * rng.standard_normal(obs.shape)
    per_pixel = np.broadcast_to(lights, (6, 12, 3)).copy()
    for row in SOLVERS:
        sol = solve(obs, lights, method=row.name, threads=1, **dict(row.defaults))
        # noise-level data, 12 lights: every method is within a degree of the normal
        assert np.degrees(np.arccos(np.clip(sol.normals @ normal, -1, 1))).max() < 1.0, row.name
        assert sol.params["method"] == row.name
        if row.near_tile is None:
            with pytest.raises(SolverInputError, match="one light matrix"):
                solve_near(obs, per_pixel, method=row.name, threads=1)
        else:
            near = solve_near(obs, per_pixel, method=row.name, threads=1)
            assert np.degrees(np.arccos(np.clip(near.normals @ normal, -1, 1))).max() < 1.0
    with pytest.raises(SolverInputError, match="unknown method 'nope'"):
        solver("nope")


def _method_lists(path: Path):
    """(line, assigned name, method names) of each literal listing two or more method names."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    owner: dict[int, str] = {}
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, ast.Assign):
            targets = node.targets
        elif isinstance(node, (ast.AnnAssign, ast.AugAssign)):
            targets = [node.target]
        for target in targets:
            name = getattr(target, "id", getattr(target, "attr", ""))
            for inner in ast.walk(node):
                owner.setdefault(id(inner), name)
    for node in ast.walk(tree):
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            items = node.elts
        elif isinstance(node, ast.Dict):
            items = [k for k in node.keys if k is not None]
        else:
            continue
        names = [e.value for e in items if isinstance(e, ast.Constant) and e.value in METHODS]
        if len(names) >= 2:
            yield node.lineno, owner.get(id(node), ""), names


def test_no_module_but_the_table_lists_methods() -> None:
    found = []
    for folder in ("reconstruct", "ps_lab", "capture", "calibration"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            if rel == "reconstruct/methods.py" or any(p.is_symlink() for p in path.parents):
                continue
            for line, name, names in _method_lists(path):
                if (rel, name) not in NOT_METHOD_LISTS:
                    found.append(f"{rel}:{line} {name} {names}")
    assert found == [], "list methods in reconstruct/methods.py only:\n" + "\n".join(found)
