"""Control charts, run lengths and calibration intervals against published worked examples (NIST/
SEMATECH e-Handbook, NCSLI RP-1 via Sandia's suncal, NASA-HDBK-8739.19-5) and against their theory on
seeded histories."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from station.trend import charts, intervals

# e-Handbook 6.3.2.4: "Example of calculation of parameters for an EWMA control chart"
EHANDBOOK_DATA = [52.0, 47.0, 53.0, 49.3, 50.1, 47.0, 51.0, 50.1, 51.2, 50.5,
                  49.6, 47.6, 49.9, 51.3, 47.8, 51.2, 52.6, 52.4, 53.6, 52.1]


def test_ewma_reproduces_the_e_handbook_example():
    c = charts.ewma(EHANDBOOK_DATA, target=50.0, s=2.0539, lam=0.3, L=3.0)
    # published with sqrt(λ/(2-λ)) rounded to 0.4201
    assert c.points[0].upper == pytest.approx(52.5884, abs=1e-4)
    assert c.points[0].lower == pytest.approx(47.4115, abs=1e-4)
    # the published EWMA statistics (two decimals): the first three and the last
    got = [round(p.statistic, 2) for p in c.points]
    assert got[:3] == [50.60, 49.52, 50.56]
    assert got[-1] == 51.99
    # the e-Handbook's reading: every EWMA value within the limits (an upward trend at the end)
    assert c.out_of_control == []
    assert got[-1] > got[-5]


def test_ewma_flags_a_shift_the_individual_values_chart_misses():
    data = list(EHANDBOOK_DATA) + [53.0] * 6
    c = charts.ewma(data, target=50.0, s=2.0539, lam=0.3, L=3.0)
    s = charts.shewhart(data, reference=len(EHANDBOOK_DATA))
    assert c.out_of_control and c.out_of_control[0] >= len(EHANDBOOK_DATA)
    assert s.out_of_control == []


def test_run_lengths_match_their_published_values():
    assert charts.shewhart_arl(0.0) == pytest.approx(370.4, abs=0.05)
    assert charts.shewhart_arl(2.0) == pytest.approx(6.30, abs=0.005)
    # Lucas and Saccucci (1990): λ = 0.25, L = 3.0 gives an in-control ARL of 503
    assert charts.ewma_arl(0.0, lam=0.25, L=3.0) == pytest.approx(503, abs=1.5)
    # the chain's first-alarm distribution has the same mean as the ARL for a constant shift
    p = charts.first_alarm_probabilities([2.0] * 400)
    assert float(np.sum(np.arange(1, 401) * p)) == pytest.approx(charts.ewma_arl(2.0), rel=1e-9)


def test_shewhart_limits_are_t_limits_and_never_tighter_than_the_stated_uncertainty():
    x = [1.0, 1.1, 0.9, 1.05, 0.95]
    c = charts.shewhart(x)
    assert c.parameters["dof"] == 4
    assert c.parameters["k"] > 3.0  # t on 4 degrees of freedom is wider than the normal's 3
    wide = charts.shewhart(x, uncertainties=[1.0] * 5)
    assert wide.s == pytest.approx(1.0)
    with pytest.raises(ValueError, match="finite"):
        charts.shewhart([1.0, math.nan, 2.0])
    with pytest.raises(ValueError, match="at least 2"):
        charts.ewma([1.0])


def _first_alarm(chart: charts.Chart, start: int) -> int | None:
    late = [i for i in chart.out_of_control if i >= start]
    return late[0] - start + 1 if late else None


def test_step_of_two_u_is_flagged_within_the_predicted_run_length():
    """A transducer whose S steps by 2 u after 25 good calibrations: over 200 seeded histories the mean
    run length to the EWMA's first alarm agrees with the chain's (s is the stated u, as the values
    scatter by their stated u); the Shewhart chart's, whose limits come from the 25 reference values,
    agrees with the geometric run length of each history's own limits."""
    rng = np.random.default_rng(20261127)
    n_ref, n_after, u = 25, 400, 1.0
    p = charts.first_alarm_probabilities(np.full(n_after, 2.0))
    ewma_theory = float(np.sum(np.arange(1, n_after + 1) * p) / p.sum())
    ewma_rl, shew_rl, shew_theory = [], [], []
    for _ in range(200):
        x = np.concatenate([rng.normal(0, u, n_ref), rng.normal(2 * u, u, n_after)])
        e = _first_alarm(charts.ewma(x, target=0.0, s=u), n_ref)
        sh = charts.shewhart(x, uncertainties=np.full(x.size, u), reference=n_ref)
        r = _first_alarm(sh, n_ref)
        assert e is not None and r is not None
        ewma_rl.append(e)
        shew_rl.append(r)
        lo, hi = sh.points[0].lower, sh.points[0].upper
        shew_theory.append(1 / (stats.norm.cdf(lo, 2 * u, u) + stats.norm.sf(hi, 2 * u, u)))
    assert np.mean(ewma_rl) == pytest.approx(ewma_theory, rel=0.2)
    assert np.mean(shew_rl) == pytest.approx(np.mean(shew_theory), rel=0.25)
    assert np.mean(ewma_rl) < np.mean(shew_rl)  # the EWMA finds a small step sooner


