"""The paper's particle swarm optimisation, PSO and PSO+ (Section 3, Eq. 12-16, Steps 1-8).

* Eq. 12  V <- w V + c1 r1 (Pbest - X) + c2 r2 (Gbest - X), r1, r2 ~ U[0, 1] per particle and
  dimension; |V| clipped to v_max.
* Eq. 13  X <- X + V, clipped to the position limit |X| <= x_max.
* Eq. 14  w(j) = w_max - j/iter_max (w_max - w_min), j = 1..iter_max.
* Eq. 15  fitness F = MSE (PSO minimises it); Eq. 16 F' = exp(-F) (PSO+ maximises it).

Random draws come from one ``numpy.random.Generator(seed)`` in a fixed order (X0, V0, then r1, r2
per iteration), so PSO and PSO+ with the same seed consume the same stream.  Because exp(-F) is
monotone they then take identical steps, except where float64 ``exp(-F)`` ties: it is 0.0 for
F > ~745 and 1.0 for F < ~1.1e-16 (see ``docs/identification.md``).

The whole swarm is evaluated at once (``batchfilter.batch_mse``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from station.ident.paper.batchfilter import batch_mse, block_length

FloatArray = NDArray[np.float64]
BatchFitness = Callable[[FloatArray], FloatArray]
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PsoSettings:
    """Swarm settings.  Defaults are the paper's Case I (Section 4.1)."""

    n_particles: int = 150
    n_iterations: int = 1000
    c1: float = 2.0
    c2: float = 2.0
    w_max: float = 0.9
    w_min: float = 0.4
    x_max: float = 2.0
    v_max: float = 0.1
    variant: Literal["pso", "pso+"] = "pso+"


# Section 4.1: population 150, max position 2, max velocity 0.1; 1000 (Case I) / 2000 (Case II).
CASE_I = PsoSettings(150, 1000, x_max=2.0, v_max=0.1)
CASE_II = PsoSettings(150, 2000, x_max=2.0, v_max=0.1)
# Section 5.1: population 200, max position 100.  Iterations and velocity limit are not stated;
# we keep Section 4.1's iterations (1000 for Eq. 11, 2000 for Eq. 10) and ratio v_max/x_max = 0.05.
SECTION5_H2 = PsoSettings(200, 1000, x_max=100.0, v_max=5.0)
SECTION5_H1 = PsoSettings(200, 2000, x_max=100.0, v_max=5.0)


@dataclass(frozen=True)
class PsoResult:
    """Outcome of one swarm run.

    position: Gbest, shape (N,); mse: its Eq. 15 value; mse_history: Gbest MSE after the
    initialisation (index 0) and after every iteration, shape (n_iterations + 1,);
    fitness_history: the fitness as the algorithm sees it (MSE for PSO, exp(-MSE) for PSO+);
    iterations_to_converge: first iteration after which fitness_history never changes again;
    tie_decisions: per iteration, how many Pbest/Gbest decisions differed from the ones the MSE
    itself would have made (always 0 for PSO; for PSO+ the float64 ties of exp(-MSE)), shape
    (n_iterations + 1,).
    The swarm gives no uncertainty; callers compute one from the Jacobian at Gbest.
    """

    position: FloatArray
    mse: float
    mse_history: FloatArray
    fitness_history: FloatArray
    iterations_to_converge: int
    settings: PsoSettings
    seed: int
    tie_decisions: NDArray[np.int64]


def _fitness(mse: FloatArray, variant: str) -> FloatArray:
    """Value the algorithm compares: -MSE (PSO, Eq. 15 minimised) or exp(-MSE) (PSO+, Eq. 16)."""
    return np.exp(-mse) if variant == "pso+" else -mse


def _move(X: FloatArray, V: FloatArray, pbest: FloatArray, gbest: FloatArray, r1: FloatArray,
          r2: FloatArray, w: float, s: PsoSettings) -> None:
    """Eq. 12 and 13 in place, each clipped."""
    V[:] = w * V + s.c1 * r1 * (pbest - X) + s.c2 * r2 * (gbest - X)
    np.clip(V, -s.v_max, s.v_max, out=V)
    X += V
    np.clip(X, -s.x_max, s.x_max, out=X)


