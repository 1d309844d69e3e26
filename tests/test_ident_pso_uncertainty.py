"""What the station states for the paper's swarm (PSO/PSO+): never S with a noise-only u that rests
on parameters the step does not determine.

Truth from the simulator (``tests.ident_support.sim``: Eq. 3 integrated, not the estimator).  On the
shipped 4 Hz step the swarm's Eq. 11 coefficients map to a negative k_f (withheld as non-physical)
and Eq. 10 is structurally undetermined, so nothing is reported today (``bench/pso_uncertainty.py``
measures it over 20 seeds).  The swarm states no uncertainty of the k_f and b_f it lands on, so
should it ever land on physical ones, S would carry a u conditional on them: such an S is withheld
(``identifiability.carried_to_determined`` with an unknown covariance).  The case is built by
handing the swarm's place RLS's physical coefficients on a step where that u is the smaller part of
S's uncertainty.
"""

from pathlib import Path

import numpy as np
import pytest

from station.ident.identifiability import carried_to_determined
from station.ident.identify import identify_recording
from station.ident.inputs import inputs_for, model_for
from station.ident.models import DigitalTF
from station.ident.paper import identify as paper_identify
from station.ident.paper.identify import step_frf
from station.ident.paper.protocol import paper_data
from station.ident.paper.pso import SECTION5_H2, PsoResult
from station.ident.paper.rls import rls_h2
from station.recording import read_recording
from tests.ident_support import sim

STEP = ((4.0, 0.01),)


def test_a_swarm_answer_that_determines_s_but_not_k_f_is_withheld_not_stated_with_the_noise_u(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rec = read_recording(sim(tmp_path, STEP, seed=10, record_s=1.5))
    data = paper_data(rec)
    r = rls_h2(data.x_id, data.y_id)

    def physical_swarm(form: str, d: object, settings: object, seed: int) -> tuple:
        mse = np.zeros(2)
        return r.b, r.a, PsoResult(np.zeros(3), 0.0, mse, mse, 0, SECTION5_H2, seed, np.zeros(2, dtype=np.int64))

    monkeypatch.setattr(paper_identify, "_swarm", physical_swarm)
    model = model_for(rec, "h2", inputs_for(rec))
    theta = model.from_digital(DigitalTF(r.b, r.a, data.T))
    assert theta[1] > 0 and theta[2] >= 0  # a physical answer, the same for every swarm seed
    cov_noise, rep = paper_identify.steady_state_uncertainty(model, theta, data, paper_identify.DEFAULT_POLICY)
    assert rep.identifiable == (True, False, False)  # S determined by the step, k_f and b_f not
    # what a noise-only statement would leave out: k_f's own scatter between noise draws (about 6 % for
    # RLS on this step) carried to S is larger than S's noise u (1.4-1.6 times on seeds 3, 5, 10, 11),
    # whatever this draw's miss
    carried = carried_to_determined(model, theta, step_frf(data), rep.identifiable,
                                    np.diag([0.0, (0.06 * theta[1]) ** 2, 0.0]))
    assert carried[0, 0] > cov_noise[0, 0]

    res = identify_recording(rec, "pso+", "h2")
    p = res.parameters["S"]
    assert not p.identifiable and p.value is None
    assert "k_f, b_f" in (p.reason or "") and "does not determine" in (p.reason or "")
    assert "S" not in res.budget
    assert not any(q.identifiable for q in res.parameters.values())


def test_with_the_undetermined_parameters_known_exactly_the_carried_term_is_zero(tmp_path: Path) -> None:
    """The same function carries RLS's covariance: a zero covariance of k_f, b_f adds nothing, and
    RLS's own adds a positive term to S only."""
    from station.ident.identifiability import carried_to_determined
    from station.ident.paper.identify import step_frf

    rec = read_recording(sim(tmp_path, STEP, seed=10, record_s=1.5))
    data = paper_data(rec)
    model = model_for(rec, "h2", inputs_for(rec))
    r = rls_h2(data.x_id, data.y_id)
    theta = model.from_digital(DigitalTF(r.b, r.a, data.T))
    frf = step_frf(data)
    assert not np.any(carried_to_determined(model, theta, frf, (True, False, False), np.zeros((3, 3))))
    c = carried_to_determined(model, theta, frf, (True, False, False), np.diag([0.0, (0.07 * theta[1]) ** 2, 0.0]))
    assert c[0, 0] > 0 and not np.any(c[1:]) and not np.any(c[:, 1:])
    unknown = carried_to_determined(model, theta, frf, (True, False, False), np.full((3, 3), np.nan))
    assert np.isnan(unknown[0, 0])


def test_a_small_swarm_lands_on_a_physical_answer_and_its_s_is_withheld_for_its_unstated_u(tmp_path: Path) -> None:
    """The tests' swarm size (24 x 60) reaches the paper's method (it used to be ignored) and gives a
    physical Eq. 11 answer on the 4 Hz step; the step determines S, but S rests on k_f, b_f."""
    from station.ident.paper.protocol import SwarmSize

    rec = read_recording(sim(tmp_path, STEP, seed=3, record_s=1.5))
    res = identify_recording(rec, "pso+", "h2", swarm=SwarmSize(24, 60))
    assert (res.extra["n_particles"], res.extra["n_iterations"]) == (24, 60)
    th = res.extra["theta_from_coefficients"]
    assert th[1] > 0 and th[2] >= 0
    reason = res.parameters["S"].reason or ""
    assert not res.parameters["S"].identifiable and "rests on k_f, b_f" in reason, reason
