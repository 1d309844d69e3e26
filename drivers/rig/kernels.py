"""The synthesis's per-sample loops compiled with numba (imported, and compiled or read from numba's
cache, on the first block synthesised; never at the import of the rig).

* ``harmonic_series``: weighted sums of cos(h phi), sin(h phi), h = 1..K, by the Chebyshev
  recurrence of ``crank.harmonic_stack`` (the same values), without the (2K, n) stack: tiles of
  ``TILE`` samples, the sample index innermost so that the compiler vectorises over it.
* ``two_input_df2t``: lfilter(num_u[p], den, u) + lfilter(num_du[p], den, du) for each output p in
  one pass: the two filters share their denominator, so one transposed direct form II state per
  output carries both (the sum of lfilter's two states).
* ``standard_normal``, ``fill_standard_normal``: the rig's noise, counter-based standard normal draws
  (draw k of a stream a function of its key and k alone).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

TILE = 512  # samples per tile of harmonic_series (its scratch stays in the L1 cache)
SYNTH_TILE = 256  # samples per tile of synth_block: one row of crank.cos_sin's rotations (crank.ROTATION_ROW)
F64 = NDArray[np.float64]  # the kernels' arrays (their shapes in each docstring)
I16 = NDArray[np.int16]
I64 = NDArray[np.int64]
U64 = NDArray[np.uint64]


@numba.njit(cache=True, error_model="numpy")
def harmonic_series(c1: F64, s1: F64, W: F64, out: F64) -> None:
    """out[i, k] = sum_h W[i, h-1] cos(h phi_k) + W[i, K+h-1] sin(h phi_k), h = 1..K.

    c1, s1: cos phi, sin phi, shape (n,); W: (m, 2K); out: (m, n)."""
    m = W.shape[0]
    n = c1.size
    rows = np.empty((m, TILE))
    cprev = np.empty(TILE)
    ccur = np.empty(TILE)
    sprev = np.empty(TILE)
    scur = np.empty(TILE)
    for k0 in range(0, n, TILE):
        t = min(TILE, n - k0)
        _harmonics_tile(c1[k0:k0 + t], s1[k0:k0 + t], t, W, m, rows, cprev, ccur, sprev, scur)
        for i in range(m):
            for q in range(t):
                out[i, k0 + q] = rows[i, q]


@numba.njit(cache=True, error_model="numpy")
def two_input_df2t(num_u: F64, num_du: F64, den: F64, u: F64, du: F64, z: F64, out: F64) -> None:
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


@numba.njit(cache=True, error_model="numpy")
def _harmonics_tile(c1: F64, s1: F64, t: int, W: F64, rows: int, out: F64,
                    cprev: F64, ccur: F64, sprev: F64, scur: F64) -> None:
    """The harmonic sums of ``harmonic_series`` on one tile: out[i, q] for the first ``rows`` rows of W
    and q < t (t at most the length of the scratch rows cprev, ccur, sprev, scur).  The synthesis's
    1, 2 and 4 rows each by a pass of its own (``_harmonics_rows``)."""
    if rows == 4:
        _harmonics_rows(c1, s1, t, W, 4, out, cprev, ccur, sprev, scur)
    elif rows == 2:
        _harmonics_rows(c1, s1, t, W, 2, out, cprev, ccur, sprev, scur)
    elif rows == 1:
        _harmonics_rows(c1, s1, t, W, 1, out, cprev, ccur, sprev, scur)
    else:
        for i in range(0, rows, 4):
            r = min(4, rows - i)
            if r == 4:
                _harmonics_rows(c1, s1, t, W[i:i + 4], 4, out[i:i + 4], cprev, ccur, sprev, scur)
            elif r == 2 or r == 3:
                _harmonics_rows(c1, s1, t, W[i:i + 2], 2, out[i:i + 2], cprev, ccur, sprev, scur)
            if r == 1 or r == 3:
                _harmonics_rows(c1, s1, t, W[i + r - 1:i + r], 1, out[i + r - 1:i + r], cprev, ccur, sprev, scur)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _chebyshev(two_c1: float, c: float, s: float, c_prev: float, s_prev: float) -> tuple[float, float]:
    """The next harmonic's cos and sin from this one's and the one before (2 cos(phi) = two_c1)."""
    return two_c1 * c - c_prev, two_c1 * s - s_prev


@numba.njit(cache=True, error_model="numpy")
def _harmonics_rows(c1: F64, s1: F64, t: int, W: F64, R: int, out: F64,
                    cprev: F64, ccur: F64, sprev: F64, scur: F64) -> None:
    """``_harmonics_tile`` for R rows (a literal: compiled for each of 1, 2 and 4, the row branches gone and
    the tile's loops vectorised): each pass over the tile takes the recurrence two harmonics on and adds
    both to every row's sum (the operations, and their order, of a harmonic and a row at a time; a third
    of the memory traffic).  Not inlined: numba's inlining of it took the kernels' compilation from 18 s
    to 58 s of CPU."""
    numba.literally(R)
    K = W.shape[1] // 2
    w = np.zeros((4, 4))  # row i: this pass's weights (cos, sin of the first harmonic, of the second)
    for i in range(R):
        w[i, 0] = W[i, 0]
        w[i, 1] = W[i, K]
    a0, b0, a1, b1, a2, b2, a3, b3 = w[0, 0], w[0, 1], w[1, 0], w[1, 1], w[2, 0], w[2, 1], w[3, 0], w[3, 1]
    for q in range(t):
        c = c1[q]
        s = s1[q]
        cprev[q] = 1.0
        sprev[q] = 0.0
        ccur[q] = c
        scur[q] = s
        out[0, q] = a0 * c + b0 * s
        if R > 1:
            out[1, q] = a1 * c + b1 * s
        if R > 2:
            out[2, q] = a2 * c + b2 * s
            out[3, q] = a3 * c + b3 * s
    h = 1
    while h < K:
        two = h + 1 < K  # two harmonics in this pass
        for i in range(R):
            w[i, 0] = W[i, h]
            w[i, 1] = W[i, K + h]
            w[i, 2] = W[i, h + 1] if two else 0.0
            w[i, 3] = W[i, K + h + 1] if two else 0.0
        a0, b0, c0, d0 = w[0, 0], w[0, 1], w[0, 2], w[0, 3]
        a1, b1, c1_, d1 = w[1, 0], w[1, 1], w[1, 2], w[1, 3]
        a2, b2, c2, d2 = w[2, 0], w[2, 1], w[2, 2], w[2, 3]
        a3, b3, c3, d3 = w[3, 0], w[3, 1], w[3, 2], w[3, 3]
        if two:
            for q in range(t):
                two_c1 = 2.0 * c1[q]
                cc, sc = ccur[q], scur[q]
                cn, sn = _chebyshev(two_c1, cc, sc, cprev[q], sprev[q])
                cm, sm = _chebyshev(two_c1, cn, sn, cc, sc)
                cprev[q] = cn
                sprev[q] = sn
                ccur[q] = cm
                scur[q] = sm
                out[0, q] = (out[0, q] + (a0 * cn + b0 * sn)) + (c0 * cm + d0 * sm)
                if R > 1:
                    out[1, q] = (out[1, q] + (a1 * cn + b1 * sn)) + (c1_ * cm + d1 * sm)
                if R > 2:
                    out[2, q] = (out[2, q] + (a2 * cn + b2 * sn)) + (c2 * cm + d2 * sm)
                    out[3, q] = (out[3, q] + (a3 * cn + b3 * sn)) + (c3 * cm + d3 * sm)
            h += 2
        else:
            for q in range(t):
                cc, sc = ccur[q], scur[q]
                cn, sn = _chebyshev(2.0 * c1[q], cc, sc, cprev[q], sprev[q])
                cprev[q] = cc
                sprev[q] = sc
                ccur[q] = cn
                scur[q] = sn
                out[0, q] += a0 * cn + b0 * sn
                if R > 1:
                    out[1, q] += a1 * cn + b1 * sn
                if R > 2:
                    out[2, q] += a2 * cn + b2 * sn
                    out[3, q] += a3 * cn + b3 * sn
            h += 1


# -- the noise: counter-based standard normal draws ------------------------------------------------
# Draw k of a stream is a function of the stream's key and of k alone, not of how a run is cut into
# blocks: ``synth_block`` draws each sample's noise where it adds it, the staged synthesis a block at a
# time (``fill_standard_normal``), and both give the same bits.  Uniforms: SplitMix64's output function
# (Steele, Lea & Flood 2014) on the Weyl sequence key + (k + 1) gamma (the generator passes BigCrush;
# two streams of random 64-bit keys overlap within a run with negligible probability).  Normals: the
# ziggurat of Marsaglia & Tsang (2000) with 256 layers and 52-bit abscissae, the steps of numpy's
# ``Generator.standard_normal`` (its tables recomputed here); the rare rejections (about 1 % of
# draws) take their further uniforms from a sub-stream of (key, k).  (In this file, not a module of
# its own: numba's cache of ``synth_block``, which inlines the draw, is invalidated by changes to its
# own file only.)

GAMMA = np.uint64(0x9E3779B97F4A7C15)  # SplitMix64's Weyl increment (the golden ratio's 64 bits)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_SUB = np.uint64(0xD1B54A32D192ED03)  # offsets a draw's sub-stream (its rejections' uniforms) from the stream
_S8, _S9, _S11, _S27, _S30, _S31 = (np.uint64(s) for s in (8, 9, 11, 27, 30, 31))
_ONE = np.uint64(1)
_LOW8 = np.uint64(0xFF)
_LOW52 = np.uint64(0x000FFFFFFFFFFFFF)

ZIGGURAT_R = 3.6541528853610088  # where the ziggurat's base strip meets the tail
_ZIGGURAT_V = 0.00492867323399  # the area of each of the 256 layers (normal density without 1/sqrt(2 pi))
_INV_R = 1.0 / ZIGGURAT_R


def _ziggurat_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ki, wi, fi), each (256,): Marsaglia & Tsang's zigset for 256 layers and 52-bit abscissae."""
    m = 2.0 ** 52
    ki = np.zeros(256, dtype=np.int64)
    wi = np.zeros(256)
    fi = np.zeros(256)
    dn = tn = ZIGGURAT_R
    q = _ZIGGURAT_V / math.exp(-0.5 * dn * dn)
    ki[0] = int((dn / q) * m)
    wi[0], wi[255] = q / m, dn / m
    fi[0], fi[255] = 1.0, math.exp(-0.5 * dn * dn)
    for i in range(254, 0, -1):
        dn = math.sqrt(-2.0 * math.log(_ZIGGURAT_V / dn + math.exp(-0.5 * dn * dn)))
        ki[i + 1] = int((dn / tn) * m)
        tn = dn
        fi[i] = math.exp(-0.5 * dn * dn)
        wi[i] = dn / m
    return ki, wi, fi


