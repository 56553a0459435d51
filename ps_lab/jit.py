"""The numba compile flags every kernel of the package shares (reconstruct's solvers, the
appearance fit): one definition below both, so that neither imports the other for them.
"""

from __future__ import annotations

__all__ = ["INLINE", "VECTOR"]

# The loops over the lights are vectorised (4 lights per AVX2 instruction) when numba may
# reassociate their sums and divides without Python's zero-division check: the sums then add in an
# order that depends on the CPU's vector width (rounding-level differences between CPUs and between
# two kernels; tests/helpers/tolerances.py derives how far they may go). No nnan/ninf:
# comparisons keep their IEEE meaning. The loops read one light table and write one per-pixel
# state array, so the compiler needs no aliasing checks between a dozen arrays (it gives up then).
# The helpers are inlined into the kernels (a call that passes arrays costs about as much as the
# loop over 40 lights), so the kernels carry the flags.
VECTOR = {"fastmath": {"reassoc", "contract", "nsz", "arcp"}, "error_model": "numpy"}
INLINE = {"inline": "always"}
