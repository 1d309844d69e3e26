"""The swarm's hot loop compiled with numba: Eq. 12-13 updates and Eq. 15 fitness of every particle.

The arithmetic is the numpy implementation's (``pso.run_pso`` with ``batchfilter.batch_mse``)
operation for operation, so a seed gives the same swarm to the last bit:

* the fitness is ``batchfilter``'s blocked filter (blocks of L samples, zero-state responses, the
  homogeneous responses, block boundaries chained, the free responses added) with the same order of
  every sum; the zero-state convolution is a fused multiply-add chain as the BLAS ``X @ b`` of the
  numpy version computes it (OpenBLAS on any x86-64 with FMA3 or on ARMv8);
* the velocity update is evaluated as numpy evaluates ``w V + c1 r1 (Pbest - X) + c2 r2 (Gbest - X)``
  and clipped as ``np.clip`` clips; the random numbers and exp(-MSE) stay numpy's (``pso``).

Work is done on chunks of ``CHUNK`` particles with the particle index innermost, so that the
compiler vectorises across particles as numpy does, and a chunk's scratch stays in the L1 cache.
Compiled on first use (``cache=True``: once per installation); nothing here is imported by the
station's CLI at start-up.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import cast

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.core.base import BaseContext
from numba.core.typing.context import BaseContext as TypingContext
from numba.core.typing.templates import Signature
from numba.extending import intrinsic
from numpy.typing import NDArray

CHUNK = 32  # particles evaluated together
F64 = NDArray[np.float64]  # the kernels' arrays (their shapes in each docstring)
# an intrinsic's code generator: (target context, LLVM IR builder, signature, arguments) -> the result
_Codegen = Callable[[BaseContext, ir.IRBuilder, Signature, list[ir.Value]], ir.Value]


@intrinsic
def _fma_intrinsic(typingctx: TypingContext, a: types.Type, b: types.Type, c: types.Type) -> tuple[Signature, _Codegen]:
    """a * b + c rounded once (llvm.fma: the hardware instruction, or an exact software fallback)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context: BaseContext, builder: ir.IRBuilder, signature: Signature, args: list[ir.Value]) -> ir.Value:
        d = ir.DoubleType()
        fn = cgutils.get_or_insert_function(  # type: ignore[no-untyped-call]  # unannotated in numba
            builder.module, ir.FunctionType(d, [d, d, d]), "llvm.fma.f64")
        return builder.call(fn, args)

    return sig, codegen


# numba's stubs give an intrinsic its typing function's signature (the typing context first, returning
# Never); compiled code calls it without the context and gets the float: _fma(a, b, c) = a * b + c
_fma = cast(Callable[[float, float, float], float], _fma_intrinsic)


@numba.njit(cache=True, error_model="numpy")
def _coefficients(X: F64, form: int, p0: int, cc: int, a: F64, b: F64) -> None:
    """a (n, CHUNK) = A[1:]/A[0], b (nbc, CHUNK) = B/A[0] of particles p0..p0+cc-1 (zeros beyond).

    form 0: Eq. 11 positions (b1', a0', a1', a2'), B = (b1'/2, b1', b1'/2); form 1: Eq. 10 (b0..b4, a0..a4)."""
    n = a.shape[0]
    nbc = b.shape[0]
    a[:] = 0.0
    b[:] = 0.0
    for c in range(cc):
        p = p0 + c
        if form == 0:
            inv = 1.0 / X[p, 1]
            for i in range(n):
                a[i, c] = X[p, 2 + i] * inv
            half = X[p, 0] / 2
            b[0, c] = half * inv
            b[1, c] = X[p, 0] * inv
            b[2, c] = half * inv
        else:
            inv = 1.0 / X[p, nbc]
            for i in range(n):
                a[i, c] = X[p, nbc + 1 + i] * inv
            for k in range(nbc):
                b[k, c] = X[p, k] * inv


