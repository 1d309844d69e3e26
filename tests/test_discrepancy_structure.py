"""Model gap: never confidently wrong about the model's structure.

Each case is a run of the project's simulator (``station.simulate``: paper Eq. 3 integrated with the
hidden effect, ``drivers.rig``), analysed by the workflow; the truth comes from the simulator's
configuration, never from the model under test.  Every case must give k_f and b_f within 3 stated
standard uncertainties, a relevant named finding, or a clear refusal.  End to end: a coupling
(k_c = 2 k_f) on a 3-40 Hz plan, then the steps the proposal names, recorded with a radius per step
and brought in through sinecal-csv v2, ends with the coupling named and k_f within its uncertainty.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from station.cli import main as station_main
from station.config import StationConfig, StepSpec, parse_config
from station.discrepancy import analyse_recording
from station.discrepancy.result import DiscrepancyResult
from station.discrepancy.scenarios import plan_steps, scenario_config
from station.ident.identify import identify_recording
from station.ident.response.gate import screen_step
from station.interchange import export_run, import_run, write_step_csv
from station.limits import check_steps
from station.recording import read_recording
from station.simulate import simulate_run
from tests.ident_support import sim


def _step(f: float, r: float) -> StepSpec:
    """A step as asked, its values not yet checked (the limits check them)."""
    return StepSpec.model_construct(crank_frequency_hz=f, crank_radius_m=r)

_cfg = scenario_config({})
assert _cfg.simulation is not None
KF, BF = _cfg.simulation.truth.k_f, _cfg.simulation.truth.b_f
FS = 20_000.0


def plan_3_40(effects: dict[str, Any], seed: int = 2, steps: list[dict[str, float]] | None = None,
              **kw: Any) -> StationConfig:
    """The 5 kN preset with ``effects`` and 6 steps at 3-40 Hz (or ``steps``)."""
    cfg = scenario_config(effects, seed=seed, **kw)
    d = cfg.model_dump(exclude_none=True)
    d["plan"]["steps"] = steps or plan_steps(cfg, 6, 3.0, 40.0)
    return parse_config(d)


def covered(rep: DiscrepancyResult, what: str = "") -> None:
    """k_f, b_f of parameters_after within 3 stated standard uncertainties of the truth."""
    for name, true in (("k_f", KF), ("b_f", BF)):
        e = rep.parameters_after[name]
        assert e.identifiable and abs(e.value - true) <= 3 * e.std, (
            f"{what}: {name} = {e.value:.6g} ± {e.std:.2g}, true {true:.6g} (z {(e.value - true) / e.std:+.3g}); "
            f"named {[x.name for x in rep.effects]}; ties {[t.message for t in rep.ties]}")


def no_unphysical_name(rep: DiscrepancyResult) -> None:
    for e in rep.effects:
        if e.name == "channel_delay":
            assert e.params["delay_s"].value >= -1.0 / FS, e.evidence


def spread_covered(rep: DiscrepancyResult) -> None:
    """The stated uncertainty covers every equally good (tied, physical) model's k_f and b_f."""
    for t in rep.ties:
        if t.kind == "undetectable":
            continue
        for m in t.models:
            if m.implausible:
                continue
            for k in ("k_f", "b_f"):
                e = rep.parameters_after[k]
                assert abs(m.fit.values[k] - e.value) <= e.std * (1 + 1e-9), (t.kind, k, m.fit.effects)


# -- the coupling (paper Eq. 8) and what else fits ------------------------------------------------

@pytest.fixture(scope="module")
def coupling_2kf(coupling_tie: tuple[StationConfig, Path, DiscrepancyResult]
                 ) -> tuple[StationConfig, DiscrepancyResult]:
    """k_c = 2 k_f, b_c = 0.5 b_f on the 3-40 Hz plan, seed 2 (``conftest.coupling_tie_config``: the run
    tests/test_discrepancy_propose.py resolves on the rig path; one analysis for both)."""
    cfg, _, rep = coupling_tie
    assert cfg.model_dump() == plan_3_40({"coupling_compliance": {"k_c": 2.0 * KF, "b_c": 0.5 * BF}}).model_dump()
    return cfg, rep


