"""The budget as frozen types: what the frequency-domain budget keeps (each source's covariance),
its JSON form (unchanged: the stored results, the page and the certificate read it) and old stored
results read back."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from station.ident.coverage import coverage
from station.ident.fd.budget import Budget
from station.ident.result import FitSummary, IdentificationResult
from station.ident.uncertainty import ParameterBudget, UncertaintyBudget


def _budget() -> Budget:
    """Three parameters, the third held; a correlated source, a diagonal one and one not propagated."""
    a = np.array([[4.0, 1.0, 0.0], [1.0, 9.0, 0.0], [0.0, 0.0, 0.0]])
    b = np.diag([1.0, 16.0, 0.0])
    return Budget(("S", "k_f", "b_f"), ("V/N", "N/m", "N*s/m"), {"noise": a, "chain_gain": b, "end_mass": None},
                  np.array([True, True, False]), {"noise": 7.0})


def test_the_fd_budget_keeps_each_sources_covariance_over_the_free_parameters() -> None:
    ub = _budget().uncertainty()
    assert list(ub) == ["S", "k_f"]  # b_f is held: not budgeted
    noise = ub.covariances["noise"]
    assert noise is not None and noise.names == ("S", "k_f") and noise.units == ("V/N", "N/m")
    assert noise.array.tolist() == [[4.0, 1.0], [1.0, 9.0]]  # the correlation the source brings is kept
    assert ub.covariances["end_mass"] is None
    s = ub["S"]
    assert s.stds == {"noise": 2.0, "chain_gain": 1.0, "end_mass": None}
    assert s.combined == pytest.approx(math.sqrt(5.0)) and s.unit == "V/N"
    assert s.dof == {"noise": 7.0} and s.contributions[1].dof == math.inf
    assert ub["k_f"].combined == pytest.approx(5.0)


def test_the_json_form_is_the_stored_one_and_reads_back() -> None:
    ub = _budget().uncertainty()
    assert ub.to_dict()["S"] == {"contributions": {"noise": 2.0, "chain_gain": 1.0, "end_mass": None},
                                 "combined": pytest.approx(math.sqrt(5.0)), "unit": "V/N", "dof": {"noise": 7.0}}
    res = IdentificationResult("fd", "sdof", {}, FitSummary(0.1, (0.1,), 1.0), budget=ub)
    back = IdentificationResult.from_dict(json.loads(json.dumps(res.to_dict())))
    assert back.budget == ub and back == res


def test_a_result_stored_before_the_per_source_covariances_reads_back_without_them() -> None:
    old = {"method": "fd", "model": "sdof", "parameters": {}, "fit": {"mse": 0.1, "residual_rms_V": [0.1]},
           "budget": {"S": {"contributions": {"noise": 3.0, "radius": 0.0}, "combined": 3.0, "unit": "V/N"}}}
    res = IdentificationResult.from_dict(old)
    assert res.budget["S"].std("noise") == 3.0 and res.budget.covariances == {}
    assert res.to_dict()["budget"] == old["budget"]


def test_a_changed_contribution_is_recombined() -> None:
    b = ParameterBudget.of({"noise": 3.0, "chain_gain": 4.0, "end_mass": None}, 5.0, "N/m", {"noise": 2.0})
    c = b.with_contribution("noise", 0.0)
    assert c.combined == 4.0 and c.stds["end_mass"] is None and c.dof == {"noise": 2.0}
    assert coverage(b).k > coverage(UncertaintyBudget({"x": c})["x"]).k  # fewer dof, larger k
