"""Counter-based standard normal draws for the simulated rig's noise, compiled with numba (imported on
first use, like ``kernels``).

Draw k of a stream is a function of the stream's key and of k alone, not of how a run is cut into
blocks: the one-pass synthesis draws each sample's noise where it adds it, the staged synthesis a
block at a time, and both give the same bits.

* Uniforms: SplitMix64's output function (Steele, Lea & Flood 2014) on the Weyl sequence
  key + (k + 1) gamma (the generator that passes BigCrush; two streams of random 64-bit keys
  overlap within a run with negligible probability).
* Normals: the ziggurat of Marsaglia & Tsang (2000) with 256 layers and 52-bit abscissae, the tables
  and steps numpy's ``Generator.standard_normal`` uses; the rare rejections (about 1 % of draws)
  take their further uniforms from a sub-stream of (key, k).
"""

from __future__ import annotations

import math

import numba
import numpy as np

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
def mix64(z):
    """SplitMix64's output function: a bijection of uint64 whose outputs on a Weyl sequence are uniform."""
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@numba.njit(cache=True, inline="always")
def _unit(u):
    """A uint64 as a double in [0, 1) (its top 53 bits)."""
    return np.float64(u >> _S11) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True, inline="always")
def standard_normal(key, k):
    """Draw k (int, >= 0) of the stream with the uint64 ``key``: one standard normal.  Branch-free
    but for the rare rejection (the sign as a factor, the 52-bit abscissa as a signed integer: half
    the time of the literal form, the same bits)."""
    r = mix64(key + (np.uint64(k) + _ONE) * GAMMA)
    i = np.int64(r & _LOW8)
    rabs = np.int64((r >> _S9) & _LOW52)
    x = np.float64(rabs) * (1.0 - 2.0 * np.float64(np.int64((r >> _S8) & _ONE))) * _WI[i]
    if rabs < _KI[i]:
        return x
    return _rejected(key, k, np.uint64(i), np.uint64(rabs), x)


@numba.njit(cache=True)
def _rejected(key, k, i, rabs, x):
    """The ziggurat's rare path for draw k (a wedge or the tail), with the uniforms of its sub-stream."""
    s = mix64((key ^ _SUB) + (np.uint64(k) + _ONE) * GAMMA)
    j = np.uint64(0)
    while True:
        if i == 0:  # the tail beyond ZIGGURAT_R (Marsaglia 1964)
            while True:
                j += _ONE
                xx = -_INV_R * np.log1p(-_unit(mix64(s + j * GAMMA)))
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
def fill_standard_normal(key, start, out):
    """out[q] = draw start + q of the stream ``key`` (uint64), q < out.size."""
    for q in range(out.size):
        out[q] = standard_normal(key, start + q)
