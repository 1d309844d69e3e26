"""The chi^2 tails and the coverage factor the identification and its report use, taken from
``scipy.special`` (the worker processes start without importing ``scipy.stats``, 0.2-0.6 s of CPU):
the same numbers as ``scipy.stats`` gives."""

from __future__ import annotations

import math

import pytest
from scipy import stats

from station.ident.coverage import COVERAGE_PROBABILITY, coverage_factor
from station.ident.fd.identify import COUPLING_P, coupling_shown
from station.ident.structure import DETECTION_POWER, noncentrality_needed


def test_the_coupling_threshold_is_the_chi2_quantile_of_two_degrees_of_freedom() -> None:
    t = coupling_shown(0.0, 0.0).threshold
    assert t == pytest.approx(stats.chi2.isf(COUPLING_P, 2), rel=1e-13)
    assert t == pytest.approx(-2.0 * math.log(COUPLING_P), rel=1e-13)  # chi^2(2)'s tail is exp(-x/2)


@pytest.mark.parametrize(("dof", "threshold"), [(1, 3.84), (4, 9.49), (17, 27.6), (60, 80.0)])
def test_the_non_centrality_needed_has_the_stated_detection_power(dof: int, threshold: float) -> None:
    lam = noncentrality_needed(dof, threshold)
    assert stats.ncx2.sf(threshold, dof, lam) == pytest.approx(DETECTION_POWER, abs=1e-9)


@pytest.mark.parametrize("nu", [1.0, 2.5, 9.0, 50.0, math.inf])
def test_the_coverage_factor_is_the_t_or_normal_quantile(nu: float) -> None:
    q = 0.5 + COVERAGE_PROBABILITY / 2
    want = stats.norm.ppf(q) if math.isinf(nu) else stats.t.ppf(q, nu)
    assert coverage_factor(nu) == pytest.approx(want, rel=1e-13)
