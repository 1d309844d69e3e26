"""A transducer with a history of completed calibrations on a real SQLite store and real result files
(S, k_f and b_f with their standard uncertainties), for the trend tests and the history page's."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from station.lab import register
from station.lab.store import RunRow, Store
from station.lab.trends import DAY_S
from station.recording.stored import write_result

TX = "TX-CHECK-1"
S0, K0, B0 = 2.0e-3, 2.91e7, 17136.0
U_REL = 2.8e-4


def add_transducer(store: Store) -> None:
    register.put_transducer(store, register.Transducer(TX, 5000.0, 2e-3, 0.12, 0.006, "check", "SN1"), "admin")


def add_runs(store: Store, rec: Path, n: int, *, drift_per_day: float = 0.0, step_at: int | None = None,
             seed: int = 5, days: float = 30.0, step_u: float = 3.0) -> list[str]:
    """n completed runs ``days`` apart whose S drifts (relative per day) or steps by ``step_u`` u at ``step_at``."""
    rng = np.random.default_rng(seed)
    t0 = 1.7e9
    ids = []
    for i in range(n):
        rid = f"run{i:03d}"
        at = t0 + i * days * DAY_S
        s = S0 * (1 + drift_per_day * i * days) + (step_u * U_REL * S0 if step_at is not None and i >= step_at else 0.0)
        s += rng.normal(0, U_REL * S0)
        k = K0 * (1 + rng.normal(0, 3e-3))
        b = B0 * (1 + rng.normal(0, 3e-3))
        name = f"{rid}.h5"
        (rec / name).write_bytes(b"not read by the history")
        write_result(rec / name, "identify_fd_sdof", {"parameters": {
            "S": {"value": s, "std": U_REL * S0, "unit": "V/N"},
            "k_f": {"value": k, "std": 3e-3 * K0, "unit": "N/m"},
            "b_f": {"value": b, "std": 3e-3 * B0, "unit": "N*s/m"}}})
        tj = json.dumps(register.transducer(store, TX).to_dict())
        store.insert_run(RunRow(id=rid, state="completed", transducer_id=TX, top_mass_kg=25.717, request_json="{}",
                                plan_json="{}", created=at, n_steps=3, recording=name,
                                result_name="identify_fd_sdof", operator="tina", transducer_json=tj))
        ids.append(rid)
    return ids


