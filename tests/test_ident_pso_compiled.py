"""The compiled swarm (``swarm_kernel``) is the paper's PSO/PSO+ to the last bit: its Gbest, MSE and
fitness histories equal those of an independent plain numpy implementation of Section 3.3 (below)
for the same seed, and its Eq. 15 fitness equals the numpy batch filter's bit for bit and
``scipy.signal.lfilter``'s to rounding."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from scipy.signal import lfilter

from station.ident.paper.batchfilter import batch_mse
from station.ident.paper.pso import (
    CASE_I,
    SECTION5_H1,
    SECTION5_H2,
    PsoSettings,
    compiled_swarm,
    output_error_objective,
    run_pso,
    split_h1,
    split_h2,
)
from station.paper import case_data


def reference_pso(objective, n_dim: int, s: PsoSettings, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps 3-8 of Section 3.3 written out plainly: Eq. 12-14 on whole arrays, r1 and r2 drawn per
    iteration, Pbest/Gbest by the fitness (Eq. 15 for PSO, Eq. 16 for PSO+).
    Returns (Gbest, Gbest MSE history, Gbest fitness history)."""
    rng = np.random.default_rng(seed)
    P = s.n_particles

    def fitness(mse: np.ndarray) -> np.ndarray:
        return np.exp(-mse) if s.variant == "pso+" else -mse

    X = rng.uniform(-s.x_max, s.x_max, (P, n_dim))
    V = rng.uniform(-s.v_max, s.v_max, (P, n_dim))
    mse = objective(X)
    fit = fitness(mse)
    pbest, pbest_fit, pbest_mse = X.copy(), fit.copy(), mse.copy()
    g = int(np.argmax(pbest_fit))
    gbest, gbest_fit, gbest_mse = pbest[g].copy(), pbest_fit[g], pbest_mse[g]
    mse_hist, fit_hist = [gbest_mse], [gbest_fit]
    for j in range(1, s.n_iterations + 1):
        w = s.w_max - j / s.n_iterations * (s.w_max - s.w_min)
        r1 = rng.random((P, n_dim))
        r2 = rng.random((P, n_dim))
        V = np.clip(w * V + s.c1 * r1 * (pbest - X) + s.c2 * r2 * (gbest - X), -s.v_max, s.v_max)
        X = np.clip(X + V, -s.x_max, s.x_max)
        mse = objective(X)
        fit = fitness(mse)
        better = fit > pbest_fit
        pbest[better], pbest_fit[better], pbest_mse[better] = X[better], fit[better], mse[better]
        g = int(np.argmax(pbest_fit))
        if pbest_fit[g] > gbest_fit:
            gbest, gbest_fit, gbest_mse = pbest[g].copy(), pbest_fit[g], pbest_mse[g]
        mse_hist.append(gbest_mse)
        fit_hist.append(gbest_fit)
    return gbest, np.array(mse_hist), np.array(fit_hist)


def assert_same_swarm(form: str, x: np.ndarray, y: np.ndarray, s: PsoSettings, seed: int) -> None:
    objective = output_error_objective(form, x, y)
    assert compiled_swarm(objective) is not None  # numba is installed: the compiled path runs
    n_dim = 4 if form == "h2" else 10
    gbest, mse_hist, fit_hist = reference_pso(objective, n_dim, s, seed)
    for compiled in (True, False):
        r = run_pso(objective, n_dim, s, seed, compiled=compiled)
        np.testing.assert_array_equal(r.position, gbest)
        np.testing.assert_array_equal(r.mse_history, mse_hist)
        np.testing.assert_array_equal(r.fitness_history, fit_hist if s.variant == "pso+" else mse_hist)


def eq11_data(M: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A noisy Eq. 11 record: x white, y = H2(x) + noise (Section 5.1's size: M points)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=M) * 40.0
    y = lfilter([0.002, 0.004, 0.002], [1.0, -1.6, 0.8], x) + rng.normal(0, 0.01, M)
    return x, y


@pytest.mark.parametrize("variant", ["pso", "pso+"])
def test_case_i_swarm_equals_the_plain_implementation_to_the_bit(variant: str) -> None:
    x, y = case_data("I")
    assert_same_swarm("h2", x, y, replace(CASE_I, n_iterations=200, variant=variant), seed=3)


@pytest.mark.slow
def test_section5_eq11_and_eq10_swarms_equal_the_plain_implementation_to_the_bit() -> None:
    x, y = eq11_data(200, 1)
    assert_same_swarm("h2", x, y, replace(SECTION5_H2, n_iterations=120), seed=0)
    # Eq. 10: ten coefficients, fourth order, a block length that does not divide M
    assert_same_swarm("h1", x[:187], y[:187], replace(SECTION5_H1, n_particles=45, n_iterations=60), seed=2)


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["pso", "pso+"])
def test_case_i_at_the_papers_settings_to_the_bit(variant: str) -> None:
    """Table 1's Case I run (150 particles, 1000 iterations), PSO+ into its exp(-MSE) ties."""
    x, y = case_data("I")
    assert_same_swarm("h2", x, y, replace(CASE_I, variant=variant), seed=0)


@pytest.mark.parametrize("form,M", [("h2", 100), ("h2", 37), ("h1", 200), ("h1", 9)])
def test_compiled_fitness_is_the_batch_filters_and_lfilters(form: str, M: int) -> None:
    rng = np.random.default_rng(M)
    n_dim = 4 if form == "h2" else 10
    X = rng.uniform(-2, 2, (70, n_dim))  # stable and unstable filters alike
    a0 = 1 if form == "h2" else 5
    X[:5, a0] = 0.0  # a0 = 0: no filter at all
    x, y = rng.normal(size=M), rng.normal(size=M)
    objective = output_error_objective(form, x, y)
    kernel = compiled_swarm(objective)
    assert kernel is not None
    got = kernel.evaluate(X)
    B, A = (split_h2 if form == "h2" else split_h1)(X)
    np.testing.assert_array_equal(got, batch_mse(B, A, x, y))
    assert np.all(np.isinf(got[:5]))
    with np.errstate(all="ignore"):
        truth = np.array([np.mean((lfilter(B[p], A[p], x) - y) ** 2) for p in range(5, X.shape[0])])
    finite = np.isfinite(truth) & (truth < 1e100)
    assert finite.sum() > 20
    np.testing.assert_allclose(got[5:][finite], truth[finite], rtol=1e-9)


def test_the_cli_does_not_import_the_compiler() -> None:
    """numba is imported (and the swarm compiled or read from its cache) on the first swarm run only,
    never for ``station --help``."""
    code = "import sys; from station.cli import main; sys.argv = ['station', '--help']\n" \
           "try:\n    main()\nexcept SystemExit:\n    pass\nprint('numba' in sys.modules, 'llvmlite' in sys.modules)"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "False False"
