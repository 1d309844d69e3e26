"""The synthesis's per-sample loops compiled with numba (imported, and compiled or read from numba's
cache, on the first block synthesised; never at the import of the rig).

* ``harmonic_series``: weighted sums of cos(h phi), sin(h phi), h = 1..K, by the Chebyshev
  recurrence of ``crank.harmonic_stack`` (the same values), without the (2K, n) stack: tiles of
  ``TILE`` samples, the sample index innermost so that the compiler vectorises over it.
* ``two_input_df2t``: lfilter(num_u[p], den, u) + lfilter(num_du[p], den, du) for each output p in
  one pass: the two filters share their denominator, so one transposed direct form II state per
  output carries both (the sum of lfilter's two states).
"""

from __future__ import annotations

import numba
import numpy as np

TILE = 512  # samples per tile of harmonic_series (its scratch stays in the L1 cache)


@numba.njit(cache=True, error_model="numpy")
def harmonic_series(c1, s1, W, out):
    """out[i, k] = sum_h W[i, h-1] cos(h phi_k) + W[i, K+h-1] sin(h phi_k), h = 1..K.

    c1, s1: cos phi, sin phi, shape (n,); W: (m, 2K); out: (m, n)."""
    m = W.shape[0]
    K = W.shape[1] // 2
    n = c1.size
    cprev = np.empty(TILE)
    ccur = np.empty(TILE)
    sprev = np.empty(TILE)
    scur = np.empty(TILE)
    for k0 in range(0, n, TILE):
        t = min(TILE, n - k0)
        for q in range(t):
            cprev[q] = 1.0
            sprev[q] = 0.0
            ccur[q] = c1[k0 + q]
            scur[q] = s1[k0 + q]
        for i in range(m):
            wc = W[i, 0]
            ws = W[i, K]
            for q in range(t):
                out[i, k0 + q] = wc * ccur[q] + ws * scur[q]
        for h in range(1, K):  # harmonic h + 1 from h and h - 1
            for q in range(t):
                two_c1 = 2.0 * c1[k0 + q]
                cn = two_c1 * ccur[q] - cprev[q]
                sn = two_c1 * scur[q] - sprev[q]
                cprev[q] = ccur[q]
                sprev[q] = scur[q]
                ccur[q] = cn
                scur[q] = sn
            for i in range(m):
                wc = W[i, h]
                ws = W[i, K + h]
                for q in range(t):
                    out[i, k0 + q] += wc * ccur[q] + ws * scur[q]


@numba.njit(cache=True, error_model="numpy")
def two_input_df2t(num_u, num_du, den, u, du, z, out):
    """out[p] = lfilter(num_u[p], den, u) + lfilter(num_du[p], den, du), state z (P, n) in and out.

    num_u, num_du: (P, n+1), den: (n+1,) with den[0] == 1; u, du: (N,); out: (P, N)."""
    P = num_u.shape[0]
    n = den.size - 1
    N = u.size
    for k in range(N):
        x1 = u[k]
        x2 = du[k]
        for p in range(P):
            y = z[p, 0] + num_u[p, 0] * x1 + num_du[p, 0] * x2
            for i in range(n - 1):
                z[p, i] = z[p, i + 1] + num_u[p, i + 1] * x1 + num_du[p, i + 1] * x2 - den[i + 1] * y
            z[p, n - 1] = num_u[p, n] * x1 + num_du[p, n] * x2 - den[n] * y
            out[p, k] = y