@pytest.mark.slow
@pytest.mark.xdist_group("coupling_2kf")  # one analysis of the coupling run, one worker
def test_coupling_twice_as_stiff_is_in_the_average_and_covered(
        coupling_2kf: tuple[StationConfig, DiscrepancyResult]) -> None:
    """k_c = 2 k_f: a coupling, a low-pass and a (negative, so unphysical) delay fit alike.  The coupling
    model (poorly determined k_f) stays in the average, the delay is never the name, and the stated
    uncertainty covers every tied model's value."""
    _, rep = coupling_2kf
    tied = {n for t in rep.ties for m in t.models for n in m.fit.effects}
    assert "coupling_compliance" in tied | {e.name for e in rep.effects}
    no_unphysical_name(rep)
    spread_covered(rep)
    covered(rep, "k_c = 2 k_f")
    out = rep.to_json()
    json.dumps(out)
    for t in out["ties"]:
        for c in t["candidates"]:
            assert c["implausible"] is None or "delay" in c["implausible"]


@pytest.mark.slow
@pytest.mark.parametrize(("effects", "what"), [
    ({"coupling_compliance": {"k_c": 10.0 * KF, "b_c": 0.0}}, "k_c = 10 k_f"),
    ({"conditioner_lowpass": {"order": 2, "cutoff_hz": 300.0},
      "mains_interference": {"frequency_hz": 50.0, "amplitudes_V": [1e-3], "phases_rad": [0.3]}}, "low-pass + mains"),
    ({"displacement_resonance": {"resonance_hz": 600.0, "damping": 0.3}}, "sensor resonance p 0.3"),
    ({"displacement_resonance": {"resonance_hz": 600.0, "damping": 1.0}}, "sensor resonance p 1"),
])
def test_fundamental_effects_are_covered(effects: dict[str, Any], what: str, tmp_path: Path) -> None:
    rep = analyse_recording(simulate_run(plan_3_40(effects), tmp_path, seed=2))
    no_unphysical_name(rep)
    spread_covered(rep)
    covered(rep, what)
    named = [e.name for e in rep.effects]
    if "conditioner_lowpass" in effects:  # the low-pass fits better than a delay: it is the name
        assert "conditioner_lowpass" in named and "channel_delay" not in named, named
    if "displacement_resonance" in effects:  # found (named, or tied with the name)
        assert "displacement_resonance" in named + [n for e in rep.effects for n in e.tied], named


@pytest.mark.slow
def test_coupling_and_lowpass_say_k_f_alone_is_not_determined(tmp_path: Path) -> None:
    """k_c = 3 k_f and a 500 Hz low-pass on a 3-40 Hz plan: a low-pass (or delay) fits within the noise,
    with the series stiffness as 'k_f' (2.33e7 N/m against 2.91e7).  Either k_f is covered, or the
    structure says that k_f alone rests on a stiff coupling and that these data do not determine it
    (the finding), and parameters_after state k_f and b_f as conditional on it (or withhold them),
    never a bare k_f, in the JSON too."""
    eff = {"coupling_compliance": {"k_c": 3.0 * KF, "b_c": 0.0},
           "conditioner_lowpass": {"order": 2, "cutoff_hz": 500.0}}
    rep = analyse_recording(simulate_run(plan_3_40(eff), tmp_path, seed=2))
    no_unphysical_name(rep)
    e = rep.parameters_after["k_f"]
    named = [x.name for x in rep.effects]
    if "coupling_compliance" in named:
        covered(rep, "coupling named")
    if abs(e.value - KF) > 3 * e.std:
        st = rep.structure
        assert st is not None and st.model.startswith("stiff coupling"), st
        assert st.k_f_alone_range is None or st.k_f_alone_range[0] <= KF <= st.k_f_alone_range[1], st.message
        assert any(n.startswith("structure: k_f rests on a stiff coupling") for n in rep.notes)
    if "coupling_compliance" not in named:
        assert not e.identifiable or e.flag == "conditional", (e, named)
        assert "stiff coupling" in e.reason, e.reason
        assert rep.parameters_after["b_f"].flag == "conditional" or not rep.parameters_after["b_f"].identifiable
        assert rep.to_json()["parameters_after"]["k_f"].get("flag") in ("conditional", None)


