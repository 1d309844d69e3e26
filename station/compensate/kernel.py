"""The compensation's per-sample loop compiled with numba: the estimate and the variance's
coefficient term of every output sample in one pass over the signal.

For output n and window x_n = (x[n], x[n-1], ..., x[n-taps+1]): y[n] = w_0 . x_n and
var[n] = var0 + sum_{i>=1} (w_i . x_n)^2, with w_0 = b and w_i = sqrt(lambda_i) v_i the scaled
eigenvectors of U_b (``apply.Compensator``).  Each sample's sums run over the taps in one fixed
order (vectorised by the compiler, re-associated the same way for every sample), so a sample's
numbers do not depend on where a block starts: streaming and one pass agree to the last bit.
Compiled on first use (``cache=True``: once per installation).
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

# re-association lets the compiler vectorise each sum over the taps; no assumption about inf/NaN
# (an overflow must reach the caller's check)
_FLAGS = {"reassoc", "contract", "nsz", "arcp"}


@numba.njit(cache=True, fastmath=_FLAGS, error_model="numpy")
def estimate_and_variance(xe: FloatArray, w_rev: FloatArray, var0: float) -> tuple[FloatArray, FloatArray]:
    """``xe`` (n + taps - 1,): the block preceded by the taps - 1 samples before it; ``w_rev``
    (1 + r, taps): the rows w_i reversed in time (w_rev[i, k] = w_i[taps - 1 - k]); ``var0`` the
    noise term.  Returns y (n,) and var (n,) in the units of w_0 x and its square."""
    rows, taps = w_rev.shape
    n = xe.size - taps + 1
    y = np.empty(n)
    var = np.empty(n)
    for i in range(n):
        s0 = 0.0
        for k in range(taps):
            s0 += w_rev[0, k] * xe[i + k]
        acc = var0
        for j in range(1, rows):
            s = 0.0
            for k in range(taps):
                s += w_rev[j, k] * xe[i + k]
            acc += s * s
        y[i] = s0
        var[i] = acc
    return y, var
