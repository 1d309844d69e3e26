"""identify_recording and ``station identify`` on simulated recordings (station.simulate)."""

import json
from pathlib import Path

import numpy as np
import pytest

from station.cli import main
from station.ident.identify import identify_recording
from station.recording import read_recording, read_result
from station.simulate import simulate_run
from tests.conftest import station_config

TRUTH = {"k_f": 2.91e7, "b_f": 17136.0}


def _cfg(steps: list[dict], record_s: float, effects: dict | None = None) -> object:
    return station_config(settle_s=0.3, record_s=record_s, steps=[(s["crank_frequency_hz"], s["crank_radius_m"])
                                                                  for s in steps],
                          effects=effects or {}, acceleration_hz_per_s=200.0, pre_roll_s=0.1)


@pytest.fixture(scope="module")
def stepped(tmp_path_factory: pytest.TempPathFactory) -> Path:
    steps = [{"crank_frequency_hz": f, "crank_radius_m": r}
             for f, r in ((4.0, 0.01), (20.0, 0.002), (50.0, 6e-4), (100.0, 1.5e-4))]
    return simulate_run(_cfg(steps, 1.0), tmp_path_factory.mktemp("st"), seed=3)


@pytest.fixture(scope="module")
def single_4hz(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate_run(_cfg([{"crank_frequency_hz": 4.0, "crank_radius_m": 0.01}], 1.5),
                        tmp_path_factory.mktemp("s4"), seed=4)


def test_fd_on_a_stepped_sine_recording_recovers_the_truth(stepped: Path) -> None:
    res = identify_recording(read_recording(stepped))
    assert res.method == "fd"
    k, b = res.parameter("k_f"), res.parameter("b_f")
    assert k.identifiable and b.identifiable
    assert abs(k.value / TRUTH["k_f"] - 1) < 1e-3 and abs(k.value - TRUTH["k_f"]) < 5 * k.std
    assert abs(b.value / TRUTH["b_f"] - 1) < 0.02 and abs(b.value - TRUTH["b_f"]) < 5 * b.std
    assert res.identifiability is not None and np.isfinite(res.identifiability.condition_number)


@pytest.mark.slow
def test_oe_agrees_with_fd_within_uncertainty(stepped: Path) -> None:
    rec = read_recording(stepped)
    fd, oe = identify_recording(rec, "fd"), identify_recording(rec, "oe")
    for name in ("k_f", "b_f"):
        a, b = fd.parameter(name), oe.parameter(name)
        assert abs(a.value - b.value) < 3 * np.hypot(a.std, b.std)


@pytest.mark.slow
def test_coupled_model_on_rigid_coupling_reports_k_c_not_identifiable(stepped: Path) -> None:
    res = identify_recording(read_recording(stepped), "fd", "coupled")
    assert not res.parameter("k_c").identifiable and res.parameter("k_c").value is None
    assert res.parameter("k_c").reason
    assert res.parameter("k_f").identifiable


def test_single_4hz_record_b_f_and_coupled_model_not_identifiable(single_4hz: Path) -> None:
    rec = read_recording(single_4hz)
    res = identify_recording(rec)
    b = res.parameter("b_f")
    assert not b.identifiable and b.value is None and b.std is None
    assert "1 sine frequency" in b.reason
    assert not res.parameter("k_f").identifiable
    s = res.parameter("S")  # one frequency: |H|/M is S only far below the resonance (high by (f/f_0)^2)
    assert not s.identifiable and s.value is None and "HIGH" in s.reason
    q = res.determined["quasi_static_sensitivity"]
    assert abs(q.value / 2e-3 - 1) < 1e-3 and q.combined > 0
    coupled = identify_recording(rec, "fd", "coupled")
    assert not any(coupled.parameter(n).identifiable for n in ("k_f", "b_f", "k_c", "b_c"))
    # the paper's PSO+ on the same record gets no digits for k_f, b_f either
    pso = identify_recording(rec, "pso+", "h2", seed=1)
    assert not pso.parameter("b_f").identifiable and pso.parameter("b_f").value is None


@pytest.mark.slow
def test_auto_model_picks_eq8_when_the_coupling_is_compliant(tmp_path: Path) -> None:
    steps = [{"crank_frequency_hz": f, "crank_radius_m": r}
             for f, r in ((4.0, 0.01), (20.0, 0.002), (50.0, 6e-4), (100.0, 1.5e-4))]
    eff = {"coupling_compliance": {"k_c": 1e8, "b_c": 200.0}}
    rec = read_recording(simulate_run(_cfg(steps, 1.0, eff), tmp_path, seed=5))
    stiff = identify_recording(rec, "fd", "sdof")
    assert stiff.fit.chi2_per_dof > 100
    # Eq. 9 sees the series stiffness, stated as such; k_f alone is withheld: a coupling explains the misfit
    k_s = 1 / (1 / TRUTH["k_f"] + 1 / 1e8)
    ser = stiff.determined["series_stiffness"]
    assert abs(ser.value - k_s) < 3 * ser.combined and abs(ser.value / TRUTH["k_f"] - 1) > 0.1
    assert not stiff.parameter("k_f").identifiable and "coupling_suspected" in {c.name for c in stiff.checks}
    assert stiff.assumptions.structure.equation == "Eq. 9"
    res = identify_recording(rec)
    assert res.model == "coupled"
    k, kc = res.parameter("k_f"), res.parameter("k_c")
    assert k.identifiable and abs(k.value - TRUTH["k_f"]) < 5 * k.std and k.std / k.value < 0.01
    assert kc.identifiable and abs(kc.value - 1e8) < 5 * kc.std
    assert res.fit.chi2_per_dof < 5


@pytest.mark.slow
def test_cli_identify_json_and_stored_result(stepped: Path, tmp_path: Path, capsys) -> None:
    path = tmp_path / "rec.h5"
    path.write_bytes(stepped.read_bytes())
    assert main(["identify", str(path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    for name, unit in (("k_f", "N/m"), ("b_f", "N*s/m")):
        p = doc["parameters"][name]
        assert p["unit"] == unit and p["identifiable"] and p["value"] > 0 and p["std"] > 0
    assert doc["fit"]["mse"] > 0 and len(doc["fit"]["residual_rms_V"]) == 4
    stored = read_result(path, "identify_fd_sdof")
    assert stored is not None and stored["parameters"]["k_f"]["value"] == doc["parameters"]["k_f"]["value"]
    assert main(["identify", str(path), "--model", "coupled", "--json", "--no-write"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert {"k_c", "b_c"} <= set(doc["parameters"])
    assert doc["parameters"]["k_c"]["value"] is None


def test_cli_rejects_missing_recording(tmp_path: Path) -> None:
    assert main(["identify", str(tmp_path / "nope.h5")]) == 2


def test_reported_correlations_are_those_of_the_estimate(stepped: Path) -> None:
    """identifiability.correlations of identifiable parameters = the estimate's covariance, whose
    correlations the 200-draw Monte Carlo test checks (tests/test_ident_fd.py)."""
    from station.ident.fd.core import fd_fit, start_values
    from station.ident.identifiability import Policy, correlations
    from station.ident.inputs import model_for
    from station.ident.response.checked import checked_response

    rec = read_recording(stepped)
    frf = checked_response(rec).frf
    model = model_for(rec, "sdof")
    fit, rep = fd_fit(frf, model, start_values(frf, model), Policy())
    assert all(rep.identifiable)
    np.testing.assert_allclose(np.array(rep.correlations), correlations(fit.cov), atol=1e-12)
    assert identify_recording(rec).identifiability.correlations == rep.correlations


def test_a_coupling_is_a_result_only_where_the_data_reject_the_rigid_limit() -> None:
    """The likelihood-ratio judgement behind k_c: Eq. 8 must lower chi^2 by more than the 3-sigma
    threshold of chi^2 with two degrees of freedom (11.8) for a finite k_c to be stated."""
    from station.ident.fd.identify import coupling_shown

    assert not coupling_shown(4.19, 2.96)  # a rigid rig's realisation that a local coupled fit overfits
    assert "do not exclude a rigid coupling" in coupling_shown(4.19, 2.96).reason
    assert coupling_shown(1.3e7, 3.4)  # k_c = 2 k_f on the same plan
    assert 11.7 < coupling_shown(0.0, 0.0).threshold < 11.9


def test_a_coupled_fit_to_a_rigid_response_stays_finite() -> None:
    """Eq. 9's H at four frequencies with 1e-4 relative noise (numpy's generator, seed 1), fitted with
    Eq. 8: b_c, free along the rigid limit, used to walk to 1e293 and overflow its covariance; it now
    stops at the end of the fit's range (1e15 times its start), every number finite, no warning."""
    import warnings

    from station.ident.models import make_model
    from station.ident.response.frf import LOG_RANGE, FrequencyResponse, fit_frf

    f = np.array([4.0, 20.0, 50.0, 100.0])
    th = np.array([2e-3, TRUTH["k_f"], TRUTH["b_f"]])
    H0 = make_model("sdof", 0.1, 1.0).response(th, f)
    rng = np.random.default_rng(1)
    s = 1e-4 * np.abs(H0)
    frf = FrequencyResponse(f, H0 + s * (rng.normal(size=4) + 1j * rng.normal(size=4)),
                            np.array([np.eye(2) * x ** 2 for x in s]), np.zeros(4), np.zeros(4))
    start = np.r_[th, 10 * th[1], 0.1 * th[2]]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit = fit_frf(frf, make_model("coupled", 0.1, 1.0), start)
    assert np.all(np.isfinite(fit.theta)) and np.all(np.isfinite(fit.cov))
    assert fit.theta[4] <= start[4] * np.exp(LOG_RANGE) * (1 + 1e-9)
