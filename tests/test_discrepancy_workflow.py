"""Model-gap workflow end to end: every catalogue effect, drawn at random from its plausible
range with several seeds, is switched on in a simulated recording that the base model lacks; the
workflow (5 kN and 12.5 kN transducers) must name it first, estimate its parameters within their
stated uncertainty (|error| <= 4 standard uncertainties), shrink the gap to within 1.5x the noise floor
and recover k_f (0.1 %) and b_f (2 %; with the coupling free: within their stated uncertainty).
Also: nothing is named without an effect (the crank harmonics' runs), two effects are both found,
structure outside the catalogue (sidebands, in an imported run; a clipped step) ends in
``unexplained``, and an imported run (either polarity) gives the station's own answer."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from station.cli import main as station_main
from station.config import parse_config
from station.discrepancy import analyse_recording
from station.discrepancy.catalogue import CATALOGUE
from station.discrepancy.result import DiscrepancyResult
from station.discrepancy.scenarios import draw_scenario, scenario_config, simulate_scenario
from station.interchange import export_run, import_run, write_step_csv
from station.simulate import simulate_run

Z_MAX = 4.0
CASES = ((101, "5kN"), (202, "12k5N"))  # (seed, transducer preset of config/)


def _truth_params(name: str, cfg: dict[str, Any]) -> dict[str, float]:
    """Catalogue configuration -> the names the report uses."""
    if name == "conditioner_lowpass":
        return {"cutoff_hz": cfg["cutoff_hz"]}
    if name == "mains_interference":
        out = {"frequency_hz": cfg["frequency_hz"]}
        for h, (a, p) in enumerate(zip(cfg["amplitudes_V"], cfg["phases_rad"], strict=True), start=1):
            out[f"amplitude_V_{h}"], out[f"phase_rad_{h}"] = a, p
        return out
    if name == "clock_skew":  # the simulator's relative rate of the force converter's clock
        return {"clock_skew": cfg["relative"]}
    return {k: float(v) for k, v in cfg.items()}


def _check_params(rep: DiscrepancyResult, name: str, cfg: dict[str, Any]) -> None:
    eff = next(e for e in rep.effects if e.name == name)
    truth = _truth_params(name, cfg)
    if name == "conditioner_lowpass" and eff.params["order"].identifiable:
        assert eff.params["order"].value == cfg["order"]
    for k, true in truth.items():
        est = eff.params[k]
        assert est.identifiable, f"{name}.{k}: {est.reason}"
        err = est.value - true
        if k.startswith("phase_rad"):
            err = (err + math.pi) % (2 * math.pi) - math.pi
        assert abs(err) <= Z_MAX * est.std, f"{name}.{k} = {est.value:.6g} ± {est.std:.2g}, true {true:.6g}"


def _transducer_ok(rep: DiscrepancyResult, coupling: bool, transducer: str = "5kN") -> None:
    cfg = scenario_config({}, transducer=transducer)
    assert cfg.simulation is not None
    kf, bf = cfg.simulation.truth.k_f, cfg.simulation.truth.b_f
    p = rep.parameters_after
    ekf, ebf = abs(p["k_f"].value / kf - 1), abs(p["b_f"].value / bf - 1)
    if coupling or rep.ties:
        # with a tie (or an effect neither found nor ruled out) k_f and b_f carry the spread between
        # the models; the stated uncertainty must cover the truth
        # k_f and k_c trade off below the resonances: the data determine k_f only to its stated
        # uncertainty (about 0.3 % with these records), which the report must carry honestly
        assert ekf * kf <= Z_MAX * p["k_f"].std and ebf * bf <= Z_MAX * p["b_f"].std
    else:
        assert ekf <= 1e-3, f"k_f off by {100 * ekf:.3g} %"
        assert ebf <= 2e-2, f"b_f off by {100 * ebf:.3g} %"


# each effect on one transducer, the two transducers in turn down the catalogue; every effect on both
# (and more seeds) is bench/discrepancy.py's catalogue accuracy
@pytest.mark.slow
@pytest.mark.parametrize(("name", "seed", "transducer"),
                         [(name, *CASES[i % len(CASES)]) for i, name in enumerate(CATALOGUE)])
def test_each_catalogue_effect_is_named_estimated_and_removed(name: str, seed: int, transducer: str,
                                                              tmp_path: Path) -> None:
    eff = draw_scenario([name], seed=seed, transducer=transducer)
    rep = analyse_recording(simulate_scenario(eff, tmp_path, seed=seed, transducer=transducer))
    assert rep.effects, f"nothing named for {eff}; rejected {rep.rejected}"
    assert rep.effects[0].name == name, f"{[e.name for e in rep.effects]} for {eff}"
    assert rep.base_gap > rep.final_gap  # the effect made a gap the workflow removed
    assert rep.final_gap <= 1.5 * rep.noise_floor_V
    assert rep.effects[0].gap_after < rep.base_gap
    _check_params(rep, name, eff[name])
    # a coupling or the displacement sensor's resonance trades off against k_f below the resonances
    _transducer_ok(rep, coupling=name in ("coupling_compliance", "displacement_resonance"), transducer=transducer)
    # the bias of the base model is visible in its parameters when the effect acts on the fundamental
    if name in ("conditioner_lowpass", "coupling_compliance"):
        assert rep.parameters_before["k_f"].value != pytest.approx(rep.parameters_after["k_f"].value, rel=1e-3)


@pytest.mark.slow
@pytest.mark.parametrize(("names", "seed"), [(("transducer_nonlinearity", "crank_harmonics"), 5),
                                             (("channel_delay", "transducer_nonlinearity"), 7)])
def test_two_effects_are_both_found(names: tuple[str, str], seed: int, tmp_path: Path) -> None:
    """(The crank harmonics are a property of the recorded motion, which drives the model: the drive
    check, not the force model, finds them.)  Mains and a drift together: the reference run of
    ``test_an_imported_run_of_inverted_polarity_gives_the_same_answer``."""
    eff = draw_scenario(list(names), seed=seed)
    rep = analyse_recording(simulate_scenario(eff, tmp_path, seed=seed))
    want = sorted(n for n in names if n != "crank_harmonics")
    assert sorted(e.name for e in rep.effects) == want, f"{rep.effects} for {eff}"
    if "crank_harmonics" in names:
        rod = rep.drive.rod_length_m
        assert rod.identifiable and abs(rod.value - eff["crank_harmonics"]["rod_length_m"]) <= Z_MAX * rod.std
    assert rep.final_gap <= 1.5 * rep.noise_floor_V
    _transducer_ok(rep, coupling=False)


def _add_sidebands(run_yaml: Path, steps: range, ratio: float, amp_V: float, seed: int) -> None:
    """Amplitude-modulation sidebands at f (1 +- ratio) added to the force column of some steps."""
    rng = np.random.default_rng(seed)
    doc = yaml.safe_load(run_yaml.read_text())
    for i, st in enumerate(doc["steps"]):
        if i not in steps:
            continue
        f = run_yaml.parent / st["file"]
        d = np.loadtxt(f, delimiter=",", skiprows=1)
        w = 2 * np.pi * st["crank_frequency_hz"]
        ph = rng.uniform(-np.pi, np.pi, 2)
        d[:, 2] += amp_V * (np.cos((1 + ratio) * w * d[:, 0] + ph[0]) + np.cos((1 - ratio) * w * d[:, 0] + ph[1]))
        write_step_csv(f, d)


@pytest.mark.slow
def test_effect_outside_the_catalogue_is_unexplained_not_misnamed(tmp_path: Path) -> None:
    """Sidebands at f +- 0.4 f in steps 3-5 of an imported run: no catalogue name, located instead."""
    rng = np.random.default_rng(9)
    ratio, amp = float(rng.uniform(0.25, 0.45)), float(rng.uniform(1e-3, 3e-3))
    run = export_run(simulate_scenario({}, tmp_path / "sim", seed=9), tmp_path / "exp")
    _add_sidebands(run, range(3, 6), ratio, amp, seed=9)
    rep = analyse_recording(import_run(run, tmp_path / "imp"))
    assert rep.effects == (), [e.name for e in rep.effects]
    want = f"sidebands at f ± {ratio:.2f} f"
    hits = [u for u in rep.unexplained if want in u]
    assert hits and "steps 3–5" in hits[0], rep.unexplained
    assert rep.final_gap > 1.5 * rep.noise_floor_V  # the gap is left, and said to be left


@pytest.mark.slow
def test_cli_json_contract_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    eff = draw_scenario(["transducer_nonlinearity"], seed=12)
    rec = simulate_scenario(eff, tmp_path, seed=12)
    png = tmp_path / "gap.png"
    assert station_main(["discrepancy", str(rec), "--json", "--plot", str(png), "--max-effects", "2"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"base_gap", "effects", "final_gap", "parameters_before", "parameters_after",
                        "unexplained", "proposal", "proposal_note", "structure", "ties", "notes", "drive"}
    assert out["proposal"] is not None or isinstance(out["proposal_note"], str)
    st = out["structure"]
    assert st["model"].startswith("stiff coupling") and st["series_stiffness"]["unit"] == "N/m"
    assert isinstance(out["base_gap"], float) and isinstance(out["final_gap"], float)
    assert [e["name"] for e in out["effects"]] == ["transducer_nonlinearity"]
    for e in out["effects"]:
        assert set(e) == {"name", "params", "gap_after", "evidence", "tied_with"} and isinstance(e["evidence"], str)
    for key in ("parameters_before", "parameters_after"):
        for p in ("S", "k_f", "b_f"):
            assert set(out[key][p]) >= {"value", "std", "unit", "identifiable"}
    assert out["parameters_after"]["k_f"]["unit"] == "N/m"
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.slow
def test_an_imported_run_of_inverted_polarity_gives_the_same_answer(tmp_path: Path) -> None:
    """Two effects at once, mains and a drift, both found in the station's own recording (the case of
    ``test_two_effects_are_both_found`` for this pair); then export + ``station import`` (absolute step
    times kept) with the force polarity inverted (negative sensitivity): the station's own answer, same
    effects, same k_f and b_f, S with the sign.  (The import as exported, polarity kept, is
    ``test_discrepancy_outside``'s and the interchange tests' ground.)"""
    eff = draw_scenario(["mains_interference", "zero_drift"], seed=13)
    own = simulate_scenario(eff, tmp_path / "sim", seed=13)
    ref = analyse_recording(own)
    run = export_run(own, tmp_path / "exp")
    doc = yaml.safe_load(run.read_text())
    doc["transducer"]["sensitivity_V_per_N"] *= -1
    run.write_text(yaml.safe_dump(doc))
    for st in doc["steps"]:
        f = run.parent / st["file"]
        d = np.loadtxt(f, delimiter=",", skiprows=1)
        d[:, 2] *= -1
        write_step_csv(f, d)
    inv = analyse_recording(import_run(run, tmp_path / "inv"))
    names = sorted(eff)
    for rep in (ref, inv):
        assert sorted(e.name for e in rep.effects) == names, f"{rep.effects} for {eff}"
        assert rep.final_gap <= 1.5 * rep.noise_floor_V
    for p in ("k_f", "b_f"):
        assert inv.parameters_after[p].value == pytest.approx(ref.parameters_after[p].value, rel=1e-6)
    assert inv.parameters_after["S"].value == pytest.approx(-ref.parameters_after["S"].value, rel=1e-6)
    drift = next(e for e in inv.effects if e.name == "zero_drift").params["rate_V_per_s"].value
    assert drift == pytest.approx(-eff["zero_drift"]["rate_V_per_s"], abs=4 * next(
        e for e in inv.effects if e.name == "zero_drift").params["rate_V_per_s"].std)


@pytest.mark.slow
def test_clipped_step_is_left_out_and_reported_not_named(tmp_path: Path) -> None:
    """A force range too small for the top step clips it: clipping is not a catalogue effect (nor a
    model gap): the step is left out and reported; the other steps still fit with nothing named."""
    rng = np.random.default_rng(14)
    d = scenario_config({}, seed=14).model_dump(exclude_none=True)
    d["daq"]["force_range_V"] = float(rng.uniform(2.0, 3.0))
    rep = analyse_recording(simulate_run(parse_config(d), tmp_path, seed=14))
    assert rep.effects == ()
    assert any("clipped" in u and "left out" in u for u in rep.unexplained), rep.unexplained
    assert 5 not in rep.steps and rep.final_gap <= 1.5 * rep.noise_floor_V


@pytest.mark.slow  # over 2 s of CPU (the analysis and identify's); another draw with a nonlinearity on top:
# test_two_effects_are_both_found (rod length too), no effect named: the clipped step's and the sidebands' runs
@pytest.mark.parametrize("seed", (101,))
def test_crank_harmonics_are_a_check_of_the_drive(seed: int, tmp_path: Path) -> None:
    """A slider crank's displacement harmonics drive the force model as recorded: nothing is named,
    the gap is at the floor, k_f and b_f are right, and the drive check reports the rod length.
    These runs are also the proof that no effect names nothing: their force model holds no catalogue
    effect (the motion is the model's input), so the base model is the final one (as on the clipped
    step's and the sidebands' runs)."""
    eff = draw_scenario(["crank_harmonics"], seed=seed)
    rep = analyse_recording(simulate_scenario(eff, tmp_path, seed=seed))
    assert rep.effects == (), [e.evidence for e in rep.effects]
    assert rep.final_gap == rep.base_gap <= 1.5 * rep.noise_floor_V
    _transducer_ok(rep, coupling=False)
    rod = rep.drive.rod_length_m
    true = eff["crank_harmonics"]["rod_length_m"]
    assert rod.identifiable and abs(rod.value - true) <= Z_MAX * rod.std, (rod, true)
    assert rep.drive.findings == () and any(n.startswith("drive: slider crank") for n in rep.notes)


@pytest.mark.slow  # one analysis, two more from its kept decomposition
def test_the_daemon_gives_a_stored_analysis_again_and_recomputes_a_stale_one(tmp_path: Path,
                                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """``worker.discrepancy_job`` (POST /runs/{id}/discrepancy): asked again for the same recording,
    ``max_effects`` and software, the stored analysis is the answer (nothing computed, the file kept);
    another ``max_effects`` or another software version is computed anew."""
    import station.discrepancy as discrepancy
    from station.recording import read_result, write_result
    from station.service import worker

    rec = simulate_scenario({}, tmp_path, seed=4, n_steps=3, record_s=0.3)
    computed: list[int] = []
    analyse = discrepancy.analyse_recording

    def counted(path: Any, max_effects: int = 4, station: Any = None) -> DiscrepancyResult:
        computed.append(max_effects)
        return analyse(path, max_effects=max_effects, station=station)

    monkeypatch.setattr(discrepancy, "analyse_recording", counted)
    first = worker.discrepancy_job(str(rec), 1)
    stored = next((rec.parent / f"{rec.stem}.results").glob("results.discrepancy*"))
    inode = stored.stat().st_ino
    again = worker.discrepancy_job(str(rec), 1)
    assert computed == [1] and stored.stat().st_ino == inode
    assert json.dumps(again, sort_keys=True) == json.dumps(first, sort_keys=True)
    assert set(again) == set(worker.CONTRACT_KEYS)
    worker.discrepancy_job(str(rec), 2)
    assert computed == [1, 2]
    doc = read_result(rec, "discrepancy")
    assert doc is not None and doc["max_effects"] == 2
    write_result(rec, "discrepancy", {**doc, "software_version": "0.0.1"})  # stored by an older station
    worker.discrepancy_job(str(rec), 2)
    assert computed == [1, 2, 2]