@numba.njit(cache=True, error_model="numpy")
def swarm_mse(X: F64, form: int, n: int, xpad: F64, y: F64, L: int, out: F64, C: int) -> None:
    """Eq. 15 of every particle (rows of X) into out (P,); n the filter order, L the block length,
    C the particles per chunk (``CHUNK``; an argument so that the compiler vectorises over it),
    xpad: x with n zeros ahead (the FIR's past) and zeros to the end of the last block.

    Per chunk, Z[r, col, c] holds the blocked responses as ``batchfilter`` lays them out: rows
    0..n-1 the zero past, rows n..n+L-1 the block's samples; columns 0..nb-1 the blocks' zero-state
    responses, nb..nb+n-1 the homogeneous responses; c the particle in the chunk."""
    P = X.shape[0]
    M = y.size
    nb = -(-M // L)
    ncol = nb + n
    nbc = n + 1
    Z = np.empty((n + L, ncol, C))
    prevs = np.empty((nb, n, C))  # the state y_{-1-i} entering each block
    a = np.empty((n, C))
    b = np.empty((nbc, C))
    acc = np.empty(C)
    for p0 in range(0, P, C):
        cc = min(C, P - p0)
        _coefficients(X, form, p0, cc, a, b)
        _block_responses(Z, xpad, a, b, n, L, nb, C)
        _chain_blocks(Z, prevs, n, L, nb, C)
        _squared_errors(Z, y, n, L, nb, acc, C)
        for c in range(cc):
            v_ = acc[c] / M
            out[p0 + c] = v_ if math.isfinite(v_) else np.inf


@numba.njit(cache=True, error_model="numpy")
def _block_responses(Z: F64, xpad: F64, a: F64, b: F64, n: int, L: int, nb: int, C: int) -> None:
    """Z of a chunk: each block's zero-state response to its input (the BLAS product's FMA chain) and
    the homogeneous responses to y_{-1-i} = 1, through the recursion of A."""
    ncol = nb + n
    nbc = n + 1
    for r in range(n + L):
        for col in range(ncol):
            z = Z[r, col]
            for c in range(C):
                z[c] = 0.0
    for col in range(nb):  # zero-state input part: the BLAS product's FMA chain
        for i in range(L):
            t = col * L + i
            z = Z[n + i, col]
            for m in range(nbc):
                xv = xpad[t + nbc - 1 - m]
                bm = b[m]
                for c in range(C):
                    z[c] = _fma(xv, bm[c], z[c])
    for i in range(n):  # homogeneous responses to y_{-1-i} = 1
        z = Z[n - 1 - i, nb + i]
        for c in range(C):
            z[c] = 1.0
    for j in range(n, n + L):
        for col in range(ncol):
            z = Z[j, col]
            for i in range(n):
                ai = a[i]
                zp = Z[j - 1 - i, col]
                for c in range(C):
                    z[c] -= ai[c] * zp[c]


@numba.njit(cache=True, error_model="numpy")
def _chain_blocks(Z: F64, prevs: F64, n: int, L: int, nb: int, C: int) -> None:
    """The state entering each block (the previous blocks' ends chained) and each block's free
    response to it added to its zero-state response."""
    for i in range(n):
        v = prevs[0, i]
        for c in range(C):
            v[c] = 0.0
    for bb in range(nb - 1):  # the state entering each block
        for r in range(n):
            v = prevs[bb + 1, r]
            zr = Z[n + L - 1 - r, bb]
            for c in range(C):
                v[c] = zr[c]
            for i in range(n):
                g = Z[n + L - 1 - r, nb + i]
                pv = prevs[bb, i]
                for c in range(C):
                    v[c] += g[c] * pv[c]
    for i in range(n):  # free responses added
        for col in range(nb):
            pv = prevs[col, i]
            for r in range(L):
                z = Z[n + r, col]
                g = Z[n + r, nb + i]
                for c in range(C):
                    z[c] += g[c] * pv[c]


@numba.njit(cache=True, error_model="numpy")
def _squared_errors(Z: F64, y: F64, n: int, L: int, nb: int, acc: F64, C: int) -> None:
    """acc[c]: the sum of squared errors of particle c in the order numpy's einsum takes it (padding
    weighted by 0)."""
    M = y.size
    for c in range(C):
        acc[c] = 0.0
    for r in range(L):
        for col in range(nb):
            t = col * L + r
            z = Z[n + r, col]
            yt = y[t] if t < M else 0.0
            wt = 1.0 if t < M else 0.0
            for c in range(C):
                e = (z[c] - yt) * wt
                acc[c] += e * e


@numba.njit(cache=True, error_model="numpy")
def move(X: F64, V: F64, pbest: F64, gbest: F64, r1: F64, r2: F64, w: float, c1: float, c2: float,
         v_max: float, x_max: float) -> None:
    """Eq. 12 and 13 in place, each clipped, in numpy's order of operations."""
    P, N = X.shape
    for p in range(P):
        for d in range(N):
            x = X[p, d]
            v = (w * V[p, d] + (c1 * r1[p, d]) * (pbest[p, d] - x)) + (c2 * r2[p, d]) * (gbest[d] - x)
            v = v if v > -v_max else -v_max
            v = v if v < v_max else v_max
            V[p, d] = v
            x = x + v
            x = x if x > -x_max else -x_max
            X[p, d] = x if x < x_max else x_max


@numba.njit(cache=True, error_model="numpy")
def remember(X: F64, mse: F64, fit: F64, pbest: F64, pbest_fit: F64, pbest_mse: F64, gbest: F64,
             gbest_state: F64) -> int:
    """Step 7: Pbest and Gbest by the fitness ``fit``; returns the decisions that differ from the
    MSE's own.  gbest_state: [fit, mse] of Gbest, updated in place."""
    P, N = X.shape
    ties = 0
    for p in range(P):
        better = fit[p] > pbest_fit[p]
        if better != (mse[p] < pbest_mse[p]):
            ties += 1
        if better:
            for d in range(N):
                pbest[p, d] = X[p, d]
            pbest_fit[p] = fit[p]
            pbest_mse[p] = mse[p]
    g = 0
    lowest = pbest_mse[0]
    for p in range(1, P):
        if pbest_fit[p] > pbest_fit[g]:
            g = p
        if pbest_mse[p] < lowest:
            lowest = pbest_mse[p]
    if pbest_mse[g] != lowest:
        ties += 1
    update = pbest_fit[g] > gbest_state[0]
    if update != (lowest < gbest_state[1]):
        ties += 1
    if update:
        for d in range(N):
            gbest[d] = pbest[g, d]
        gbest_state[0] = pbest_fit[g]
        gbest_state[1] = pbest_mse[g]
    return ties
