"""The environmental conditions of a run, stored in the recording's start document (metadata
``environment``) and stated on the certificate.

Entered values (the configuration's ``environment`` section, which a run request's configuration
carries) take precedence; without them a configuration with a ``simulation`` section reads the
simulated room sensor (its mean reading plus seeded scatter of 0.05 degC and 0.5 %rh); otherwise the
conditions are not recorded (``None``), and the certificate says so.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from station.config import StationConfig


def run_environment(cfg: StationConfig, seed: int | None = None) -> dict[str, Any] | None:
    """``{"temperature_c", "temperature_std_c", "relative_humidity_pct", "relative_humidity_std_pct",
    "source"}`` for the start document, or None when nothing is entered or measured."""
    env = cfg.environment
    if env.temperature_c is not None or env.relative_humidity_pct is not None:
        return {"temperature_c": env.temperature_c, "temperature_std_c": env.temperature_std_c,
                "relative_humidity_pct": env.relative_humidity_pct,
                "relative_humidity_std_pct": env.relative_humidity_std_pct, "source": "entered with the run"}
    sim = cfg.simulation
    if sim is None:
        return None
    rng = np.random.default_rng([sim.seed if seed is None else seed, 0x454E56])
    return {"temperature_c": round(sim.room_temperature_c + 0.05 * float(rng.standard_normal()), 2),
            "temperature_std_c": env.temperature_std_c,
            "relative_humidity_pct": round(sim.room_humidity_pct + 0.5 * float(rng.standard_normal()), 1),
            "relative_humidity_std_pct": env.relative_humidity_std_pct, "source": "simulated room sensor"}