def test_drift_of_a_tenth_of_a_percent_a_month_is_flagged_within_the_predicted_run_length():
    """Weekly check calibrations of S (stated u 0.028 % of S, as the station states on clean runs)
    drifting by 0.1 % a month after 20 good weeks: the EWMA's mean run length agrees with the chain's
    prediction for the growing shift."""
    rng = np.random.default_rng(7)
    rel_u = 2.8e-4
    per_week = 1e-3 / (365.25 / 12 / 7) / rel_u  # drift per week in units of u
    n_ref, n_after = 20, 40
    shifts = per_week * np.arange(1, n_after + 1)
    p = charts.first_alarm_probabilities(shifts)
    theory = float(np.sum(np.arange(1, n_after + 1) * p) / p.sum())
    lengths = []
    for _ in range(300):
        x = np.concatenate([rng.normal(0, 1, n_ref), rng.normal(shifts, 1)])
        rl = _first_alarm(charts.ewma(x, target=0.0, s=1.0), n_ref)
        assert rl is not None
        lengths.append(rl)
    assert np.mean(lengths) == pytest.approx(theory, rel=0.2)
    assert theory < 8  # flagged within two months


def test_a_stable_transducer_raises_no_more_alarms_than_the_stated_rate():
    rng = np.random.default_rng(11)
    alarms, points = 0, 0
    for _ in range(200):
        x = rng.normal(0, 1, 100)
        c = charts.ewma(x, target=0.0, s=1.0)
        alarms += len(c.out_of_control)
        points += x.size
    rate = c.false_alarm_rate
    # the EWMA's alarms come in runs: count at most what a binomial at 3x the stated rate allows
    assert alarms <= points * rate * 3 + 3 * math.sqrt(points * rate * 3)


# NCSLI RP-1 method A3 on the 2019 NCSL International symposium tutorial's assets (suncal's tests)
@pytest.mark.parametrize(("passfail", "interval", "expected", "rejection", "lo", "hi"), [
    ([1, 1, 0, 1, 0, 1, 1, 1, 1, 0, 1, 1, 1, 1, 1, 0, 1, 1, 1, 0], 365, 231, .9949, .6516, .8286),
    ([1, 1, 1, 0, 1, 0, 0, 1, 1, 1, 0, 0, 1, 1, 1, 0, 1, 1, 1, 1], 365, 205, .9993, .6000, .7843),
    ([1, 1, 1, 1, 0, 1, 0, 1, 1, 1, 0, 1, 1, 1, 1, 1, 1, 0, 1, 1], 730, 523, .9682, .7041, .8716),
])
def test_method_a3_reproduces_the_published_intervals(passfail, interval, expected, rejection, lo, hi):
    r = intervals.a3(sum(passfail), len(passfail), interval, target=0.95)
    assert round(r.interval) == expected
    assert r.rejection_confidence == pytest.approx(rejection, abs=5e-5)
    assert r.reliability_range[0] == pytest.approx(lo, abs=5e-5)
    assert r.reliability_range[1] == pytest.approx(hi, abs=5e-5)


def test_method_a3_keeps_the_interval_below_the_change_confidence():
    r = intervals.a3(42, 50, 365, target=0.9, confidence=0.3)
    assert round(r.interval) == 329 and r.rejection_confidence == pytest.approx(.7557, abs=5e-5)
    kept = intervals.a3(42, 50, 365, target=0.9, confidence=0.9)
    assert kept.interval == 365
    with pytest.raises(ValueError):
        intervals.a3(5, 4, 365)