_KI, _WI, _FI = _ziggurat_tables()


@numba.njit(cache=True, inline="always")
def mix64(z: np.uint64) -> np.uint64:
    """SplitMix64's output function: a bijection of uint64 whose outputs on a Weyl sequence are uniform."""
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@numba.njit(cache=True, inline="always")
def _unit(u: np.uint64) -> float:
    """A uint64 as a double in [0, 1) (its top 53 bits)."""
    return np.float64(u >> _S11) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True, inline="always")
def standard_normal(key: np.uint64, k: int) -> float:
    """Draw k (int, >= 0) of the stream with the uint64 ``key``: one standard normal.  Branch-free
    but for the rare rejection (the sign as a factor, the 52-bit abscissa as a signed integer: half
    the time of the literal form, the same bits)."""
    r = mix64(key + (np.uint64(k) + _ONE) * GAMMA)
    i = np.int64(r & _LOW8)
    rabs = np.int64((r >> _S9) & _LOW52)
    x: float = np.float64(rabs) * (1.0 - 2.0 * np.float64(np.int64((r >> _S8) & _ONE))) * _WI[i]
    if rabs < _KI[i]:
        return x
    return _rejected(key, k, np.uint64(i), np.uint64(rabs), x)


@numba.njit(cache=True)
def _rejected(key: np.uint64, k: int, i: np.uint64, rabs: np.uint64, x: float) -> float:
    """The ziggurat's rare path for draw k (a wedge or the tail), with the uniforms of its sub-stream."""
    s = mix64((key ^ _SUB) + (np.uint64(k) + _ONE) * GAMMA)
    j = np.uint64(0)
    while True:
        if i == 0:  # the tail beyond ZIGGURAT_R (Marsaglia 1964)
            while True:
                j += _ONE
                xx: float = -_INV_R * np.log1p(-_unit(mix64(s + j * GAMMA)))
                j += _ONE
                yy = -np.log1p(-_unit(mix64(s + j * GAMMA)))
                if yy + yy > xx * xx:
                    return -(ZIGGURAT_R + xx) if (rabs >> _S8) & _ONE else ZIGGURAT_R + xx
        j += _ONE
        if (_FI[i - 1] - _FI[i]) * _unit(mix64(s + j * GAMMA)) + _FI[i] < np.exp(-0.5 * x * x):
            return x
        j += _ONE
        r = mix64(s + j * GAMMA)
        i = r & _LOW8
        rabs = (r >> _S9) & _LOW52
        x = np.float64(rabs) * _WI[i]
        if (r >> _S8) & _ONE:
            x = -x
        if np.int64(rabs) < _KI[i]:
            return x