# -- the budget ---------------------------------------------------------------------------------

def _end_mass_cfg(factor: float) -> StationConfig:
    cfg = scenario_config({}, seed=3)
    d = cfg.model_dump(exclude_none=True)
    d["simulation"]["truth"]["end_mass_kg"] = d["transducer"]["end_mass_kg"]
    d["transducer"]["end_mass_kg"] = d["transducer"]["end_mass_kg"] * factor
    return parse_config(d)


@pytest.mark.slow
def test_parameters_after_carry_the_whole_budget(tmp_path: Path) -> None:
    """The end mass stated 5 % high (its default standard uncertainty): covered; on clean data the model
    gap's uncertainties are identify's (both carry the chain and mass terms: not the noise-only term,
    a tenth of them), or wider by the model averaging over effects the data neither find nor rule out
    (seed 3 of the rig's counter-based noise gives a clock skew at Delta chi2 2.4 weight 0.36: k_f's u
    1.7 times identify's)."""
    rep = analyse_recording(simulate_run(_end_mass_cfg(1.05), tmp_path / "me", seed=3))
    covered(rep, "end mass +5 %")
    clean = simulate_run(_end_mass_cfg(1.0), tmp_path / "clean", seed=3)
    rep = analyse_recording(clean)
    ident = identify_recording(read_recording(clean)).parameters
    for k in ("S", "k_f", "b_f"):
        ratio = rep.parameters_after[k].std / float(ident[k].std or math.nan)
        assert 0.7 < ratio < 2.0, (k, rep.parameters_after[k], ident[k])
    covered(rep, "clean")


# -- legal recordings: own time origins, short and two-cycle steps ------------------------------

def _export_edit(rec: Path, folder: Path, own_origins: bool = False, drop_rig: bool = False) -> Path:
    run = export_run(rec, folder / "exp")
    doc = yaml.safe_load(run.read_text(encoding="utf-8"))
    if drop_rig:
        doc.pop("rig")
        run.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    if own_origins:
        for st in doc["steps"]:
            f = run.parent / st["file"]
            d = np.loadtxt(f, delimiter=",", skiprows=1)
            d[:, 0] -= d[0, 0]
            write_step_csv(f, d)
    return import_run(run, folder / "imp")


@pytest.mark.slow
def test_delay_and_drift_with_own_time_origins(tmp_path: Path) -> None:
    """Each step's time starting at 0: the drift is each step's own; no harmonic the data do not hold is
    reported, the delay is found, k_f and b_f are covered; the import's rig limits allow a proposal."""
    eff = {"channel_delay": {"delay_s": 2e-5}, "zero_drift": {"rate_V_per_s": 3e-4, "quadratic_V_per_s2": 1e-5}}
    cfg = plan_3_40(eff, seed=1, steps=plan_steps(scenario_config(eff), 6, 5.0, 95.0))
    rep = analyse_recording(_export_edit(simulate_run(cfg, tmp_path / "sim", seed=1), tmp_path, own_origins=True))
    assert {e.name for e in rep.effects} == {"zero_drift", "channel_delay"}, [e.evidence for e in rep.effects]
    d = next(e for e in rep.effects if e.name == "channel_delay").params["delay_s"]
    assert abs(d.value - 2e-5) <= 4 * d.std
    assert not rep.effects[0].params["rate_V_per_s"].identifiable or rep.effects[0].name != "zero_drift"
    assert not [u for u in rep.unexplained if "harmonic" in u], rep.unexplained
    covered(rep, "delay + drift, own origins")
    out = rep.to_json()
    assert out["proposal"] is not None or "nothing to propose" in out["proposal_note"]


