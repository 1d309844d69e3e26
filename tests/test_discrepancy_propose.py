"""The next run that settles a tie: planned-step weights against a real decomposition, proposed
steps within the rig's limits under every tied model, and end to end over the rig path: a coupling
compliance (k_c = 2 k_f) on a 3-40 Hz plan ties with a delay and a low-pass; running the proposed
steps names the coupling and recovers k_f within 3 standard uncertainties.  The same scenario's tie,
its proposal and the proposed run on the physics path (``station.simulate``, then sinecal-csv) are
tests/test_discrepancy_structure.py's: both read the one analysis of ``conftest.coupling_tie``."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.rig.model import spring_force_per_acceleration
from drivers.rig.params import CouplingCompliance, Transducer
from drivers.sim.clock import VirtualClock
from station.config import StationConfig
from station.discrepancy import analyse_recording
from station.discrepancy.data import prepare
from station.discrepancy.design import expected_chi2, planned_data, with_model
from station.discrepancy.fit import fit_model
from station.discrepancy.propose import candidate_steps
from station.discrepancy.result import DiscrepancyResult
from station.discrepancy.scenarios import scenario_config
from station.discrepancy.search import base_start
from station.limits import check_steps, force_limit_N
from station.recording import read_recording
from station.run.calibrate import run_and_identify
from station.run.request import RunRequest, StepSpec
from station.simulate import simulate_run


def _step(f: float, r: float) -> StepSpec:
    """A step as asked, its values not yet checked (the limits check them)."""
    return StepSpec.model_construct(crank_frequency_hz=f, crank_radius_m=r)


def test_planned_step_weights_match_a_measured_decomposition(tmp_path: Path) -> None:
    """R^T R of a planned step (the Gram of its basis) is that of a measured step at the same
    frequency and record length, from the real decomposition (within 2 %)."""
    rec = simulate_run(scenario_config({}, seed=3), tmp_path, seed=3)
    data = prepare(read_recording(rec))
    i = 2
    plan = planned_data(data, [(float(data.f_hz[i]), float(abs(data.x1[i])))], 1.0, 2.0)
    assert plan.n_steps == data.n_steps + 1
    A, B = data.Rf[i], plan.Rf[-1]
    K = int(data.kmask[i].sum())
    for sl in (slice(0, 2), slice(2 * K - 2, 2 * K)):  # fundamental and top harmonic blocks
        ga, gb = A[:, sl].T @ A[:, sl], B[:, sl].T @ B[:, sl]
        assert np.allclose(np.diag(gb), np.diag(ga), rtol=0.02), (np.diag(ga), np.diag(gb))
    assert plan.sigma_f[-1] == pytest.approx(float(np.median(data.sigma_f)))
    # a model refitted to its own noise-free predictions leaves nothing
    base = fit_model(data, {}, base_start(data))
    assert expected_chi2(with_model(plan, base), base) < 1e-6


@pytest.mark.slow
def test_candidate_steps_stay_within_the_limits_under_every_model(
        coupling_tie_recording: tuple[StationConfig, Path]) -> None:
    """The coupling tie run (``conftest.coupling_tie_config``: k_c = 2 k_f, b_c = 0.5 b_f, 3-40 Hz)."""
    cfg, rec = coupling_tie_recording
    data = prepare(read_recording(rec))
    stiff = fit_model(data, {}, base_start(data))
    soft = fit_model(data, {"coupling_compliance": 0}, {**stiff.values, "k_c": stiff.values["k_f"], "b_c": 0.0})
    steps = candidate_steps(cfg, data, [stiff, soft])
    assert len(steps) >= 10
    fr, rr = cfg.rig.crank_frequency_hz, cfg.rig.crank_radius_m
    M = data.total_mass_kg
    for f, r in steps:
        check_steps(cfg, [_step(f, r)])  # the station's own refusal rule
        assert fr.min <= f <= fr.max and rr.min <= r <= rr.max
        assert r * cfg.displacement_sensor.gain_V_per_m <= cfg.daq.displacement_range_V  # no clipped motion
        for fit in (stiff, soft):  # dynamic peak force, computed here from paper Eq. 8/9
            v = fit.values
            t = Transducer(k_f=v["k_f"], b_f=v["b_f"], m_e=data.end_mass_kg, m_l=data.load_mass_kg,
                           sensitivity_V_per_N=v["S"], capacity_N=data.capacity_N)
            cpl = CouplingCompliance(v["k_c"], v["b_c"]) if "coupling_compliance" in fit.effects else None
            amp = abs(spring_force_per_acceleration(t, cpl, np.array([f]))[0])
            peak = M * 9.80665 + amp * (2 * math.pi * f) ** 2 * r
            assert peak <= force_limit_N(cfg), (f, r, peak)


def _truth_ok(rep: Any, cfg: StationConfig) -> None:
    assert cfg.simulation is not None
    t = cfg.simulation.truth
    assert [e.name for e in rep.effects] == ["coupling_compliance"], [e.evidence for e in rep.effects]
    for name, true in (("k_f", t.k_f), ("b_f", t.b_f)):
        est = rep.parameters_after[name]
        assert abs(est.value - true) <= 3 * est.std, (name, est.value, est.std, true)


@pytest.mark.slow
@pytest.mark.xdist_group("coupling_2kf")  # the tie run's analysis is test_discrepancy_structure's: one worker
def test_the_proposed_run_resolves_the_tie_on_the_rig_path(
        coupling_tie: tuple[StationConfig, Path, DiscrepancyResult], tmp_path: Path) -> None:
    """The same over the rig path of ``station calibrate --sim`` (emulated motor and DAQ bridge, the
    drivers, the procedure, the HDF5 recording, processing), in-process on the virtual clock; the
    wire itself is covered by the real-time layer (tests/test_calibrate_e2e.py, the page's one-click
    run in tests/test_web_readme.py)."""
    cfg, _, rep = coupling_tie  # conftest.coupling_tie_config: k_c = 2 k_f, b_c = 0.5 b_f, 3-40 Hz, 1 s records
    assert rep.proposal is not None and "coupling_compliance" in rep.proposal.separates
    req = RunRequest(transducer_id=cfg.transducer.id, top_mass_kg=cfg.rig.top_mass_kg,
                     steps=[StepSpec(crank_frequency_hz=f, crank_radius_m=r) for f, r in rep.proposal.run_steps])
    res = asyncio.run(run_and_identify(cfg, req, tmp_path / "rig", sim=True, sim_clock=VirtualClock()))
    assert res.outcome.exit_status == "completed", res.outcome
    after = analyse_recording(res.outcome.path)
    _truth_ok(after, cfg)


def test_without_the_station_configuration_nothing_is_proposed(tmp_path: Path) -> None:
    """A recording without any rig limits: no steps are offered, and the reason is given; a station
    configuration (``--config``) supplies the limits."""
    from dataclasses import replace

    from station.discrepancy.workflow import RunContext, run_context

    cfg = scenario_config({}, seed=4, n_steps=3, record_s=0.2, settle_s=0.05)
    rec = read_recording(simulate_run(cfg, tmp_path, seed=4))
    ctx = run_context(rec)
    assert isinstance(ctx, RunContext) and len(ctx.steps) == 3
    assert ctx.config.rig.crank_radius_m.max == pytest.approx(0.05)
    why = run_context(replace(rec, config={}))
    assert isinstance(why, str) and "no rig limits" in why and "--config" in why
    given = run_context(replace(rec, config={}), cfg)
    assert isinstance(given, RunContext) and given.config.transducer.capacity_N == rec.capacity_N
    assert given.config.rig.load_mass_kg == pytest.approx(rec.load_mass_kg)