@numba.njit(cache=True)
def fill_standard_normal(key: np.uint64, start: int, out: F64) -> None:
    """out[q] = draw start + q of the stream ``key`` (uint64), q < out.size."""
    for q in range(out.size):
        out[q] = standard_normal(key, start + q)


MAX_ORDER = 8  # the highest filter order synth_block runs (its states are tuples of this length)
State = tuple[float, float, float, float, float, float, float, float]  # a filter's state held in registers


@numba.njit(cache=True, error_model="numpy", inline="always")
def _df2t(b: F64, c: F64, a: F64, n: int, z: State, x1: float, x2: float) -> tuple[float, State]:
    """One sample of ``two_input_df2t`` for one output of order n <= MAX_ORDER (the same operations):
    b, c, a its num_u, num_du, den; z its state padded with zeros to a tuple of MAX_ORDER (kept in
    registers, not in memory, across the samples).  Returns (y, the next state)."""
    z0, z1, z2, z3, z4, z5, z6, z7 = z
    y = z0 + b[0] * x1 + c[0] * x2
    if n == 1:
        return y, (b[1] * x1 + c[1] * x2 - a[1] * y, z1, z2, z3, z4, z5, z6, z7)
    z0 = z1 + b[1] * x1 + c[1] * x2 - a[1] * y
    if n == 2:
        return y, (z0, b[2] * x1 + c[2] * x2 - a[2] * y, z2, z3, z4, z5, z6, z7)
    z1 = z2 + b[2] * x1 + c[2] * x2 - a[2] * y
    if n == 3:
        return y, (z0, z1, b[3] * x1 + c[3] * x2 - a[3] * y, z3, z4, z5, z6, z7)
    z2 = z3 + b[3] * x1 + c[3] * x2 - a[3] * y
    if n == 4:
        return y, (z0, z1, z2, b[4] * x1 + c[4] * x2 - a[4] * y, z4, z5, z6, z7)
    z3 = z4 + b[4] * x1 + c[4] * x2 - a[4] * y
    if n == 5:
        return y, (z0, z1, z2, z3, b[5] * x1 + c[5] * x2 - a[5] * y, z5, z6, z7)
    z4 = z5 + b[5] * x1 + c[5] * x2 - a[5] * y
    if n == 6:
        return y, (z0, z1, z2, z3, z4, b[6] * x1 + c[6] * x2 - a[6] * y, z6, z7)
    z5 = z6 + b[6] * x1 + c[6] * x2 - a[6] * y
    if n == 7:
        return y, (z0, z1, z2, z3, z4, z5, b[7] * x1 + c[7] * x2 - a[7] * y, z7)
    z6 = z7 + b[7] * x1 + c[7] * x2 - a[7] * y
    return y, (z0, z1, z2, z3, z4, z5, z6, b[8] * x1 + c[8] * x2 - a[8] * y)