@pytest.mark.slow
def test_an_import_without_rig_limits_says_why_nothing_is_proposed(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """Without rig limits the JSON says why nothing is proposed; --config (the rig's station
    configuration) gives them."""
    cfg = scenario_config({}, seed=4, n_steps=3, record_s=0.3, settle_s=0.05)
    rec = _export_edit(simulate_run(cfg, tmp_path / "sim", seed=4), tmp_path, drop_rig=True)
    out = analyse_recording(rec, max_effects=1).to_json()
    assert out["proposal"] is None and "no rig limits" in out["proposal_note"] and "--config" in out["proposal_note"]
    station_yaml = tmp_path / "station.yaml"
    station_yaml.write_text(yaml.safe_dump(cfg.model_dump(mode="json", exclude_none=True)), encoding="utf-8")
    assert station_main(["discrepancy", str(rec), "--json", "--no-plot", "--max-effects", "1",
                         "--config", str(station_yaml)]) == 0
    given = json.loads(capsys.readouterr().out)
    assert given["proposal"] is not None or "no rig limits" not in given["proposal_note"], given["proposal_note"]


@pytest.mark.slow
@pytest.mark.parametrize(("freqs", "record_s", "short"), [((3.0, 8.0, 20.0, 40.0), 0.25, {0}),
                                                          ((1.0, 4.0, 12.0, 30.0), 0.9, {0})])
def test_steps_under_one_cycle_never_enter(freqs: tuple[float, ...], record_s: float, short: set[int],
                                           tmp_path: Path) -> None:
    """0.25 s records (3 Hz: 0.75 cycles) or a 1 Hz step of 0.9 s: left out with a note, never a
    negative frequency or a drive finding; the rest analysed and covered."""
    cfg = scenario_config({}, seed=5, record_s=record_s, settle_s=0.2)
    d = cfg.model_dump(exclude_none=True)
    radius = [min(0.01, 1000 / (26.3 * (2 * math.pi * f) ** 2)) for f in freqs]  # 1 kN of dynamic force
    d["plan"]["steps"] = [{"crank_frequency_hz": f, "crank_radius_m": float(f"{r:.3g}")}
                          for f, r in zip(freqs, radius, strict=True)]
    rep = analyse_recording(simulate_run(parse_config(d), tmp_path, seed=5))
    assert set(range(len(freqs))) - set(rep.steps) == short
    assert all(f > 0 for f in rep.f_hz)
    assert any("cycles" in n and "left out" in n for n in rep.notes), rep.notes
    assert not rep.drive.findings, rep.drive.findings
    covered(rep, f"{record_s} s records")


@pytest.mark.slow
def test_a_step_of_one_cycle_whose_frequency_cannot_be_told_is_left_out(tmp_path: Path) -> None:
    """A 4 Hz step of 0.25 s (one cycle, the fewest ``MIN_CYCLES`` lets in) whose sine fit cannot tell
    the frequency (this draw's variance of it came out negative; before, a bare math domain error
    ended the analysis): the step is left out with the reason, the rest analysed."""
    rec = sim(tmp_path, seed=101, record_s=0.25)
    rep = analyse_recording(rec, max_effects=1)
    assert 0 not in rep.steps and set(rep.steps) == {1, 2, 3, 4}, rep.steps
    assert all(f > 0 for f in rep.f_hz)
    assert any(n.startswith("step 0: step left out") and "cycles of 4 Hz" in n for n in rep.notes), rep.notes


def test_a_step_of_two_cycles_is_kept() -> None:
    """4 Hz for 0.5 s (two cycles), at every start phase: the step's sine fit is kept (the spectral peak
    of so short a window can be far off; the labelled frequency is the other start)."""
    t = np.arange(10_000) / FS
    rng = np.random.default_rng(1)
    for ph in np.linspace(0, 2 * np.pi, 12, endpoint=False):
        x = 0.01 * np.sin(2 * np.pi * 4.0 * t + ph) + 1e-7 * rng.standard_normal(t.size)
        u = -0.5 + 0.02 * np.sin(2 * np.pi * 4.0 * t + ph + 0.01) + 1e-4 * rng.standard_normal(t.size)
        item, checks = screen_step(0, t, x, u, 4.0, 0.01, FS)
        assert item is not None, (ph, [c.message for c in checks])
        assert item[2].frequency_hz == pytest.approx(4.0, rel=1e-3)


def test_a_refusal_under_json_is_a_json_document(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = station_main(["discrepancy", str(tmp_path / "missing.h5"), "--json", "--no-plot"])
    cap = capsys.readouterr()
    assert code != 0 and "error" in cap.err
    err = json.loads(cap.out)["error"]
    assert err["command"] == "discrepancy" and err["exit_code"] == code and "missing.h5" in err["message"]


# -- end to end: tie -> proposal -> the proposed run recorded elsewhere -> sinecal-csv v2 -> named --

@pytest.mark.slow
@pytest.mark.xdist_group("coupling_2kf")  # one analysis of the coupling run, one worker
def test_the_tie_gets_a_proposal_within_the_rig_limits(coupling_2kf: tuple[StationConfig, DiscrepancyResult]
                                                       ) -> None:
    """The tie this scenario is about (coupling, a low-pass and a negative, so never named, delay) gets
    a next run: the planned steps first, then steps that separate coupling and delay, all within the
    rig's limits (the station's own refusal rule)."""
    cfg, rep = coupling_2kf
    assert rep.effects and {"channel_delay", "coupling_compliance"} <= set(rep.effects[0].tied)
    assert rep.effects[0].name != "channel_delay", rep.effects[0].evidence
    prop = rep.proposal
    assert prop is not None and prop.measure == "delta_chi2", rep.proposal_note
    assert {"channel_delay", "coupling_compliance"} <= set(prop.separates)
    assert prop.current < 10 < prop.expected_information_gain
    assert prop.run_steps[: len(cfg.plan.steps)] == tuple((s.crank_frequency_hz, s.crank_radius_m)
                                                          for s in cfg.plan.steps)
    check_steps(cfg, [_step(f, r) for f, r in prop.run_steps])
    js = rep.to_json()["proposal"]
    assert js["steps"][0] == {"crank_frequency_hz": prop.steps[0][0], "crank_radius_m": prop.steps[0][1]}
    assert len({r for _, r in prop.run_steps}) > 1  # a radius per step: what v1 could not carry


@pytest.fixture(scope="module")
def follow_up(coupling_2kf: tuple[StationConfig, DiscrepancyResult], tmp_path_factory: pytest.TempPathFactory
              ) -> tuple[list[tuple[float, float]], Path, DiscrepancyResult]:
    """The proposed steps recorded on another rig (simulated), exported as sinecal-csv, imported and
    analysed: (the proposal's run steps, the exported RUN.yaml, the analysis)."""
    _, rep = coupling_2kf
    assert rep.proposal is not None, rep.proposal_note
    run_steps = list(rep.proposal.run_steps)
    tmp = tmp_path_factory.mktemp("follow")
    follow = plan_3_40({"coupling_compliance": {"k_c": 2.0 * KF, "b_c": 0.5 * BF}},
                       steps=[{"crank_frequency_hz": f, "crank_radius_m": r} for f, r in run_steps])
    elsewhere = export_run(simulate_run(follow, tmp / "rig", seed=102), tmp / "lab")
    return run_steps, elsewhere, analyse_recording(import_run(elsewhere, tmp / "imported"))


@pytest.mark.slow
@pytest.mark.xdist_group("coupling_2kf")  # one analysis of the coupling run, one worker
def test_the_proposed_run_recorded_elsewhere_and_imported_names_the_coupling(
        follow_up: tuple[list[tuple[float, float]], Path, DiscrepancyResult]) -> None:
    run_steps, elsewhere, after = follow_up
    doc = yaml.safe_load(elsewhere.read_text(encoding="utf-8"))
    assert doc["format_version"] == 2 and [s["crank_radius_m"] for s in doc["steps"]] == [r for _, r in run_steps]
    assert [e.name for e in after.effects] == ["coupling_compliance"], [e.evidence for e in after.effects]
    covered(after, "after the proposed steps")
    k = after.parameters_after["k_f"]
    assert abs(k.value - KF) <= 3 * k.std and k.std < 0.02 * KF  # determined, not just covered
    assert after.proposal is None, after.proposal  # nothing left to settle
