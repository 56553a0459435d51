"""The first run: kernels compiled ahead, one specialization each, and a compile that says so."""

from __future__ import annotations

import numpy as np
from numba import njit
from numba.core import event

from ps_lab.io import _coding_kernel, coding
from ps_lab.io.bands import ObservationStore, plan_bands
from ps_lab.reconstruct import _kernels, _near_kernels, _pl_kernels, _tiles, solve
from ps_lab.reconstruct._warm_up import METHOD_GROUPS, CompileNotice, warm_all

KERNELS = (_kernels._l1_kernel, _kernels._sbl_kernel, _pl_kernels._pl_kernel,
           _near_kernels._l1_kernel_pp, _near_kernels._sbl_kernel_pp, _coding_kernel._observe,
           _tiles._prepare_kernel, _tiles._store_kernel, _tiles._ls_direct)


def _signatures() -> dict[str, set]:
    return {k.py_func.__name__: set(k.signatures) for k in KERNELS}


def test_the_warm_up_compiles_every_type_the_wrappers_pass(rng):
    # What warm_all compiled (the install step) is all that the tile wrappers ever call: lam as
    # a scalar, per pixel or per observation (a read-only broadcast view would be a second
    # compile of a minute), inputs of other dtypes and layouts, per-pixel lights.
    warm_all(say=lambda line: None)
    warmed = _signatures()
    m, n = 5, 9
    y = rng.uniform(0.1, 1.0, (n, m)).astype(np.float32).T  # float32, Fortran order
    w = np.ones((m, n), np.float32)
    lights = rng.normal(size=(n, 3))
    for lam in (1e-4, np.full((m, 1), 1e-4), np.full((m, n), 1e-4)):
        _kernels.sbl_tile(y, w, lights, lam=lam, sigma_x2=1e6, max_iter=2, tol=1e-4,
                          gamma_floor=1e-10, gamma_start=1.0, outlier_threshold=np.inf)
        for choose in (False, True):
            _pl_kernels.pl_tile(y, w, lights, segments=2, lam=lam, lam_pl=lam, max_iter=2,
                                choose=choose, residuals=choose)
        _pl_kernels.pl_tile(y, w, np.broadcast_to(lights, (m, n, 3)), segments=2, lam=lam,
                            max_iter=2)
    _kernels.l1_tile(np.ascontiguousarray(y, np.float64), np.ascontiguousarray(w, np.float64),
                     lights, max_iter=2, tol=1e-6, delta=1e-6, outlier_threshold=np.inf)
    # the solvers' tile ends on observations of any dtype and layout, with a validity mask
    for obs in (y.T, y.T.astype(np.float64), np.asfortranarray(y.T), (y.T * 100).astype(int)):
        for method in ("ls", "sbl"):
            solve(obs, lights, method=method, valid=np.asfortranarray(obs > 0), threads=1)
    # the store's read of codes (8 and 16 bits, grey and colour) and of float values
    mask = np.ones((2, 3), bool)
    for dtype, channels in ((np.uint8, 3), (np.uint16, 1)):
        table = coding.code_table(8 * np.dtype(dtype).itemsize, channels, lambda v: v)
        store_coding = coding.Coding(np.dtype(dtype), channels, table, 250)
        with ObservationStore(plan_bands(mask, 4), n, mask, coding=store_coding,
                              in_memory=True, colours=3) as store:
            for i in range(n):
                store.write_frame(i, np.full((2, 3, channels), i, dtype))
            store.read(store.bands[0])
            store.read_colour(store.bands[0])
    with ObservationStore(plan_bands(mask, 4), n, mask, in_memory=True) as store:
        store.write_frame(0, np.ones((2, 3), np.float32), np.ones((2, 3), bool))
        store.read(store.bands[0])
    per_pixel = np.ascontiguousarray(np.broadcast_to(lights, (m, n, 3)))
    _near_kernels.l1_tile_pp(np.ascontiguousarray(y, np.float64),
                             np.ascontiguousarray(w, np.float64), per_pixel, max_iter=2,
                             tol=1e-6, delta=1e-6, outlier_threshold=np.inf)
    assert _signatures() == warmed
    assert all(len(sigs) >= 1 for sigs in warmed.values())


def test_every_method_with_kernels_is_warmed():
    from ps_lab.reconstruct import METHODS

    assert set(METHOD_GROUPS) == set(METHODS)
    # the store's read and the tile ends serve every method; L1 the noise estimate of the robust
    assert all({"store", "tiles"} <= set(groups) for groups in METHOD_GROUPS.values())
    robust = {"l1", "sbl", "plsbl", "auto"}
    assert all("l1" in METHOD_GROUPS[method] for method in robust)


def test_a_compile_says_what_it_is_doing_and_a_cached_call_says_nothing():
    said: list[str] = []
    notice = CompileNotice(said.append)

    @njit
    def _fresh_kernel(x):
        return x + 1.0

    with event.install_listener("numba:compile", notice):
        assert _fresh_kernel(1.0) == 2.0
        assert _fresh_kernel(2.0) == 3.0  # compiled: no second line
    assert len(said) == 1
    assert said[0].startswith("compiling solver kernels (first run only, ~")
    assert "_fresh_kernel" in said[0]
    assert [name for name, _, _ in notice.compiled] == ["_fresh_kernel"]