@numba.njit(cache=True, error_model="numpy")
def _filter_loop(b: F64, c: F64, a: F64, N: int, z: State, x1: F64, x2: F64, y: F64, t: int) -> State:
    """y[q] = ``_df2t`` of x1[q], x2[q] for q < t, state z in and out; compiled for each order N (a
    literal: the loop without branches, its state in registers), N == 0 for any order."""
    numba.literally(N)
    n = a.size - 1
    for q in range(t):
        y[q], z = _df2t(b, c, a, N if N > 0 else n, z, x1[q], x2[q])
    return z


@numba.njit(cache=True, error_model="numpy")
def _filter_pass(b: F64, c: F64, a: F64, n: int, z: State, x1: F64, x2: F64, y: F64, t: int) -> State:
    """``_filter_loop`` for the order n: the second order (the sensor, the rigid mechanics) compiled for
    its own."""
    if n == 2:
        return _filter_loop(b, c, a, 2, z, x1, x2, y, t)
    return _filter_loop(b, c, a, 0, z, x1, x2, y, t)


@numba.njit(cache=True, error_model="numpy")
def _lp_sensor_loop(b: F64, c: F64, a: F64, N: int, z: State, x1: F64, x2: F64, y: F64, bs: F64, cs: F64,
                    as_: F64, zs: State, x1s: F64, x2s: F64, ys: F64, t: int) -> tuple[State, State]:
    """``_filter_loop`` of the low-pass (order N) and of the second-order sensor in one loop: two
    independent recurrences side by side."""
    numba.literally(N)
    n = a.size - 1
    for q in range(t):
        y[q], z = _df2t(b, c, a, N if N > 0 else n, z, x1[q], x2[q])
        ys[q], zs = _df2t(bs, cs, as_, 2, zs, x1s[q], x2s[q])
    return z, zs