def _remember(X: FloatArray, mse: FloatArray, fit: FloatArray, pbest: FloatArray, pbest_fit: FloatArray,
              pbest_mse: FloatArray, gbest: FloatArray, gbest_state: FloatArray) -> int:
    """Step 7 in place: Pbest and Gbest by the fitness; gbest_state = [fitness, MSE] of Gbest.
    Returns how many decisions differ from the ones the MSE itself would have made."""
    better = fit > pbest_fit
    n_tie = int(np.count_nonzero(better != (mse < pbest_mse)))
    pbest[better], pbest_fit[better], pbest_mse[better] = X[better], fit[better], mse[better]
    g = int(np.argmax(pbest_fit))
    n_tie += int(pbest_mse[g] != pbest_mse.min())
    update = bool(pbest_fit[g] > gbest_state[0])
    n_tie += int(update != bool(pbest_mse.min() < gbest_state[1]))
    if update:
        gbest[:] = pbest[g]
        gbest_state[:] = pbest_fit[g], pbest_mse[g]
    return n_tie


_DRAWS_AHEAD = 64  # iterations whose random numbers are drawn in one call


def run_pso(fitness_mse: BatchFitness, n_dim: int, settings: PsoSettings, seed: int, *,
            compiled: bool = True) -> PsoResult:
    """Steps 3-8 of Section 3.3 on a batch objective ``fitness_mse(X (P, N)) -> MSE (P,)``.

    An ``OutputErrorObjective`` runs compiled (``swarm_kernel``, the same arithmetic to the last bit)
    unless ``compiled`` is False or numba is missing; any other objective runs in numpy."""
    s = settings
    kernel = compiled_swarm(fitness_mse) if compiled else None
    evaluate = kernel.evaluate if kernel is not None else fitness_mse
    move = kernel.move if kernel is not None else _move
    remember = kernel.remember if kernel is not None else _remember
    rng = np.random.default_rng(seed)
    P = s.n_particles
    X = rng.uniform(-s.x_max, s.x_max, (P, n_dim))  # Step 3
    V = rng.uniform(-s.v_max, s.v_max, (P, n_dim))
    mse = evaluate(X)
    fit = _fitness(mse, s.variant)
    pbest, pbest_fit, pbest_mse = X.copy(), fit.copy(), mse.copy()  # Step 4
    g = int(np.argmax(pbest_fit))
    gbest, gbest_state = pbest[g].copy(), np.array([pbest_fit[g], pbest_mse[g]])
    mse_hist = np.empty(s.n_iterations + 1)
    fit_hist = np.empty(s.n_iterations + 1)
    ties = np.zeros(s.n_iterations + 1, dtype=np.int64)
    ties[0] = int(pbest_mse[g] != pbest_mse.min())
    pso_plus = s.variant == "pso+"
    for j in range(s.n_iterations + 1):  # Steps 5-7
        if j:
            w = s.w_max - j / s.n_iterations * (s.w_max - s.w_min)  # Eq. 14
            if (j - 1) % _DRAWS_AHEAD == 0:  # r1 then r2 of each iteration: the stream of per-iteration draws
                r = rng.random((min(_DRAWS_AHEAD, s.n_iterations + 1 - j), 2, P, n_dim))
            r1, r2 = r[(j - 1) % _DRAWS_AHEAD]
            move(X, V, pbest, gbest, r1, r2, w, s)
            mse = evaluate(X)  # Step 6
            ties[j] = remember(X, mse, _fitness(mse, s.variant), pbest, pbest_fit, pbest_mse, gbest, gbest_state)
        mse_hist[j] = gbest_state[1]
        fit_hist[j] = gbest_state[0] if pso_plus else gbest_state[1]
    changes = np.nonzero(fit_hist[1:] != fit_hist[:-1])[0]
    conv = int(changes[-1] + 1) if changes.size else 0
    log.debug("%s seed %d: MSE %.3e after %d iterations (converged at %d)", s.variant, seed,
              gbest_state[1], s.n_iterations, conv)
    return PsoResult(gbest, float(gbest_state[1]), mse_hist, fit_hist, conv, s, seed, ties)  # Step 8


# --- parametrisations of the paper's transfer functions as particle positions ---------------

