"""Multi-mass campaign (station.ident.campaign.identify) on recordings made by the project's simulator
(station.simulate): the truth is the configuration, not the code under test."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from station.cli import main
from station.errors import BadInputError
from station.ident.campaign.identify import CampaignRefused, identify_campaign
from station.recording import read_recording, read_result
from station.report.html import render_report
from station.simulate import simulate_run
from tests.conftest import station_config

END_MASS = 0.12
TRUTH = {"S": 2.0e-6 * 1000.0, "m_e": END_MASS, "k_f": 2.91e7, "b_f": 17136.0}  # bridge x conditioner gain


def _cfg(top_mass_kg: float, transducer_id: str = "TX5K-0001", effects: dict | None = None) -> object:
    return station_config(settle_s=0.2, record_s=0.5, acceleration_hz_per_s=200.0, pre_roll_s=0.1,
                          steps=((4.0, 0.01), (20.0, 0.002), (50.0, 6e-4), (100.0, 1.5e-4)), effects=effects or {},
                          rig={"top_mass_kg": top_mass_kg},
                          transducer={"end_mass_kg": END_MASS, "id": transducer_id})


def _sim(tmp: Path, top_masses: tuple[float, ...], seed: int) -> list[Path]:
    return [simulate_run(_cfg(m), tmp, seed=seed + i) for i, m in enumerate(top_masses)]


@pytest.fixture(scope="module")
def three(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return _sim(tmp_path_factory.mktemp("three"), (5.0, 15.0, 25.717), seed=21)


@pytest.fixture(scope="module")
def alike(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return _sim(tmp_path_factory.mktemp("alike"), (25.717, 25.9), seed=31)


@pytest.mark.slow
def test_three_top_masses_recover_the_end_mass_within_its_uncertainty(three: list[Path]) -> None:
    res = identify_campaign([read_recording(p) for p in three])
    assert res.status == "separated"
    sep = next(c for c in res.checks if c.name == "end_mass_separation")
    assert sep.severity == "info"
    for name, truth in TRUTH.items():
        p = res.parameter(name)
        assert p.identifiable and p.value is not None and p.std is not None and p.std > 0
        z = (p.value - truth) / p.std
        assert abs(z) < 3, (name, p.value, p.std, z)
    # the uncertainty is small enough for the end mass to mean something (not a vacuous pass), and the
    # simulator's masses and chain are exact, so even the noise term alone must cover the error
    assert res.parameter("m_e").std < 0.01 * END_MASS * 10
    for name in ("S", "m_e"):
        p = res.parameter(name)
        assert abs(p.value - TRUTH[name]) < 4 * res.budget[name].stds["noise"], name
    cov = res.covariance.array
    assert res.covariance.names == ("S", "m_e", "k_f", "b_f") and cov.shape == (4, 4) and np.allclose(cov, cov.T)
    assert np.allclose(np.sqrt(np.diag(cov)), [res.parameter(n).std for n in TRUTH])
    for n in TRUTH:  # the budget's combined value is the reported uncertainty
        assert res.budget[n].combined == pytest.approx(res.parameter(n).std)
    cons = next(c for c in res.checks if c.name == "same_transducer_model")
    assert cons.severity == "info"
    assert 0.2 < res.chi2_per_dof < 3
    # the joint k_f rests on a stiff coupling, stated as identify states it (never a bare k_f alone)
    assert "series stiffness" in res.parameter("k_f").reason and "stiff coupling" in res.parameter("k_f").reason
    assert res.assumptions.structure.to_dict()["coupling"]["assumed"] == "stiff"


@pytest.mark.slow
def test_nearly_equal_top_masses_are_too_alike(alike: list[Path]) -> None:
    res = identify_campaign([read_recording(p) for p in alike])
    sep = next(c for c in res.checks if c.name == "end_mass_separation")
    assert sep.severity == "refused" and "too alike" in sep.message
    assert res.status == "conditional"
    assert res.parameter("m_e").value is None
    S = res.parameter("S")  # conditional on the stated (here true) end mass, with its 5 % propagated
    assert S.value is not None and S.std is not None and abs(S.value - TRUTH["S"]) < 3 * S.std
    assert "end_mass" in res.budget["S"].stds


@pytest.mark.slow
def test_too_alike_without_a_stated_end_mass_is_refused(alike: list[Path]) -> None:
    recs = [replace(read_recording(p), end_mass_kg=None) for p in alike]
    res = identify_campaign(recs)
    assert res.status == "refused"
    assert all(p.value is None and p.reason for p in res.parameters.values())
    sm = res.determined["S_times_M"]  # what the data do determine: S (m_e + m_l) per recording
    for r, d in zip(recs, sm, strict=True):
        truth = TRUTH["S"] * (END_MASS + r.load_mass_kg)
        assert abs(d.value - truth) < 4 * d.combined + 2e-4 * truth


@pytest.mark.slow
def test_one_recording_is_conditional_or_refused(three: list[Path]) -> None:
    rec = read_recording(three[2])
    res = identify_campaign([rec])
    assert res.status == "conditional" and res.parameter("m_e").value is None
    assert "distinct" in next(c for c in res.checks if c.name == "end_mass_separation").message
    bare = replace(rec, end_mass_kg=None)
    assert identify_campaign([bare]).status == "refused"
    held = identify_campaign([bare], assumed_end_mass_kg=END_MASS)  # assumed, no uncertainty: conditional
    S = held.parameter("S")
    assert held.status == "conditional" and S.flag == "conditional" and "not propagated" in S.reason
    assert "end_mass" not in held.budget["S"].stds
    prop = identify_campaign([bare], assumed_end_mass_kg=END_MASS, assumed_end_mass_std_kg=0.01)
    assert prop.budget["S"].stds["end_mass"] > 0 and prop.parameter("S").std > S.std
    with pytest.raises(BadInputError, match="states the end mass"):
        identify_campaign([rec], assumed_end_mass_kg=0.1)


def test_recordings_of_different_transducers_are_refused(three: list[Path]) -> None:
    recs = [read_recording(p) for p in three]
    recs[1] = replace(recs[1], transducer_id="TX5K-0002")
    with pytest.raises(CampaignRefused, match="different transducers"):
        identify_campaign(recs)
    recs[1] = replace(recs[1], transducer_id=recs[0].transducer_id, sensitivity_V_per_N=1e-3)
    with pytest.raises(CampaignRefused, match="nominal sensitivity"):
        identify_campaign(recs)


@pytest.mark.slow
def test_a_mistyped_top_mass_is_not_a_confident_number(three: list[Path]) -> None:
    recs = [read_recording(p) for p in three]
    recs[0] = replace(recs[0], load_mass_kg=recs[0].load_mass_kg * 1.02)  # 2 % typo
    res = identify_campaign(recs)
    cons = next(c for c in res.checks if c.name == "same_transducer_model")
    assert cons.severity == "refused"
    assert res.status == "refused" and all(p.value is None for p in res.parameters.values())


@pytest.mark.slow
def test_with_four_masses_the_mistyped_one_is_named(three: list[Path], tmp_path: Path) -> None:
    recs = [read_recording(p) for p in [*three, *_sim(tmp_path, (10.0,), seed=41)]]
    recs[2] = replace(recs[2], load_mass_kg=recs[2].load_mass_kg * 1.01)
    cons = next(c for c in identify_campaign(recs).checks if c.name == "same_transducer_model")
    assert cons.severity == "refused" and cons.values["odd_one_out"] == recs[2].path.name
    assert cons.values["chi2_per_dof_without"] < 3


def test_two_masses_fit_any_stated_masses_but_the_stated_end_mass_catches_a_typo(three: list[Path]) -> None:
    recs = [read_recording(p) for p in three[1:]]
    recs[0] = replace(recs[0], load_mass_kg=recs[0].load_mass_kg + 0.5)  # 15.45 typed as 15.95 kg
    res = identify_campaign(recs)
    names = {c.name: c for c in res.checks}
    assert names["mass_redundancy"].severity == "info"
    assert names["end_mass_stated"].severity == "warning"  # the stated 0.12 kg against about -0.75 kg
    assert "end_mass_negative" in names


@pytest.mark.slow
def test_polarity_is_kept_and_a_mixed_polarity_refused(three: list[Path]) -> None:
    recs = [read_recording(p) for p in three]
    flipped = [replace(r, force_V=-r.force_V) for r in recs]
    res = identify_campaign(flipped)
    S = res.parameter("S")
    assert res.status == "separated" and S.value is not None and S.std is not None
    assert abs(S.value + TRUTH["S"]) < 3 * S.std
    with pytest.raises(CampaignRefused, match="polarity"):
        identify_campaign([flipped[0], *recs[1:]])


@pytest.mark.slow
def test_cli_identifies_jointly_and_stores_in_every_recording(three: list[Path], tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    copies = []
    for p in three:
        q = tmp_path / p.name
        q.write_bytes(p.read_bytes())
        copies.append(q)
    assert main(["identify", *map(str, copies), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["kind"] == "campaign" and out["status"] == "separated"
    assert out["covariance"]["names"] == ["S", "m_e", "k_f", "b_f"]
    assert {c["name"] for c in out["checks"]} >= {"end_mass_separation", "same_transducer_model"}
    for q in copies:
        stored = read_result(q, "campaign")
        assert stored["parameters"]["m_e"]["value"] == out["parameters"]["m_e"]["value"]
    html = render_report(copies[1])  # the report of every recording that took part shows the campaign
    assert "Multi-mass campaign" in html and "(this run)" in html
    me = out["parameters"]["m_e"]["value"]
    assert f'data-value="{me!r}" data-key="campaign.m_e"' in html
    assert main(["identify", str(copies[0]), str(copies[0]), "--no-write"]) == 2
    assert "more than once" in capsys.readouterr().err


@pytest.mark.slow
def test_joint_fit_covariance_matches_the_scatter_and_the_cramer_rao_bound() -> None:
    """Complex Gaussian H(f) around Eq. 9 (drawn here, not by the code under test), 200 draws: the
    estimator is unbiased, its spread is the bound, and the covariance each fit reports matches it."""
    from station.ident.campaign import jointfit as jf
    from station.ident.models import SdofModel
    from station.ident.response.frf import FrequencyResponse

    theta = np.array([TRUTH["S"], END_MASS, TRUTH["k_f"], TRUTH["b_f"]])
    f = np.array([4.0, 20.0, 50.0, 100.0])
    masses = (5.45, 15.45, 26.167)
    rng = np.random.default_rng(7)
    truth_H = [SdofModel(END_MASS, m).response(theta[[0, 2, 3]], f) for m in masses]
    sig = [2e-5 * np.abs(H) for H in truth_H]
    priors = [jf.MassPrior(m, 0.0) for m in masses]
    est, rep = [], []
    for _ in range(200):
        frfs = [FrequencyResponse(f, H + s * (rng.normal(size=f.size) + 1j * rng.normal(size=f.size)),
                                  np.array([np.eye(2) * v**2 for v in s]), np.zeros(f.size), np.zeros(f.size))
                for H, s in zip(truth_H, sig, strict=True)]
        fit = jf.fit_joint(frfs, priors, theta * np.array([1.001, 0.9, 0.999, 1.01]))
        est.append(fit.theta)
        rep.append(np.sqrt(np.diag(fit.cov)))
    est_a = np.array(est)
    emp = est_a.std(axis=0, ddof=1)
    scale = np.r_[theta[0], np.mean(masses) + END_MASS, theta[2], theta[3], masses]
    exact = [FrequencyResponse(f, H, np.array([np.eye(2) * v**2 for v in s]), np.zeros(f.size), np.zeros(f.size))
             for H, s in zip(truth_H, sig, strict=True)]
    crb = np.sqrt(np.diag(np.linalg.inv(jf.fisher_relative(exact, priors, np.r_[theta, masses], scale, None))))
    crb *= scale[:4]
    assert np.all(np.abs(est_a.mean(axis=0) - theta) < 4 * emp / np.sqrt(len(est)))
    assert np.all((emp / crb > 0.8) & (emp / crb < 1.2)), emp / crb
    assert np.all((np.mean(rep, axis=0) / emp > 0.8) & (np.mean(rep, axis=0) / emp < 1.2))


@pytest.mark.slow
def test_an_effect_eq9_lacks_is_refused_not_fitted(tmp_path: Path) -> None:
    """A coupling compliance (Eq. 8, k_c = 1e8 N/m) in every recording: not one Eq. 9 transducer."""
    eff = {"coupling_compliance": {"k_c": 1e8, "b_c": 200.0}}
    paths = [simulate_run(_cfg(top, effects=eff), tmp_path, seed=5 + i) for i, top in enumerate((5.0, 15.0, 25.717))]
    res = identify_campaign([read_recording(p) for p in paths])
    names = {c.name: c for c in res.checks}
    assert names["model_misfit"].severity == "warning" and res.chi2_per_dof > 1e3
    assert names["same_transducer_model"].severity == "refused" and "station discrepancy" in (
        names["same_transducer_model"].message)
    assert res.status == "refused" and all(p.value is None for p in res.parameters.values())
