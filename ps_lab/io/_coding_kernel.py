"""The numba kernel of :func:`ps_lab.io.coding.observe_block` (imported on its first call).

Kept apart from :mod:`ps_lab.io.coding` so that reading images (code tables, the ``Coding`` of a
file) does not load numba: ``ps-lab calibrate`` never observes a band.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Codes per table up to which each light's products and quotients are tabulated first (8-bit):
#: a band's samples are then three lookups and two additions each.
SMALL_TABLE = 4096


@njit(nogil=True, cache=True, error_model="numpy")
def _observe(values, saturated, coded, table, clip, divisors, weights, grey, mode, threshold,
             use_threshold, lights, obs, valid, want_colour, colour):
    n, p, c = values.shape
    size = table.shape[0]
    small = coded and size <= SMALL_TABLE
    # per light, the float32 operations of the rule on every code (the same bits as on a pixel)
    quot = np.empty((3, size if small else 1), np.float32)  # v_c / d_c (colour; one channel)
    prod = np.empty((3, size if small else 1), np.float32)  # v_c * w_c (mean of three)
    for a in range(n):
        light = lights[a]
        g = grey[light]
        d0, d1, d2 = divisors[light, 0], divisors[light, 1], divisors[light, 2]
        w0, w1, w2 = weights[light, 0], weights[light, 1], weights[light, 2]
        if small:
            for k in range(size):
                if c == 3:
                    quot[0, k] = table[k, 0] / d0
                    quot[1, k] = table[k, 1] / d1
                    quot[2, k] = table[k, 2] / d2
                    prod[0, k] = table[k, 0] * w0
                    prod[1, k] = table[k, 1] * w1
                    prod[2, k] = table[k, 2] * w2
                else:
                    quot[0, k] = table[k, 0] / g
            for q in range(p):
                k0 = int(values[a, q, 0])
                if c == 3:
                    k1 = int(values[a, q, 1])
                    k2 = int(values[a, q, 2])
                    if mode < 0:
                        o = (prod[0, k0] + prod[1, k1]) + prod[2, k2]
                    elif mode == 0:
                        o = quot[0, k0]
                    elif mode == 1:
                        o = quot[1, k1]
                    else:
                        o = quot[2, k2]
                    ok = k0 < clip and k1 < clip and k2 < clip
                    if want_colour:
                        colour[a, q, 0] = quot[0, k0]
                        colour[a, q, 1] = quot[1, k1]
                        colour[a, q, 2] = quot[2, k2]
                else:
                    o = quot[0, k0]
                    ok = k0 < clip
                obs[a, q] = o
                if use_threshold:
                    ok = ok and o > threshold
                valid[a, q] = ok
            continue
        for q in range(p):
            bad = False
            if coded:
                k0 = int(values[a, q, 0])
                v0 = table[k0, 0]
                bad = k0 >= clip
                if c == 3:
                    k1 = int(values[a, q, 1])
                    k2 = int(values[a, q, 2])
                    v1 = table[k1, 1]
                    v2 = table[k2, 2]
                    bad = bad or k1 >= clip or k2 >= clip
                else:
                    v1 = v0
                    v2 = v0
            else:
                v0 = np.float32(values[a, q, 0])
                if c == 3:
                    v1 = np.float32(values[a, q, 1])
                    v2 = np.float32(values[a, q, 2])
                else:
                    v1 = v0
                    v2 = v0
                bad = saturated[a, q]
            if c == 1:
                o = v0 / g
            elif mode < 0:
                o = (v0 * w0 + v1 * w1) + v2 * w2
            elif mode == 0:
                o = v0 / d0
            elif mode == 1:
                o = v1 / d1
            else:
                o = v2 / d2
            obs[a, q] = o
            ok = not bad
            if use_threshold:
                ok = ok and o > threshold
            valid[a, q] = ok
            if want_colour:
                colour[a, q, 0] = v0 / d0
                colour[a, q, 1] = v1 / d1
                colour[a, q, 2] = v2 / d2
