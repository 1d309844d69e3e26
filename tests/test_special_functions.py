"""Where the station takes a distribution's function from ``scipy.special`` instead of ``scipy.stats``
(whose import costs a daemon or worker process about 0.6 s of CPU), it gets scipy.stats's numbers bit
for bit, over a grid of the arguments those calls see and their edges: the control charts' and the
interval methods' normal and t functions (``station.trend.tails``), the model gap's chi^2 tails
(``chdtrc``) and gamma quantiles (``gammainccinv``), and the identification's misfit rate."""

from __future__ import annotations

import math

import numpy as np
from scipy import special, stats

from station.ident.response.frf import misfit_false_alarm_rate, misfit_threshold
from station.trend import tails

EDGES = [-math.inf, -1e300, -40.0, -1.0, -1e-300, -0.0, 0.0, 1e-300, 1.0, 40.0, 1e300, math.inf, math.nan]


def _same(a: object, b: object) -> None:
    """Same type, shape and bits (NaN where the other is NaN, the sign of zero included)."""
    assert type(a) is type(b), (type(a), type(b))
    x, y = np.asarray(a), np.asarray(b)
    assert x.dtype == y.dtype and x.shape == y.shape
    nan = np.isnan(x)
    assert np.array_equal(nan, np.isnan(y)), (x[nan != np.isnan(y)], y[nan != np.isnan(y)])
    diff = (x[~nan] != y[~nan]) | (np.signbit(x[~nan]) != np.signbit(y[~nan]))
    assert not diff.any(), (x[~nan][diff][:5], y[~nan][diff][:5])


def test_the_charts_normal_and_t_functions_are_scipy_stats_bit_for_bit() -> None:
    x = np.concatenate([np.linspace(-12, 12, 4801), EDGES])
    _same(tails.norm_cdf(x), stats.norm.cdf(x))
    _same(tails.norm_sf(x), stats.norm.sf(x))
    for v in [*EDGES, 2.5, -3.25]:
        _same(tails.norm_cdf(v), stats.norm.cdf(v))
        _same(tails.norm_sf(v), stats.norm.sf(v))
    q = np.concatenate([np.linspace(0, 1, 2001), [-0.5, 1.5, 1e-300, 1 - 1e-16, math.nan]])
    df = np.array([1, 2, 3, 4, 5, 7, 9, 10, 19, 30, 99, 1e4, 1e9, math.inf, 0.5, 0, -1, math.nan])
    qq, dd = np.meshgrid(q, df)
    _same(tails.t_ppf(qq, dd), stats.t.ppf(qq, dd))
    for qv in (0.0, 0.5, 0.95, 0.9985, 1.0):  # the charts' and the variables method's scalar calls
        for dv in (1, 2, 9, 0):
            _same(tails.t_ppf(qv, dv), stats.t.ppf(qv, dv))


def test_the_model_gaps_chi2_tails_and_gamma_quantiles_are_scipy_stats_bit_for_bit() -> None:
    # chi2.sf(x, dof) as chdtrc(dof, x): dof >= 1 at every call (a count of components, or max(.., 1))
    dof = np.array([1, 2, 3, 4, 5, 6, 8, 10, 17, 40, 100, 333, 1000, 4096, 50_000])
    x = np.concatenate([np.geomspace(1e-8, 1e7, 1500), [0.0, -0.0, 1e-300, 1e300, math.inf, math.nan]])
    xx, dd = np.meshgrid(x, dof)
    _same(special.chdtrc(dd, xx), stats.chi2.sf(xx, dd))
    for d in (1, 2, 7):
        for v in (0.0, 3.5, 1e3, math.nan):
            _same(special.chdtrc(d, v), stats.chi2.sf(v, d))
    # below 0 (a quadratic form rounded below 0): scipy.stats says 1, chdtrc NaN: a test "p < alpha"
    # decides the same, and max(x, 0) (locate's ">= alpha") gives 1 exactly
    for v in (-1e-12, -1.0, -math.inf):
        assert stats.chi2.sf(v, 3) == 1.0 and math.isnan(special.chdtrc(3, v))
        assert not special.chdtrc(3, v) < 1e-3 and not stats.chi2.sf(v, 3) < 1e-3
        _same(special.chdtrc(3, max(v, 0.0)), stats.chi2.sf(v, 3))
    # no added parameter: scipy.stats has no distribution (NaN), chdtrc would say 0; the candidate's
    # p-value is NaN by hand there
    assert math.isnan(stats.chi2.sf(4.0, 0)) and special.chdtrc(0, 4.0) == 0.0
    # gamma.isf(q, a) as gammainccinv(a, q): a = n or 3 n steps, q a level over the cells searched
    a = np.array([1, 2, 3, 4, 5, 6, 9, 12, 15, 30, 60, 150, 600])
    q = np.concatenate([np.geomspace(1e-14, 1, 700), [0.5, 1e-3, 1e-4]])
    qq, aa = np.meshgrid(q, a)
    _same(special.gammainccinv(aa, qq), stats.gamma.isf(qq, aa))
    for n in (1, 3, 5):
        _same(special.gammainccinv(n, 1e-4), stats.gamma.isf(1e-4, n))


def test_the_misfit_rate_is_the_chi2_tail_beyond_the_threshold() -> None:
    for dof in (1, 2, 7, 17, 100, 1000):
        assert misfit_false_alarm_rate(dof) == float(stats.chi2.sf(dof * misfit_threshold(dof), dof))
    assert 0.010 < misfit_false_alarm_rate(7) < 0.012  # the docstring's "1.1 % at dof 7"
