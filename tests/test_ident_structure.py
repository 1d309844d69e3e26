"""The model's structure as a stated assumption: a coupling in series with the transducer, the
displacement sensor's own resonance, the paper's Eq. 10 with a swarm, and short steps.

Every run is made by the project's simulator (Eq. 3 integrated with the hidden effect switched on in
``simulation.effects``; nothing of the identification under test) and, where a new user would have
it from elsewhere, exported and imported through sinecal-csv.  Each case ends right within 3 stated
standard uncertainties, with a named finding, or refused."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from station.cli import main
from station.ident.identify import identify_recording
from station.ident.paper.identify import seed_stability
from station.ident.structure import ADAPTER_COUPLING_RATIO, plausible_coupling
from station.recording import read_recording
from tests.ident_support import B, K, sim, via_csv

PLAN_3_40 = tuple((f, 1.5e-3) for f in (3.0, 10.0, 20.0, 40.0))
K_C = 20 * K  # a coupling below the 3-40 Hz plan's signature at 25 times the noise


def effects(eff: dict[str, Any], noise: float = 1.0) -> Any:
    def edit(d: dict[str, Any]) -> None:
        d["simulation"]["effects"] = eff
        d["simulation"]["displacement_noise_m"] *= noise
        d["simulation"]["conditioner_noise_V"] *= noise
    return edit


def identify_json(rec: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> dict[str, Any]:
    assert main(["identify", str(rec), "--json", "--no-write", *extra]) == 0
    return dict(json.loads(capsys.readouterr().out))


@pytest.mark.slow
def test_a_coupling_below_its_signature_leaves_k_f_alone_conditional_with_a_range_that_holds_the_truth(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """k_c = 20 k_f on a 3-40 Hz plan with noise enough that Eq. 9 fits: the series stiffness is right,
    k_f alone is conditional and its range covers the truth, and the finding says so.  (At k_c = 10 k_f
    this plan and noise show the coupling in about one realisation in four, and identify then rightly
    withholds k_f as coupling_suspected, the soft-coupling test's case; at 20 k_f Eq. 9 fit in each of
    seeds 1-12, with Eq. 9's k_f 17-20 u below the truth.)"""
    rec = via_csv(sim(tmp_path, PLAN_3_40, edit=effects({"coupling_compliance": {"k_c": K_C, "b_c": 0.0}}, 25)),
                  tmp_path)
    doc = identify_json(rec, capsys)
    st = doc["assumptions"]["structure"]
    assert st["equation"] == "Eq. 9" and st["coupling"]["assumed"] == "stiff"
    ser = doc["determined"]["series_stiffness"]
    assert abs(ser["value"] - 1 / (1 / K + 1 / K_C)) < 3 * ser["combined"]
    k = doc["parameters"]["k_f"]
    assert abs(k["value"] - K) > 3 * k["std"]  # Eq. 9's k_f is the series stiffness: off by -4.8 %
    assert k["flag"] == "conditional" and "stiff coupling" in k["reason"]
    lo, hi = doc["determined"]["transducer_stiffness_alone"]["range"]
    assert lo <= K <= hi
    assert st["coupling"]["k_c_lower_bound_N_per_m"] <= K_C  # the plan cannot exclude the truth
    found = {c["name"]: c for c in doc["checks"]}
    assert found["coupling_not_excluded"]["severity"] == "warning"


def test_a_soft_coupling_is_named_and_k_f_alone_withheld(tmp_path: Path) -> None:
    """k_c = 2 k_f (the paper's Eq. 8 effect) on the 3-40 Hz plan: Eq. 9 misfits, a coupling explains
    it: coupling_suspected, k_f alone withheld with its reason, the series stiffness right."""
    rec = read_recording(sim(tmp_path, PLAN_3_40, edit=effects({"coupling_compliance": {"k_c": 2 * K, "b_c": 0.0}})))
    res = identify_recording(rec)
    assert "coupling_suspected" in {c.name for c in res.checks}
    k = res.parameter("k_f")
    assert not k.identifiable and k.value is None and "contradict the stiff coupling" in k.reason
    ser = res.determined["series_stiffness"]
    assert abs(ser.value - 2 * K / 3) < 3 * ser.combined
    assert res.assumptions.structure.to_dict()["coupling"]["contradicted_by_the_data"]


@pytest.mark.slow
def test_with_the_steps_that_show_the_coupling_eq8_is_chosen_and_k_f_alone_is_right(tmp_path: Path) -> None:
    """The same k_c = 2 k_f with the higher steps the model-gap proposal names (16.5, 54.8, 67,
    100 Hz): the auto model takes Eq. 8, states it, and gives k_f and k_c within 3 u."""
    plan = (*PLAN_3_40, (16.5, 1.5e-3), (54.8, 6e-4), (67.0, 4e-4), (100.0, 1.5e-4))
    res = identify_recording(read_recording(sim(tmp_path, plan, edit=effects({"coupling_compliance": {
        "k_c": 2 * K, "b_c": 0.0}}))))
    assert res.model == "coupled" and res.assumptions.structure.to_dict()["equation"] == "Eq. 8"
    for name, truth in (("k_f", K), ("k_c", 2 * K)):
        p = res.parameter(name)
        assert p.value is not None and abs(p.value - truth) < 3 * p.std
    assert not {"coupling_suspected", "coupling_not_excluded"} & {c.name for c in res.checks}


def test_a_clean_run_states_its_structure_and_bounds_the_coupling(tmp_path: Path) -> None:
    """No coupling, the shipped plan's frequencies: the structure is stated, the plan excludes couplings
    softer than ADAPTER_COUPLING_RATIO k_s, k_f is right and unflagged, no warning."""
    res = identify_recording(read_recording(sim(tmp_path, record_s=0.5)))
    c = res.assumptions.structure.to_dict()["coupling"]
    assert c["k_c_lower_bound_over_k_s"] > ADAPTER_COUPLING_RATIO
    lo, hi = c["k_f_alone_range_N_per_m"]
    k = res.parameter("k_f")
    assert abs(k.value - K) < 3 * k.std and not k.flag and lo - 3 * k.std <= K <= hi and hi / lo - 1 < 0.01
    assert not [x for x in res.checks if x.severity != "info"]
    assert res.assumptions.structure.to_dict()["displacement_chain"]["response"] == "flat"


@pytest.mark.parametrize("damping", [0.3, 1.0])
@pytest.mark.slow
def test_a_displacement_sensor_resonance_is_flagged_or_corrected_when_stated(
        tmp_path: Path, damping: float) -> None:
    """A displacement sensor with its own resonance at 600 Hz: with the default (flat) chain the
    misfit is a named finding that names the sensor (its resonance found near 600 Hz); stated in
    RUN.yaml's measurement_chain (its data-sheet f_r and p with their uncertainties), H is corrected
    and k_f, b_f are right within their budget."""
    path = sim(tmp_path, PLAN_3_40, edit=effects({"displacement_resonance": {"resonance_hz": 600.0,
                                                                              "damping": damping}}))
    flat = identify_recording(read_recording(path))
    named = {c.name: c for c in flat.checks if c.severity == "warning"}
    assert "model_misfit" in named and "displacement_resonance_suspected" in named
    assert 300 < named["displacement_resonance_suspected"].values["resonance_hz"] < 1200
    chain = {"displacement_resonance_hz": 600.0, "displacement_resonance_std_hz": 30.0,
             "displacement_damping": damping, "displacement_damping_std": 0.1}
    rec = via_csv(path, tmp_path, doc=lambda d: d.update(measurement_chain=chain))
    res = identify_recording(read_recording(rec))
    assert res.assumptions.structure.to_dict()["displacement_chain"]["resonance_hz"] == 600.0
    for name, truth in (("k_f", K), ("b_f", B)):
        p = res.parameter(name)
        assert p.value is not None and abs(p.value - truth) < 3 * p.std
        assert res.budget[name].stds["chain_resonance"] > 0
    assert not [c for c in res.checks if c.severity == "warning"]


def test_a_swarm_answer_counts_only_when_stable_and_physical() -> None:
    """The rules behind the paper methods' verdict, on parameter sets: a coupling 300 times softer than
    the transducer is not physical; a value another seed does not reproduce is withheld."""
    kf = 2.91e7
    assert plausible_coupling(np.array([2e-3, kf, 17136.0, 10 * kf, 0.0]))
    assert not plausible_coupling(np.array([2e-3, kf, 17136.0, 0.003 * kf, 0.0]))
    assert not plausible_coupling(np.array([2e-3, kf, 17136.0, 10 * kf, -5.0]))
    theta, std = np.array([2e-3, kf, 17136.0]), np.array([1e-6, 1e4, 10.0])
    names = ("S", "k_f", "b_f")
    assert seed_stability("h2", theta, std, {1: theta + std, 2: theta - 2 * std}, names) == ["", "", ""]
    out = seed_stability("h2", theta, std, {1: theta * np.array([1.0, 1.08, 1.0])}, names)
    assert out[0] == out[2] == "" and "seed 1" in out[1]
    bad = seed_stability("h2", theta, std, {2: theta * np.array([1.0, -1.0, 1.0])}, names)
    assert all("seed 2" in r and "non-physical" in r for r in bad)


@pytest.mark.slow
def test_pso_on_eq10_gives_the_same_refusal_whatever_the_seed(tmp_path: Path) -> None:
    """PSO+ on Eq. 10 from one 4 Hz step: before, seed 1 gave nothing, seed 3 called S identifiable
    at -11 %, seed 10 k_c at 6e-4 k_f; now every seed gives the same verdict, nothing identifiable, each
    with its reason."""
    rec = read_recording(sim(tmp_path, ((4.0, 0.01), (12.0, 0.004)), record_s=2.0))
    verdicts = []
    for seed in (1, 3, 10):
        res = identify_recording(rec, "pso+", "h1", seed=seed)
        verdicts.append(tuple(p.identifiable for p in res.parameters.values()))
        assert all(p.reason for p in res.parameters.values() if not p.identifiable)
    assert verdicts == [(False,) * 5] * 3


def test_steps_of_two_cycles_are_kept(tmp_path: Path) -> None:
    """The campaign plan in the docs (4 Hz for 0.5 s: two cycles), each step cut to start at a zero
    crossing of the displacement (where the spectral peak alone led the frequency fit astray)."""
    path = sim(tmp_path, ((4.0, 1.5e-3), (20.0, 1.5e-3), (40.0, 1.5e-3)), record_s=0.75)

    def two_cycles_from_a_zero_crossing(a: np.ndarray) -> np.ndarray:
        t, x = a[:, 0], a[:, 1] - np.mean(a[:, 1])
        f = 1 / (np.median(np.diff(np.flatnonzero(np.diff(np.sign(x)) > 0))) * np.median(np.diff(t)))
        i0 = int(np.flatnonzero(np.diff(np.sign(x)) > 0)[0]) + 1
        n = round(2 / f / np.median(np.diff(t)))
        return a[i0:i0 + n]

    rec = via_csv(path, tmp_path, step={0: two_cycles_from_a_zero_crossing})
    res = identify_recording(read_recording(rec))
    assert res.extra["steps_used"] == [0, 1, 2]
    assert not {"frequency_fit_diverged", "no_signal"} & {c.name for c in res.checks}
    k = res.parameter("k_f")
    assert abs(k.value - K) < 3 * k.std