def split_h2(X: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Eq. 11 positions (N = 4): (b1', a0', a1', a2') with b0' = b2' = b1'/2.  X: (P, 4)."""
    b1 = X[:, 0:1]
    return np.hstack([b1 / 2, b1, b1 / 2]), X[:, 1:4]


def split_h1(X: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Eq. 10 positions (N = 10): (b0..b4, a0..a4).  X: (P, 10)."""
    return X[:, 0:5], X[:, 5:10]


SPLITS: dict[str, tuple[Callable[[FloatArray], tuple[FloatArray, FloatArray]], int]] = {
    "h2": (split_h2, 4), "h1": (split_h1, 10)}


@dataclass(frozen=True, eq=False)
class OutputErrorObjective:
    """Batch Eq. 15 objective: MSE of lfilter(B(X), A(X), x) against y for every particle.

    form: 'h2' (Eq. 11) or 'h1' (Eq. 10); x, y: input and output, shape (M,)."""

    form: str
    x: FloatArray
    y: FloatArray

    def __call__(self, X: FloatArray) -> FloatArray:
        B, A = SPLITS[self.form][0](X)
        return batch_mse(B, A, self.x, self.y)


def output_error_objective(form: str, x: FloatArray, y: FloatArray) -> OutputErrorObjective:
    """Batch Eq. 15 objective: MSE of lfilter(B(X), A(X), x) against y for every particle."""
    return OutputErrorObjective(form, np.asarray(x, float), np.asarray(y, float))


class CompiledSwarm:
    """``run_pso``'s three steps for an ``OutputErrorObjective``, compiled (``swarm_kernel``)."""

    def __init__(self, objective: OutputErrorObjective) -> None:
        from station.ident.paper import swarm_kernel  # numba: imported (and compiled) on first use

        self._k = swarm_kernel
        self._form = 0 if objective.form == "h2" else 1
        self._n = 2 if objective.form == "h2" else 4
        x, self._y = objective.x, np.ascontiguousarray(objective.y, dtype=float)
        M = x.size
        self._L = block_length(self._n, M)
        nb = -(-M // self._L)
        self._xpad = np.zeros(nb * self._L + self._n)  # n zeros ahead of x: the FIR's past
        self._xpad[self._n: self._n + M] = x

    def evaluate(self, X: FloatArray) -> FloatArray:
        out = np.empty(X.shape[0])
        self._k.swarm_mse(X, self._form, self._n, self._xpad, self._y, self._L, out, self._k.CHUNK)
        return out

    def move(self, X: FloatArray, V: FloatArray, pbest: FloatArray, gbest: FloatArray, r1: FloatArray,
             r2: FloatArray, w: float, s: PsoSettings) -> None:
        self._k.move(X, V, pbest, gbest, r1, r2, w, s.c1, s.c2, s.v_max, s.x_max)

    def remember(self, X: FloatArray, mse: FloatArray, fit: FloatArray, pbest: FloatArray, pbest_fit: FloatArray,
                 pbest_mse: FloatArray, gbest: FloatArray, gbest_state: FloatArray) -> int:
        return int(self._k.remember(X, mse, fit, pbest, pbest_fit, pbest_mse, gbest, gbest_state))


_NO_COMPILER: list[str] = []  # why the compiled swarm is unavailable in this process, once known


def compiled_swarm(objective: BatchFitness) -> CompiledSwarm | None:
    """The compiled steps for an output-error objective; None for any other objective or without numba."""
    if not isinstance(objective, OutputErrorObjective) or objective.form not in SPLITS or _NO_COMPILER:
        return None
    try:
        return CompiledSwarm(objective)
    except ImportError as e:
        _NO_COMPILER.append(str(e))
        log.warning("the swarm runs in numpy (slower): numba is unavailable: %s", e)
        return None


def output_error_objective_loop(form: str, x: FloatArray, y: FloatArray) -> BatchFitness:
    """The straightforward reference: one ``scipy.signal.lfilter`` call per particle."""
    split, _ = SPLITS[form]

    def f(X: FloatArray) -> FloatArray:
        B, A = split(X)
        out = np.empty(X.shape[0])
        with np.errstate(all="ignore"):
            for p in range(X.shape[0]):
                out[p] = np.mean((lfilter(B[p], A[p], x) - y) ** 2)
        out[~np.isfinite(out)] = np.inf
        return out

    return f


def identify_digital(form: str, x: FloatArray, y: FloatArray, settings: PsoSettings,
                     seed: int) -> tuple[FloatArray, FloatArray, PsoResult]:
    """Run PSO/PSO+ on Eq. 10 ('h1') or Eq. 11 ('h2'); returns (b, a, result)."""
    split, n_dim = SPLITS[form]
    res = run_pso(output_error_objective(form, x, y), n_dim, settings, seed)
    B, A = split(res.position[None, :])
    return B[0], A[0], res
