"""The uncertainty statement is generated from the budget it describes; effective degrees of freedom
and k from the t-distribution; the GUM Supplement 1 Monte Carlo check agrees with the linear budget."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest
from scipy import stats

from station.ident.coverage import coverage, effective_dof
from station.ident.fd.identify import identify_fd
from station.ident.montecarlo import check_result
from station.ident.uncertainty import ParameterBudget
from station.recording import read_recording
from station.report.statement import uncertainty_statement
from tests.ident_support import sim


@pytest.fixture(scope="module")
def identified(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    rec = read_recording(sim(Path(tmp_path_factory.mktemp("stmt"))))
    return rec, identify_fd(rec)


def _end_mass_sentence(lines: list[str]) -> str:
    return next(s for s in lines if "end mass m_e" in s and s.startswith("The end mass"))


def test_the_statement_follows_the_budget(identified) -> None:  # type: ignore[no-untyped-def]
    _, res = identified
    budget, assumptions = res.budget, res.assumptions.to_dict()
    lines = uncertainty_statement(budget, assumptions)
    # the end mass is the largest contribution to u(S) in this budget, and the statement says so
    c = budget["S"].stds
    assert max(c, key=lambda s: c[s] or 0) == "end_mass"
    assert "to u(S) the end mass m_e" in " ".join(lines)
    em = _end_mass_sentence(lines)
    assert "uncertain input" in em and "taken as exact" not in " ".join(lines)
    # the same result with the end mass assumed (not propagated): the sentence changes with the budget
    cond = {n: ParameterBudget.of({**b.stds, "end_mass": None}, b.combined, b.unit, b.dof) for n, b in budget.items()}
    em2 = _end_mass_sentence(uncertainty_statement(cond, assumptions))
    assert "conditional" in em2 and "uncertain input" not in em2
    # a budget whose noise has few degrees of freedom: ν_eff and k follow it
    few = {n: ParameterBudget.of({"noise": 3.0, "chain_gain": 1.0}, math.sqrt(10.0), b.unit, {"noise": 4.0})
           for n, b in budget.items()}
    text = " ".join(uncertainty_statement(few, assumptions))
    nu = 100 / (81 / 4)  # u_c^4 / (u_noise^4 / 4)
    assert f"ν_eff = {nu:.3g}" in text and f"k = {stats.t.ppf(0.975, nu):.3g}" in text
    assert "ν = 4" in text


def test_effective_dof_and_k() -> None:
    assert math.isinf(effective_dof({"noise": 1.0, "end_mass": 2.0}, None))
    nu = effective_dof({"noise": 1.0, "end_mass": 1.0}, {"noise": 3.0})
    assert nu == pytest.approx(4 * 3.0)  # (1 + 1)^2 / (1 / 3)
    c = coverage(ParameterBudget.of({"noise": 1.0}, 1.0, "N/m", {"noise": 5.0}))
    assert c.k == pytest.approx(2.5706, abs=1e-4) and pytest.approx(c.k) == c.U
    assert coverage(ParameterBudget.of({"noise": 1.0}, 1.0, "N/m")).k == pytest.approx(1.95996, abs=1e-5)


@pytest.mark.slow
def test_monte_carlo_agrees_with_the_linear_budget(identified) -> None:  # type: ignore[no-untyped-def]
    """GUM S1: 600 refits of draws of every propagated source; u and the 95 % interval of the trials
    against the linear budget's u and y +- k u (within the Monte Carlo's own sampling error)."""
    rec, res = identified
    mc = check_result(rec, res, trials=600, seed=1)
    assert {"noise", "chain_gain", "end_mass", "load_mass"} <= set(mc.sources)
    assert [p.name for p in mc.parameters] == ["S", "k_f", "b_f"]
    n = mc.trials
    for p in mc.parameters:
        se_u = p.u_linear / math.sqrt(2 * (n - 1))  # sampling error of a standard deviation
        assert abs(p.u_mc - p.u_linear) < 4 * se_u + 0.05 * p.u_linear, p
        se_end = 2.7 * p.u_linear / math.sqrt(n)  # of a 2.5 % quantile of a normal sample
        assert p.d_low < p.delta + 3 * se_end and p.d_high < p.delta + 3 * se_end, p


def test_the_fit_stores_its_convergence(identified) -> None:  # type: ignore[no-untyped-def]
    """The frequency-domain fit's χ² per Levenberg–Marquardt iteration (the convergence plot's data):
    from the linear start down to the final χ², never up, ending at the χ² the result states."""
    _, res = identified
    hist = res.extra["cost_history"]
    assert len(hist) >= 2 and all(b <= a * (1 + 1e-12) for a, b in itertools.pairwise(hist))
    assert hist[-1] / res.extra["dof"] == pytest.approx(res.fit.chi2_per_dof, rel=1e-9)


def test_conditions_entered_with_the_run_request_reach_the_start_document() -> None:
    """Temperature and humidity entered with a run request are the run's (its configuration, from which
    the procedure writes the start document); without them the simulated room sensor reads."""
    from station.config import parse_config
    from station.environment import run_environment
    from station.run.request import RunRequest, default_request, plan_run
    from tests.conftest import station_dict

    cfg = parse_config(station_dict())
    body = default_request(cfg).model_dump(exclude_none=True)
    plan = plan_run(cfg, RunRequest.model_validate({**body, "environment": {"temperature_c": 22.5,
                                                                              "relative_humidity_pct": 38}}))
    env = run_environment(plan.config)
    assert env is not None and env["source"] == "entered with the run"
    assert (env["temperature_c"], env["relative_humidity_pct"]) == (22.5, 38)
    sensed = run_environment(plan_run(cfg, RunRequest.model_validate(body)).config)
    assert sensed is not None and sensed["source"] == "simulated room sensor"
    with pytest.raises(ValueError):
        RunRequest.model_validate({**body, "environment": {"temperature_c": 500}})
