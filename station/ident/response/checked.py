"""The measured frequency response of a recording, step by step, through the plausibility gate."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from station.ident.inputs import IdentInputs, inputs_for
from station.ident.response import frf as frfmod
from station.ident.response.gate import run_checks, screen_step
from station.ident.response.redundancy import clock_check, radius_check
from station.ident.response.sinefit import SineFit
from station.ident.result import Check
from station.recording import Recording
from station.vocabulary import Severity

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class StepSignal:
    """The signals of one step the gate kept, for the time-domain fits (OE): t (N,) in s, force
    u (N,) in V, the displacement fit (frequency, time origin) and its harmonic phasors X_h in m,
    shape (n_h,) complex (index 0 = fundamental)."""

    t: FloatArray
    u: FloatArray
    fit_x: SineFit
    X_h: NDArray[np.complex128]


@dataclass(frozen=True)
class CheckedResponse:
    """H(f) of the steps that passed (frf), their signals for OE, the step indices used, every
    check, the polarity sign of S (+1 / -1), and the force channel's mean per step used
    (``force_offsets``: (window centre s, offset V, its standard uncertainty V)) for the static check."""

    frf: frfmod.FrequencyResponse
    sigs: list[StepSignal]
    used: list[int]
    checks: list[Check] = field(default_factory=list)
    sign: float = 1.0
    force_offsets: tuple[tuple[float, float, float], ...] = ()

    @property
    def notes(self) -> list[str]:
        return [c.message for c in self.checks if c.severity != "info"]


def checked_response(rec: Recording, inputs: IdentInputs | None = None,
                     n_harmonics: int = 3) -> CheckedResponse:
    """Screen every step (``gate.screen_step``), then the run (``gate.run_checks``; raises
    ``IdentificationRefused``), check the redundant measurements against each other
    (``redundancy``: displacement against crank radius, the two converters' clocks), and assemble
    H(f) of the steps left."""
    inputs = inputs or inputs_for(rec)
    fs = rec.sample_rate_hz
    items: dict[int, frfmod.StepItem] = {}
    sigs: dict[int, StepSignal] = {}
    checks: list[Check] = []
    radii = {}
    for st in rec.steps:
        if not st.usable:
            checks.append(Check("samples_lost", Severity.WARNING, st.index, f"step {st.index} skipped: "
                                f"{st.lost_in_window} samples lost in its window", {"lost": st.lost_in_window}))
            continue
        x, u = rec.step_signals(st)
        t = np.arange(st.start_sample, st.end_sample) / fs
        item, found = screen_step(st.index, t, np.asarray(x, float), np.asarray(u, float),
                                  st.crank_frequency_hz, st.crank_radius_m, fs, n_harmonics)
        checks += found
        radii[st.index] = st.crank_radius_m
        if item is not None:
            items[st.index] = item
            sigs[st.index] = StepSignal(t, u, item[2], np.array((item[2].phasor, *item[2].harmonics)))
    more, used, sign = run_checks(items, checks, radii, rec.sensitivity_V_per_N, inputs.m_e + inputs.m_l)
    checks += more
    # redundant measurements: the displacement against the crank radius, one clock for both converters
    checks += [c for c in (radius_check({i: items[i][2] for i in used}, radii, inputs),
                           clock_check({i: (sigs[i].t, sigs[i].u, sigs[i].fit_x) for i in used}, n_harmonics))
               if c is not None]
    offsets = tuple((items[i][3].t_center_s, items[i][3].offset, items[i][3].offset_std) for i in used)
    return CheckedResponse(frfmod.assemble([items[i] for i in used]), [sigs[i] for i in used], used,
                           checks, sign, offsets)
