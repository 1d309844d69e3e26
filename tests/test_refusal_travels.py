"""A refusal is never swallowed and the structure reaches every result: the model gap builds on
identify, so a run identify refuses gives no parameters there either (the same reason, as a finding).
(A stiff-coupling k_f is the series stiffness, stated as conditional wherever the model gap reports
it: ``test_discrepancy_structure.test_coupling_and_lowpass_say_k_f_alone_is_not_determined``.)

The recordings come from the project's simulator (``station.simulate``: paper Eq. 3 integrated, with
the truth and the effects of its configuration), never from the code under test.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from station.config import StationConfig, parse_config
from station.discrepancy import analyse_recording
from station.discrepancy.scenarios import scenario_config
from station.ident.identify import identify_recording
from station.ident.response.gate import IdentificationRefused
from station.recording import read_recording
from station.simulate import simulate_run

_cfg = scenario_config({})


def _config(effects: dict[str, Any], **edit: Any) -> StationConfig:
    d = scenario_config(effects, n_steps=5, record_s=0.6, settle_s=0.2, seed=4).model_dump(exclude_none=True)
    for path, value in edit.items():
        *head, last = path.split("__")
        node = d
        for k in head:
            node = node.setdefault(k, {})
        node[last] = value
    return parse_config(d)


_ME = _cfg.transducer.end_mass_kg
assert _ME is not None
REFUSED_CASES = {
    # the sensitivity written in mV/N while the signal is in V (1000 x the true one), the end mass 5 %
    # above its stated value
    "sensitivity_in_mV_per_N": {"transducer__sensitivity_V_per_N": 2e-3, "simulation__truth__sensitivity_V_per_N": 2e-6,
                                "simulation__truth__end_mass_kg": 1.05 * _ME},
    # the top mass typed ten times too small (the rig carries the stated 25.717 kg)
    "top_mass_ten_times_too_small": {"rig__top_mass_kg": _cfg.rig.top_mass_kg / 10,
                                     "simulation__truth__load_mass_kg": _cfg.rig.load_mass_kg},
}


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(REFUSED_CASES))
def test_a_run_identify_refuses_gives_no_parameters_in_the_model_gap(tmp_path: Path, case: str) -> None:
    """Identify refuses; the model gap withholds S, k_f, b_f with the same reason and names the refusal
    among its findings (it used to report S with a noise-only uncertainty, z 1e5 and +68)."""
    cfg = _config({}, **REFUSED_CASES[case])
    path = simulate_run(cfg, tmp_path, seed=4)
    with pytest.raises(IdentificationRefused) as refused:
        identify_recording(read_recording(path))
    rep = analyse_recording(path)
    for k in ("S", "k_f", "b_f"):
        e = rep.parameters_after[k]
        assert not e.identifiable and e.value is None, (k, e)
        assert str(refused.value) in e.reason
    assert any(str(refused.value) in u and "refuses" in u for u in rep.unexplained), rep.unexplained
    assert rep.to_json()["parameters_after"]["S"]["value"] is None