@numba.njit(cache=True, error_model="numpy")
def _lp_sensor_pass(b: F64, c: F64, a: F64, n: int, z: State, x1: F64, x2: F64, y: F64, bs: F64, cs: F64,
                    as_: F64, zs: State, x1s: F64, x2s: F64, ys: F64, t: int) -> tuple[State, State]:
    """``_lp_sensor_loop`` for the low-pass's order n: the fourth compiled for its own."""
    if n == 4:
        return _lp_sensor_loop(b, c, a, 4, z, x1, x2, y, bs, cs, as_, zs, x1s, x2s, ys, t)
    return _lp_sensor_loop(b, c, a, 0, z, x1, x2, y, bs, cs, as_, zs, x1s, x2s, ys, t)


@numba.njit(cache=True, error_model="numpy")
def _mech_loop(num_u: F64, num_du: F64, den: F64, N: int, z0: State, z1: State, x1: F64, x2: F64, y0: F64,
               y1: F64, t: int) -> tuple[State, State]:
    """The mechanics' two outputs (the force and its rate) side by side, order N as in ``_filter_loop``."""
    numba.literally(N)
    n = den.size - 1
    b0, c0, b1, c1 = num_u[0], num_du[0], num_u[1], num_du[1]
    for q in range(t):
        y0[q], z0 = _df2t(b0, c0, den, N if N > 0 else n, z0, x1[q], x2[q])
        y1[q], z1 = _df2t(b1, c1, den, N if N > 0 else n, z1, x1[q], x2[q])
    return z0, z1


@numba.njit(cache=True, error_model="numpy")
def _mech_pass(num_u: F64, num_du: F64, den: F64, n: int, P: int, z0: State, z1: State, x1: F64, x2: F64,
               y0: F64, y1: F64, t: int) -> tuple[State, State]:
    """The mechanics' P outputs over a tile: the coupled chain's two (order 4) compiled for their own."""
    if P == 1:
        return _filter_pass(num_u[0], num_du[0], den, n, z0, x1, x2, y0, t), z1
    if n == 4:
        return _mech_loop(num_u, num_du, den, 4, z0, z1, x1, x2, y0, y1, t)
    return _mech_loop(num_u, num_du, den, 0, z0, z1, x1, x2, y0, y1, t)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _load_state(z: F64, p: int) -> State:
    """Row p of a (P, n <= MAX_ORDER) state array as the padded tuple ``_df2t`` carries."""
    n = z.shape[1]
    return (z[p, 0] if n > 0 else 0.0, z[p, 1] if n > 1 else 0.0, z[p, 2] if n > 2 else 0.0,
            z[p, 3] if n > 3 else 0.0, z[p, 4] if n > 4 else 0.0, z[p, 5] if n > 5 else 0.0,
            z[p, 6] if n > 6 else 0.0, z[p, 7] if n > 7 else 0.0)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _store_state(zt: State, z: F64, p: int) -> None:
    """Write the tuple state zt back to row p of z (its first n entries)."""
    n = z.shape[1]
    z0, z1, z2, z3, z4, z5, z6, z7 = zt
    for i, zi in enumerate((z0, z1, z2, z3, z4, z5, z6, z7)):
        if i < n:
            z[p, i] = zi


@numba.njit(cache=True, error_model="numpy")
def _rotate_tile(base: F64, table: F64, j: int, t: int, c: F64, s: F64) -> None:
    """c + i s = base[j] * table[q] for q < t, the product written out as ``crank.cos_sin`` does;
    base, table: (2, rows), (2, SYNTH_TILE) real and imaginary parts."""
    br = base[0, j]
    bi = base[1, j]
    for q in range(t):
        c[q] = br * table[0, q] - bi * table[1, q]
        s[q] = br * table[1, q] + bi * table[0, q]


