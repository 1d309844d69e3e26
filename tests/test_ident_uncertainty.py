"""The budget as frozen types: what the frequency-domain budget keeps (each source's covariance),
its JSON form (unchanged: the stored results, the page and the certificate read it) and old stored
results read back."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml

from station.ident.assumptions import Assumptions
from station.ident.coverage import coverage
from station.ident.fd.budget import Budget
from station.ident.result import Estimate, FitSummary, IdentificationResult
from station.ident.uncertainty import DeterminedQuantity, ParameterBudget, UncertaintyBudget
from station.vocabulary import Flag


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


@pytest.mark.parametrize("stored", [
    {"value": 5.0, "noise": 0.3, "end_mass": 0.0, "chain_gain": None, "combined": 0.3, "unit": "N/m",
     "note": "1/k_s = 1/k_f + 1/k_c"},
    {"value": None, "range": [5.0, None], "unit": "N/m", "k_c_lower_bound_N_per_m": None,
     "conditional_on": "a stiff coupling"},
    {"run_id": "r1", "value": 2.0, "combined": None, "unit": "Hz"},
])
def test_a_determined_quantity_reads_back_its_stored_form(stored: dict[str, object]) -> None:
    q = DeterminedQuantity.from_dict(stored)
    assert q.to_dict() == stored
    assert (q.budget is None) == ("combined" not in stored)
    if "noise" in stored:
        assert q.budget is not None and q.budget.std("noise") == 0.3 and q.combined == 0.3 and not q.bounds
    if "range" in stored:
        assert q.range == (5.0, None) and q.bounds == {"k_c_lower_bound_N_per_m": None}


def test_the_derived_quantitys_budget_propagates_each_source_through_its_gradient() -> None:
    q = _budget().budget_of(np.array([1.0, 1.0, 0.0]), "V/N", invariant=("chain_gain",))
    assert q.stds == {"noise": pytest.approx(math.sqrt(4 + 9 + 2)), "chain_gain": 0.0, "end_mass": None}
    assert q.combined == pytest.approx(math.sqrt(15.0)) and q.unit == "V/N"


STORED_ASSUMPTIONS = {
    "end_mass_kg": {"value": 0.12, "std": 0.006, "source": "config"},
    "load_mass_kg": {"value": 1.5, "std": 1.5e-4, "source": "config"},
    "measurement_chain": {"gain_rel_std": 1e-4, "delay_std_s": 1e-6},
    "displacement_chain": {"response": "flat", "note": "taken as flat"},
    "crank_radius_std_m": 1e-7, "unsupported_defaults": ["crank radius u = 1e-07 m"],
    "structure": {"model": "stiff", "equation": "Eq. 9", "displacement_chain": {"response": "flat"},
                  "coupling": {"assumed": "stiff", "data_determine": "the series stiffness",
                               "k_f_alone_range_N_per_m": [5e6, None], "contradicted_by_the_data": True}},
    "rls_uncertainty": {"estimate": "the paper's RLS"},
}


def test_the_assumptions_read_back_their_stored_form() -> None:
    a = Assumptions.from_dict(STORED_ASSUMPTIONS)
    assert a.to_dict() == STORED_ASSUMPTIONS
    assert a.end_mass is not None and a.end_mass.source == "config"
    assert a.mass_std_kg == pytest.approx(math.hypot(0.006, 1.5e-4))
    assert a.structure is not None and a.structure.coupling is not None
    assert a.structure.coupling.contradicted_by_the_data and a.structure.coupling.k_f_alone_range == (5e6, None)
    assert Assumptions.from_dict({}).to_dict() == {}  # a result stored without assumptions


def test_an_estimates_flag_is_the_domains_enumeration_and_stored_as_its_string() -> None:
    e = Estimate.from_dict({"value": 1.0, "std": 0.1, "unit": "V/N", "identifiable": True, "reason": "r",
                            "flag": "conditional"})
    assert e.flag is Flag.CONDITIONAL
    assert Estimate.from_dict({"value": 1.0, "std": 0.1, "unit": "V/N"}).flag is Flag.NONE
    stored = e.to_dict()["flag"]
    assert type(stored) is str and yaml.safe_dump(e.to_dict())  # a plain string: any serialiser takes it
