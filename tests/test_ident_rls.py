"""What the station states for the paper's RLS (Eq. 17): S right within its stated uncertainty.

Truth from the simulator (``tests.ident_support.sim``: Eq. 3 integrated, not the estimator).  One
4 Hz step does not determine k_f and b_f; RLS's own k_f scatters by ~6 % between noise draws and
reaches S through Eq. 9 at fixed H(4 Hz).  The station's budget used to hold the step's noise term
only, and on clean runs S missed the truth by up to ~3.4 of it; the ``unidentified_dynamics`` term
(``station.ident.paper.rls_uncertainty``) covers it.
"""

from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lfilter

from station.ident.identify import identify_recording
from station.ident.paper.rls import rls_covariance, rls_h2
from station.ident.result import IdentificationResult
from station.recording import read_recording
from tests.ident_support import S, sim

STEP = ((4.0, 0.01),)  # the paper's 4 Hz step (Section 5.1 takes the lowest frequency)


def _rls(folder: Path, seed: int) -> IdentificationResult:
    return identify_recording(read_recording(sim(folder, STEP, seed=seed, record_s=1.5)), "rls", "h2")


@pytest.mark.slow
def test_the_sandwich_covariance_matches_the_scatter_of_rls_on_a_well_posed_arx() -> None:
    """A broadband input and an equation error that is white (an ARX system, no errors in variables):
    P Omega P is the Monte Carlo covariance of RLS's theta."""
    rng = np.random.default_rng(5)
    b, a = np.array([0.25, 0.5, 0.25]), np.array([1.0, -0.3, 0.4])
    x = rng.normal(size=300)
    thetas, stated = [], []
    for _ in range(150):
        y = lfilter(b, a, x) + lfilter([1.0], a, rng.normal(0, 0.2, x.size))  # e white in A(q) y = B(q) x + e
        r = rls_h2(x, y)
        thetas.append(r.theta)
        stated.append(np.sqrt(np.diag(rls_covariance(x, y, r))))
    ratio = np.median(stated, axis=0) / np.std(thetas, axis=0, ddof=1)
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio


def test_rls_s_states_the_unidentified_dynamics_beside_the_noise_term(tmp_path: Path) -> None:
    """One run: the budget names the unidentified-dynamics term beside the noise term, the larger of the
    two (over seeds 1-20 it is 1.0-1.7 times the noise term: the old, noise-only statement is the
    smaller part; the scatter that shows it is the twenty-seed test's), and the miss is within 2
    combined u."""
    res = _rls(tmp_path, 10)
    p = res.parameters["S"]
    assert p.identifiable and p.value is not None and p.std is not None
    terms = res.budget["S"].stds
    assert set(terms) == {"noise", "unidentified_dynamics"}
    assert res.budget["S"].combined == pytest.approx(np.hypot(terms["noise"], terms["unidentified_dynamics"]))
    assert terms["unidentified_dynamics"] > terms["noise"]
    assert abs(p.value - S) / p.std <= 2
    assert "unidentified_dynamics" in res.assumptions.rls_uncertainty
    assert any("unidentified_dynamics" in n for n in res.notes)
    assert not res.parameters["k_f"].identifiable and not res.parameters["b_f"].identifiable


@pytest.mark.slow
def test_rls_s_covers_the_truth_over_twenty_noise_seeds(tmp_path: Path) -> None:
    """The stated u covers the truth with an honest scatter of z; against the noise term alone the
    scatter is well above 1 (1.77 over seeds 1-20: the station's old statement was too small), which
    does not hang on one realisation crossing 3."""
    z, z_noise = [], []
    for seed in range(1, 21):
        res = _rls(tmp_path / str(seed), seed)
        p = res.parameters["S"]
        assert p.value is not None and p.std is not None
        z.append((p.value - S) / p.std)
        z_noise.append((p.value - S) / res.budget["S"].stds["noise"])
    a = np.abs(z)
    assert np.mean(a <= 2) >= 0.9 and a.max() <= 3, np.round(z, 2)
    assert 0.5 < np.std(z) < 1.5, np.std(z)  # honest, and not inflated either
    # what the station used to state: its z scatters beyond 1 (20 draws: the sample std's own relative
    # scatter is about 1/sqrt(40) = 0.16), by the factor the unidentified-dynamics term adds per run
    # (sqrt(1 + 1.0^2) to sqrt(1 + 1.7^2)), which does not depend on the draw
    assert np.std(z_noise) > 1.2, np.round(z_noise, 2)
    assert np.std(z_noise) > 1.3 * np.std(z), (np.std(z_noise), np.std(z))