def test_method_s2_models_reproduce_rp1_table_d1():
    """RP-1 Table D-1 (weeks, counts, observed reliability), target 0.75: suncal lists the exponential
    model's interval as 10 weeks and the Weibull model's as 6 (whole weeks, truncated)."""
    ti = [4, 7, 10, 13, 21, 28, 40, 48]
    ni = [4, 6, 14, 13, 22, 49, 18, 6]
    ri = [1.0, .83333, .6429, .6154, .5455, .4082, .5000, .3333]
    models = {m.name: m for m in intervals.s2(ti, ri, ni, target=0.75)}
    assert math.floor(models["exponential"].interval) == 10
    assert math.floor(models["weibull"].interval) == 6
    assert models["weibull"].log_likelihood >= models["exponential"].log_likelihood


def test_variables_method_reproduces_nasa_hdbk_tables_7_3_to_7_7():
    dt = [70., 86., 104., 135., 167., 173.]
    deltas = [.1, .11, .251, .299, .403, .615]
    v = intervals.variables(dt, deltas, u0=.28, y0=10.03, limits=(9, 11), confidence=.9, u_target=.5)
    b, cov = v.fit.coefficients, v.fit.covariance
    assert b[0] == pytest.approx(0.00015741, rel=1e-4) and b[1] == pytest.approx(0.00001674, rel=1e-3)
    assert cov[0][0] == pytest.approx(1.01e-6, rel=1e-2) and cov[1][1] == pytest.approx(4.549e-11, rel=1e-3)
    assert cov[0][1] == pytest.approx(-6.607e-9, rel=1e-3)
    assert v.fit.s_yx == pytest.approx(0.0708, abs=5e-5)
    assert v.reliability_interval == pytest.approx(140.1, abs=0.05)
    assert 10.03 + v.fit.predict(v.reliability_interval) == pytest.approx(10.38, abs=0.005)
    assert v.uncertainty_interval == pytest.approx(327.15, abs=0.005)
    one_sided = intervals.variables(dt, deltas, u0=.28, y0=10.03, limits=(None, 11), confidence=.9)
    assert one_sided.reliability_interval == pytest.approx(171.75, abs=0.005)
    # as-left 9.03 is already too close to the lower limit at t = 0: no interval
    assert intervals.variables(dt, deltas, u0=.28, y0=9.03, limits=(9, 11), confidence=.9).reliability_interval == 0


def test_drift_risk_grows_towards_the_due_date_and_covers_the_truth():
    days = np.arange(0, 360, 30.0)
    truth = 1.0 + 1e-5 * days
    rng = np.random.default_rng(3)
    y = truth + rng.normal(0, 2e-4, days.size)
    near = intervals.drift_risk(days, y, np.full(days.size, 2e-4), due_day=390, nominal=1.0, tolerance=5e-3)
    far = intervals.drift_risk(days, y, np.full(days.size, 2e-4), due_day=720, nominal=1.0, tolerance=5e-3)
    assert abs(near.slope_per_day - 1e-5) < 3 * near.u_slope_per_day
    assert near.probability_out_of_tolerance < 0.05 < far.probability_out_of_tolerance
    with pytest.raises(ValueError):
        intervals.drift_risk([0, 1], [1, 1], [1, 1], due_day=2, nominal=1, tolerance=1)


def test_the_drift_risk_does_not_depend_on_where_time_starts() -> None:
    """Days counted from 1970 for runs minutes apart (a seeded history) once made the fit's variance
    negative (a 500 on the history): the fit is the same whatever the origin of time."""
    from station.trend import intervals

    minutes = np.array([0.0, 7.0, 13.0, 30.0]) / 1440
    values, u = [1.0, 1.0001, 0.9999, 1.0002], [1e-4] * 4
    near = intervals.drift_risk(minutes, values, u, due_day=365.0, nominal=1.0, tolerance=0.005)
    far = intervals.drift_risk(minutes + 20_776.0, values, u, due_day=20_776.0 + 365.0, nominal=1.0,
                               tolerance=0.005)
    assert np.isfinite(far.u_predicted) and far.u_predicted > 0
    assert far.slope_per_day == pytest.approx(near.slope_per_day, rel=1e-6)
    assert far.u_predicted == pytest.approx(near.u_predicted, rel=1e-6)
    with pytest.raises(ValueError, match="different times"):
        intervals.drift_risk([5.0] * 3, values[:3], u[:3], due_day=30.0, nominal=1.0, tolerance=0.005)
