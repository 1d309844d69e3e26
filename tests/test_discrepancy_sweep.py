"""Model-gap workflow over ranges wider than those where the data decide (coupling k_c 1-10 k_f,
low-pass cut-off 150-3000 Hz, delays 1-100 us, ``scenarios.draw_wide``): no run states k_f or b_f more
than 3 reported standard uncertainties from the truth, and an effect that is not named is shown as a
tie or as undetectable, or is too small to move k_f and b_f beyond their stated uncertainty."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from station.discrepancy import analyse_recording
from station.discrepancy.scenarios import WIDE_EFFECTS, draw_wide, scenario_config, simulate_scenario

_cfg = scenario_config({})
assert _cfg.simulation is not None
KF, BF = _cfg.simulation.truth.k_f, _cfg.simulation.truth.b_f


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(1000, 1003))  # one draw per wide effect; more: bench/discrepancy.py --wide-cases
def test_wide_ranges_are_never_confidently_wrong(seed: int, tmp_path: Path) -> None:
    name = WIDE_EFFECTS[seed % 3]
    eff = {name: draw_wide(name, np.random.default_rng(seed), KF, BF)}
    rep = analyse_recording(simulate_scenario(eff, tmp_path, seed=seed))
    p = rep.parameters_after
    for k, true in (("k_f", KF), ("b_f", BF)):
        assert abs(p[k].value - true) <= 3 * p[k].std, f"{k}: {p[k]} true {true:.6g} for {eff}; {rep.notes}"
    named = [e.name for e in rep.effects]
    shown = {n for t in rep.ties for m in t.models for n in m.fit.effects}
    if named and named[0] != name:
        assert name in shown, f"{eff} named {named} without a tie: {[t.message for t in rep.ties]}"