@numba.njit(cache=True, error_model="numpy", inline="always")
def _taylor_shift(c: F64, s: F64, om: F64, t: int, delay: float, skew: float, k: int, T: float, alpha: float,
                  centre: float, cx: F64, sx: F64) -> None:
    """cx + i sx = (c + i s) exp(-i (delta_q - centre)), q < t, the lag delta_q of sample k + q (rad) by
    the Taylor series of ``crank.shift_cos_sin`` (|delta_q - centre| < 0.1 rad)."""
    for q in range(t):
        d = delay - skew * ((k + q) * T)
        delta = om[q] * d - 0.5 * alpha * d * d - centre
        d2 = delta * delta
        cd = 1.0 - d2 * (0.5 - d2 * (1.0 / 24.0 - d2 / 720.0))
        sd = delta * (1.0 - d2 * (1.0 / 6.0 - d2 * (1.0 / 120.0 - d2 / 5040.0)))
        cx[q] = c[q] * cd + s[q] * sd
        sx[q] = s[q] * cd - c[q] * sd


@numba.njit(cache=True, error_model="numpy")
def _quantise(v: F64, lsb: float, lo: float, hi: float, codes: I16) -> int:
    """codes = clip(rint(v / lsb), lo, hi) as int16; returns how many were clipped."""
    clipped = 0
    for k in range(v.size):
        c = np.rint(v[k] / lsb)
        if c < lo:
            clipped += 1
            c = lo
        elif c > hi:
            clipped += 1
            c = hi
        codes[k] = np.int16(c)
    return clipped


