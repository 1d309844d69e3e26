"""Model-gap workflow on every legal recording: steps with their own time origins (the interchange
format allows it), few steps, one step.  No crash; what the data cannot determine (the mains
frequency without a common clock, S/k_f/b_f from one step) is reported not identifiable."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from station.discrepancy import analyse_recording
from station.discrepancy.result import DiscrepancyResult
from station.discrepancy.scenarios import draw_scenario, scenario_config, simulate_scenario
from station.interchange import export_run, import_run, write_step_csv

_cfg = scenario_config({})
assert _cfg.simulation is not None
KF, BF = _cfg.simulation.truth.k_f, _cfg.simulation.truth.b_f


def _imported(tmp_path: Path, effects: dict, seed: int, keep: list[int] | None = None,
              own_origins: bool = True, n_steps: int = 6) -> Path:
    """A simulated run exported and imported again, each step's time starting at 0 (own origin),
    optionally keeping only the steps ``keep``."""
    run = export_run(simulate_scenario(effects, tmp_path / "sim", seed=seed, n_steps=n_steps), tmp_path / "exp")
    doc = yaml.safe_load(run.read_text())
    if keep is not None:
        doc["steps"] = [doc["steps"][i] for i in keep]
        run.write_text(yaml.safe_dump(doc))
    for st in doc["steps"] if own_origins else ():
        f = run.parent / st["file"]
        d = np.loadtxt(f, delimiter=",", skiprows=1)
        d[:, 0] -= d[0, 0]
        write_step_csv(f, d)
    return import_run(run, tmp_path / "imp")


def _honest(rep: DiscrepancyResult) -> None:
    for name, true in (("k_f", KF), ("b_f", BF)):
        e = rep.parameters_after[name]
        assert e.identifiable and abs(e.value - true) <= 3 * e.std, f"{name}: {e}, true {true:.6g}"


@pytest.mark.slow
@pytest.mark.parametrize(("seed", "keep"), [(1, None), (4, [0, 5])])  # six steps; two steps
def test_mains_without_common_clock(seed: int, keep: list[int] | None, tmp_path: Path) -> None:
    """Mains hum, every step with its own time origin (and with two steps only): no crash; the lines
    are fitted per step, their frequency and phases are not identifiable, the amplitudes are right."""
    eff = draw_scenario(["mains_interference"], seed=seed)
    rep = analyse_recording(_imported(tmp_path, eff, seed, keep))
    mains = [e for e in rep.effects if e.name == "mains_interference"]
    assert mains, (rep.unexplained, rep.rejected)
    p = mains[0].params
    assert not p["frequency_hz"].identifiable and "own time origins" in p["frequency_hz"].reason
    for h, a in enumerate(eff["mains_interference"]["amplitudes_V"], start=1):
        est = p[f"amplitude_V_{h}"]
        assert not p[f"phase_rad_{h}"].identifiable
        assert abs(est.value - a) <= 4 * est.std + 0.02 * a, (h, est, a)
    _honest(rep)


@pytest.mark.slow
# seed 2: its offsets point to a negative rod length (1/L = -0.09 +- 0.13 1/m), the old wrong answer's
# sign, so a rod length wrongly stated identifiable fails here (seed 1, 1/L = +0.09, went the same way)
@pytest.mark.parametrize("seed", [2])
def test_drift_without_common_clock_names_nothing_implausible(seed: int, tmp_path: Path) -> None:
    """A zero drift with own time origins: the per-step offsets it leaves are not explained by a
    nonlinearity or crank harmonics (the old answer: a rod length of -0.42 m); k_f and b_f right."""
    eff = draw_scenario(["zero_drift"], seed=seed)
    rep = analyse_recording(_imported(tmp_path, eff, seed))
    assert {e.name for e in rep.effects} <= {"zero_drift"}, [e.evidence for e in rep.effects]
    assert rep.drive.rod_length_m.identifiable is False or rep.drive.rod_length_m.value > 0
    _honest(rep)


@pytest.mark.slow
def test_one_step_is_analysed_not_refused(tmp_path: Path) -> None:
    """One step (35 Hz): the report is made; S, k_f, b_f are not identifiable from one fundamental."""
    rep = analyse_recording(_imported(tmp_path, {}, 5, keep=[2], own_origins=False, n_steps=4))
    assert len(rep.steps) == 1
    for k in ("S", "k_f", "b_f"):
        assert not rep.parameters_after[k].identifiable and "one step" in rep.parameters_after[k].reason
    assert rep.effects == ()


def test_a_parameter_the_steps_leave_free_has_infinite_not_zero_variance() -> None:
    """The step proposal's variance: a Jacobian column of zeros (one step cannot move k_f) is an
    undetermined parameter, not a perfectly known one (the pseudo-inverse alone says 0)."""
    from station.discrepancy.propose import linear_variance

    J = np.array([[1.0, 0.0, 2.0], [0.5, 0.0, -1.0], [2.0, 0.0, 0.3]])
    assert linear_variance(J, 1) == math.inf
    assert linear_variance(J, 0) == pytest.approx(float(np.linalg.inv(J[:, [0, 2]].T @ J[:, [0, 2]])[0, 0]))
    # two parameters that only move together: neither is determined alone
    assert linear_variance(np.array([[1.0, 1.0], [2.0, 2.0]]), 0) == math.inf