# C901: one fused pass over the tiles on purpose (every stage's scratch stays in the L1 cache); the filters
# keep their states in registers across a tile (the same filter with its state in memory measured 6x
# slower); the staged path is RigSynth.advance_stages
@numba.njit(cache=True, error_model="numpy")
def synth_block(fl: F64, ints: I64, crank_base: F64, crank_tab: F64, crank_cs: F64, Wc: F64,  # noqa: C901
                mech: F64, mech_z: F64, lp: F64, lp_z: F64, mains_base: F64, mains_tab: F64, Wm: F64,
                keys: U64, shift_cs: F64, sen: F64, sen_z: F64, out_x: F64, out_fV: F64, out_dV: F64,
                codes_d: I16, codes_f: I16) -> int:
    """One block of ``synth.RigSynth``: every stage of its signal chain for each tile of SYNTH_TILE samples
    (the crank's and the mains' harmonics and every elementwise stage vectorised over the tile; the
    mechanics' outputs side by side in one loop over it, then the conditioner's low-pass beside the
    sensor's resonance in another, each loop compiled for its filter order: ``_mech_pass``,
    ``_lp_sensor_pass``), the same operations as the staged numpy path in the same order, so the same
    samples to the bit.  Returns the number of clipped samples (both channels).

    fl (float64): [T, f0, rate, alpha, g, S, capacity, quadratic, cubic, gain, offset, drift_rate,
    drift_quadratic, noise_V, cd, sd, delay, skew, disp_gain, disp_noise_scale, lsb_d, lsb_f, lo, hi,
    centre]
    (T s; f0 Hz; rate Hz/s; alpha rad/s^2; the rest as in ``params``); ints (int64): [n, k_abs,
    ramp, has_nl, has_lp, has_drift, has_mains, has_fnoise, shift_mode, has_sen, has_dnoise];
    shift_mode 0 none, 1 constant (cd, sd), 2 Taylor of the per-sample lag, 3 given (shift_cs), 4 the
    constant lag centre (rad; its cos and sin cd, sd) and the Taylor series of the per-sample lag less it.
    crank_base, crank_tab, mains_base, mains_tab: (2, rows), (2, SYNTH_TILE) the rotations of ``crank.cos_sin``;
    crank_cs: (2, n) cos and sin of the crank angle when ``ramp``; Wc (4, 2K), Wm (1, 2Km): weights
    of ``harmonic_series``; mech, lp, sen: (3, P, n+1) num_u, num_du and the denominator (in row
    [2, 0]) of a ``two_input_df2t``, with their states mech_z, lp_z, sen_z (P, n) carried over;
    keys (uint64): the streams of the force's and the displacement's noise (``standard_normal``, drawn at
    each sample's index k_abs + k); outputs (n,)."""
    T, f0, rate, alpha, g = fl[0], fl[1], fl[2], fl[3], fl[4]
    S, cap, quad, cub = fl[5], fl[6], fl[7], fl[8]
    gain, offset, dr, dq, noise_V = fl[9], fl[10], fl[11], fl[12], fl[13]
    cd0, sd0, delay, skew, dgain, dscale = fl[14], fl[15], fl[16], fl[17], fl[18], fl[19]
    lsb_d, lsb_f, lo, hi, centre = fl[20], fl[21], fl[22], fl[23], fl[24]
    n, k_abs, ramp, has_nl, has_lp = ints[0], ints[1], ints[2], ints[3], ints[4]
    has_drift, has_mains, has_fnoise, shift_mode = ints[5], ints[6], ints[7], ints[8]
    has_sen, has_dnoise = ints[9], ints[10]
    two_pi = 2.0 * np.pi
    K = Wc.shape[1] // 2
    P = mech.shape[1]
    mech_u, mech_du, mech_den = mech[0], mech[1], mech[2, 0]
    lp_u, lp_du, lp_den = lp[0], lp[1], lp[2, 0]
    sen_u, sen_du, sen_den = sen[0], sen[1], sen[2, 0]
    c = np.empty(SYNTH_TILE)
    s = np.empty(SYNTH_TILE)
    om = np.empty(SYNTH_TILE)
    u = np.empty(SYNTH_TILE)
    jerk = np.empty(SYNTH_TILE)
    cx = np.empty(SYNTH_TILE)
    sx = np.empty(SYNTH_TILE)
    du_s = np.empty(SYNTH_TILE)
    v = np.empty(SYNTH_TILE)
    xm = np.empty(SYNTH_TILE)
    Fs = np.empty(SYNTH_TILE)
    dFs = np.empty(SYNTH_TILE)
    vr_s = np.empty(SYNTH_TILE)
    rows = np.empty((4, SYNTH_TILE))
    mrow = np.empty((1, SYNTH_TILE))
    cprev = np.empty(SYNTH_TILE)
    ccur = np.empty(SYNTH_TILE)
    sprev = np.empty(SYNTH_TILE)
    scur = np.empty(SYNTH_TILE)
    n_mech, n_lp, n_sen = mech_den.size - 1, lp_den.size - 1, sen_den.size - 1
    zm0 = _load_state(mech_z, 0)
    zm1 = _load_state(mech_z, P - 1)
    zl = _load_state(lp_z, 0)
    zs = _load_state(sen_z, 0)
    for j in range((n + SYNTH_TILE - 1) // SYNTH_TILE):
        k0 = j * SYNTH_TILE
        t = min(SYNTH_TILE, n - k0)
        # the crank angle and rate
        if ramp:
            for q in range(t):
                c[q] = crank_cs[0, k0 + q]
                s[q] = crank_cs[1, k0 + q]
        else:
            _rotate_tile(crank_base, crank_tab, j, t, c, s)
        for q in range(t):
            om[q] = two_pi * (f0 + rate * ((k0 + q) * T))
        # kinematics (crank.evaluate): displacement, acceleration + g, jerk
        x = out_x[k0:k0 + t]
        if K == 1:
            a = Wc[0, 0]
            b = Wc[0, 1]
            d1 = v  # scratch until the filter pass
            if a == 0.0:
                for q in range(t):
                    x[q] = b * s[q]
                    d1[q] = b * c[q]
            else:
                for q in range(t):
                    x[q] = a * c[q] + b * s[q]
                    d1[q] = b * c[q] - a * s[q]
            if alpha == 0.0:
                for q in range(t):
                    w = om[q]
                    w2 = w * w
                    u[q] = -w2 * x[q] + g
                    jerk[q] = -(w2 * w) * d1[q]
            else:
                for q in range(t):
                    w = om[q]
                    w2 = w * w
                    u[q] = (alpha * d1[q] - w2 * x[q]) + g
                    jerk[q] = -(w2 * w) * d1[q] - 3.0 * alpha * w * x[q]
        else:
            _harmonics_rows(c, s, t, Wc, 4, rows, cprev, ccur, sprev, scur)
            if alpha == 0.0:
                for q in range(t):
                    w = om[q]
                    w2 = w * w
                    x[q] = rows[0, q]
                    u[q] = rows[2, q] * w2 + g
                    jerk[q] = rows[3, q] * (w2 * w)
            else:
                for q in range(t):
                    w = om[q]
                    w2 = w * w
                    x[q] = rows[0, q]
                    u[q] = (rows[2, q] * w2 + rows[1, q] * alpha) + g
                    jerk[q] = rows[3, q] * (w2 * w) + 3.0 * alpha * rows[2, q] * w
        # the displacement channel's angle: lagging by the channel delay less the clock skew's lead
        if shift_mode == 1:
            for q in range(t):
                cx[q] = c[q] * cd0 + s[q] * sd0
                sx[q] = s[q] * cd0 - c[q] * sd0
        elif shift_mode == 2:
            _taylor_shift(c, s, om, t, delay, skew, k_abs + k0, T, alpha, 0.0, cx, sx)
        elif shift_mode == 4:
            for q in range(t):
                cq, sq = c[q], s[q]
                c[q] = cq * cd0 + sq * sd0  # c, s: the crank's angle less the centre (the crank's not needed again)
                s[q] = sq * cd0 - cq * sd0
            _taylor_shift(c, s, om, t, delay, skew, k_abs + k0, T, alpha, centre, cx, sx)
        elif shift_mode == 3:
            for q in range(t):
                cd = shift_cs[0, k0 + q]
                sd = shift_cs[1, k0 + q]
                cx[q] = c[q] * cd + s[q] * sd
                sx[q] = s[q] * cd - c[q] * sd
        if shift_mode != 0:
            if has_sen:
                _harmonics_rows(cx, sx, t, Wc, 2, rows, cprev, ccur, sprev, scur)
            else:
                _harmonics_rows(cx, sx, t, Wc, 1, rows, cprev, ccur, sprev, scur)
        elif has_sen:
            _harmonics_rows(c, s, t, Wc, 2, rows, cprev, ccur, sprev, scur)
        if has_sen:
            for q in range(t):
                du_s[q] = rows[1, q] * om[q]
        # the filters: the mechanics, the transducer, the conditioner's low-pass beside the sensor
        zm0, zm1 = _mech_pass(mech_u, mech_du, mech_den, n_mech, P, zm0, zm1, u, jerk, Fs, dFs, t)
        rate_path = P > 1 and has_lp
        if has_nl and rate_path:
            for q in range(t):
                F = Fs[q]
                r = F / cap
                v[q] = S * F * (1.0 + quad * r + cub * r * r)
                vr_s[q] = S * dFs[q] * (1.0 + 2.0 * quad * r + 3.0 * cub * r * r)
        elif has_nl:
            for q in range(t):
                F = Fs[q]
                r = F / cap
                v[q] = S * F * (1.0 + quad * r + cub * r * r)
        else:
            for q in range(t):
                v[q] = S * Fs[q]
            if rate_path:
                for q in range(t):
                    vr_s[q] = S * dFs[q]
        if rate_path and has_sen and n_sen == 2:
            zl, zs = _lp_sensor_pass(lp_u[0], lp_du[0], lp_den, n_lp, zl, v, vr_s, v,
                                     sen_u[0], sen_du[0], sen_den, zs, rows[0], du_s, xm, t)
        else:
            if rate_path:
                zl = _filter_pass(lp_u[0], lp_du[0], lp_den, n_lp, zl, v, vr_s, v, t)
            if has_sen:
                zs = _filter_pass(sen_u[0], sen_du[0], sen_den, n_sen, zs, rows[0], du_s, xm, t)
        # the force channel: gain, offset, drift, mains, noise
        fV = out_fV[k0:k0 + t]
        for q in range(t):
            fV[q] = gain * v[q] + offset
        if has_drift:
            for q in range(t):
                ta = (k_abs + k0 + q) * T
                fV[q] += dr * ta + dq * (ta * ta)
        if has_mains:
            _rotate_tile(mains_base, mains_tab, j, t, cx, sx)
            _harmonics_rows(cx, sx, t, Wm, 1, mrow, cprev, ccur, sprev, scur)
            for q in range(t):
                fV[q] += mrow[0, q]
        if has_fnoise:
            key = keys[0]
            for q in range(t):
                fV[q] += standard_normal(key, k_abs + k0 + q) * noise_V
        # the displacement channel
        dV = out_dV[k0:k0 + t]
        if has_sen:
            for q in range(t):
                dV[q] = dgain * xm[q]
        elif shift_mode != 0:
            for q in range(t):
                dV[q] = dgain * rows[0, q]
        else:
            for q in range(t):
                dV[q] = dgain * x[q]
        if has_dnoise:
            key = keys[1]
            for q in range(t):
                dV[q] += standard_normal(key, k_abs + k0 + q) * dscale
    _store_state(zm0, mech_z, 0)
    if P > 1:
        _store_state(zm1, mech_z, 1)
    if has_lp:
        _store_state(zl, lp_z, 0)
    if has_sen:
        _store_state(zs, sen_z, 0)
    return _quantise(out_dV, lsb_d, lo, hi, codes_d) + _quantise(out_fV, lsb_f, lo, hi, codes_f)
