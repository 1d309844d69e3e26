"""Frozen result types of the discrepancy workflow and their JSON form (the ``--json`` contract)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from station.discrepancy.fit import ModelFit


def _num(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


@dataclass(frozen=True)
class Estimate:
    """A parameter: value and standard uncertainty (SI ``unit``); identifiable False when the data do
    not determine it (then value/std are reported as null with a reason)."""

    value: float
    std: float
    unit: str
    identifiable: bool = True
    reason: str = ""

    def to_dict(self) -> dict[str, Any]:
        if not self.identifiable:
            return {"value": None, "std": None, "unit": self.unit, "identifiable": False, "reason": self.reason}
        return {"value": _num(self.value), "std": _num(self.std), "unit": self.unit, "identifiable": True}


@dataclass(frozen=True)
class Candidate:
    """One catalogue effect tried in one round: chi^2 decrease (scaled by the Birge ratio of the
    larger model), added parameters, p-value of the likelihood-ratio test, Delta BIC (> 0 favours the
    effect), gap after (V)."""

    name: str
    delta_chi2: float
    added_params: int
    p_value: float
    delta_bic: float
    gap_V: float


@dataclass(frozen=True)
class AddedEffect:
    """An effect the workflow named: parameters with uncertainties, gap after it (V), overall and
    per step (n,), the evidence sentence, and the candidates of its round."""

    name: str
    params: dict[str, Estimate]
    gap_after: float
    gap_steps_after: tuple[float, ...]
    evidence: str
    candidates: tuple[Candidate, ...]
    parameters: dict[str, Estimate]
    tied: tuple[str, ...] = ()  # the candidates of its round that fit as well (itself included)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "params": {k: v.to_dict() for k, v in self.params.items()},
                "gap_after": float(self.gap_after), "evidence": self.evidence,
                "tied_with": [t for t in self.tied if t != self.name]}


@dataclass(frozen=True)
class DiscrepancyReport:
    """Result of ``analyse_recording``.

    base_gap / final_gap: RMS force residual (V) of the base and the final model over all record
    windows; noise_floor_V: RMS of the force noise measured from the data (the gap cannot go below);
    steps / f_hz / base_gap_steps / final_gap_steps: per step (recording index, Hz, V);
    base_findings: where the base model disagrees; unexplained: what no catalogue effect explains;
    rejected: the last round's candidates that were not significant; base_fundamental /
    final_fundamental: per step (f Hz, gain error %, phase error mrad, z) of the force fundamental.
    """

    recording: str
    base_gap: float
    final_gap: float
    noise_floor_V: float
    effects: tuple[AddedEffect, ...]
    parameters_before: dict[str, Estimate]
    parameters_after: dict[str, Estimate]
    unexplained: tuple[str, ...]
    base_findings: tuple[str, ...]
    steps: tuple[int, ...]
    f_hz: tuple[float, ...]
    base_gap_steps: tuple[float, ...]
    final_gap_steps: tuple[float, ...]
    rejected: tuple[Candidate, ...] = ()
    base_fundamental: tuple[tuple[float, float, float, float], ...] = ()
    final_fundamental: tuple[tuple[float, float, float, float], ...] = ()
    mains_search: str = ""
    notes: tuple[str, ...] = field(default_factory=tuple)
    wall_s: float = 0.0
    proposal: Any = None  # propose.Proposal: the next run that settles a tie, or None
    proposal_note: str = ""  # why there is no proposal ('' when there is one)
    structure: Any = None  # structure.Structure: the model parameters_after rests on, and what a coupling changes
    ties: tuple[Any, ...] = ()  # ties.Tie: models the data do not decide between
    drive: Any = None  # drive.DriveCheck: the recorded frame motion against the slider crank

    def to_json(self) -> dict[str, Any]:
        """The stable ``--json`` contract."""
        return {"base_gap": float(self.base_gap), "effects": [e.to_dict() for e in self.effects],
                "final_gap": float(self.final_gap),
                "parameters_before": {k: v.to_dict() for k, v in self.parameters_before.items()},
                "parameters_after": {k: v.to_dict() for k, v in self.parameters_after.items()},
                "unexplained": list(self.unexplained), "ties": [t.to_json() for t in self.ties],
                "notes": list(self.notes), "drive": None if self.drive is None else self.drive.to_json(),
                "proposal": None if self.proposal is None else self.proposal.to_json(),
                "proposal_note": self.proposal_note or None,
                "structure": None if self.structure is None else self.structure.to_json()}

    def to_dict(self) -> dict[str, Any]:
        """Everything (the contract plus details), e.g. to store with the recording's results."""
        out = self.to_json()
        out.update({
            "recording": self.recording, "noise_floor_V": self.noise_floor_V,
            "steps": list(self.steps), "f_hz": list(self.f_hz),
            "base_gap_steps": list(self.base_gap_steps), "final_gap_steps": list(self.final_gap_steps),
            "effect_gap_steps": {e.name: list(e.gap_steps_after) for e in self.effects},
            "base_findings": list(self.base_findings), "mains_search": self.mains_search,
            "fundamental_columns": ["f_hz", "gain_error_percent", "phase_error_mrad", "z"],
            "base_fundamental": [list(r) for r in self.base_fundamental],
            "final_fundamental": [list(r) for r in self.final_fundamental],
            "rounds": [[c.__dict__ for c in e.candidates] for e in self.effects],
            "rejected": [c.__dict__ for c in self.rejected]})
        return out


ORDER_AMBIGUITY = 10.0  # chi^2 units (times the Birge ratio): low-pass orders closer than this tie
TRANSDUCER = (("S", "V/N"), ("k_f", "N/m"), ("b_f", "N*s/m"))


def transducer_parameters(fit: ModelFit) -> dict[str, Estimate]:
    """S, k_f, b_f (and k_c, b_c when the coupling is in the model) as in ``station identify``."""
    out = {n: Estimate(fit.values[n], fit.std[n], u) for n, u in TRANSDUCER}
    if "coupling_compliance" in fit.effects:
        out.update(effect_estimates(fit, "coupling_compliance"))
    return out


def _idx(fit: ModelFit, name: str) -> int:
    return [q.name for q in fit.params].index(name)


def effect_estimates(fit: ModelFit, name: str) -> dict[str, Estimate]:
    """The effect's parameters in the units of ``drivers.rig.params`` (derived ones by the delta
    method: rod length L = 1/kappa, mains amplitude |Q_h| and phase angle(Q_h) + pi/2 of
    a sin(h w t + phase))."""
    v, s = fit.values, fit.std
    if name == "coupling_compliance":
        return {"k_c": Estimate(v["k_c"], s["k_c"], "N/m"), "b_c": Estimate(v["b_c"], s["b_c"], "N*s/m")}
    if name == "conditioner_lowpass":
        order = fit.effects[name]
        close = [a for a in fit.alternatives if a[0] != order and a[1] - fit.chi2 < ORDER_AMBIGUITY * fit.birge]
        est = {"order": Estimate(float(order), 0.0, "1"), "cutoff_hz": Estimate(v["cutoff_hz"], s["cutoff_hz"], "Hz")}
        if close:
            why = (f"orders {', '.join(str(a[0]) for a in close)} fit as well (Delta chi2 < {ORDER_AMBIGUITY:g}); "
                   f"k_f would be {', '.join(f'{a[2]:.6g}' for a in close)} N/m")
            est["order"] = Estimate(float(order), math.nan, "1", False, why)
        return est
    if name == "channel_delay":
        return {"delay_s": Estimate(v["delay_s"], s["delay_s"], "s")}
    if name == "displacement_resonance":
        return {"resonance_hz": Estimate(v["sensor_resonance_hz"], s["sensor_resonance_hz"], "Hz"),
                "damping": Estimate(v["sensor_damping"], s["sensor_damping"], "1")}
    if name == "crank_harmonics":
        kap, sk = v["inverse_rod_length_per_m"], s["inverse_rod_length_per_m"]
        if abs(kap) <= 2 * sk:
            return {"rod_length_m": Estimate(math.nan, math.nan, "m", False,
                                             f"1/L = {kap:.3g} +- {sk:.3g} 1/m is not distinct from 0")}
        return {"rod_length_m": Estimate(1 / kap, sk / kap**2, "m")}
    if name == "transducer_nonlinearity":
        return {"quadratic": Estimate(v["quadratic"], s["quadratic"], "1"),
                "cubic": Estimate(v["cubic"], s["cubic"], "1")}
    if name == "zero_drift" and "slope_s0" in v:
        why = ("the steps have their own time origins: the drift is fitted as each step's own offset, slope and "
               "curvature, and a rate over the run is not determined")
        return {"rate_V_per_s": Estimate(math.nan, math.nan, "V/s", False, why),
                "quadratic_V_per_s2": Estimate(math.nan, math.nan, "V/s^2", False, why)}
    if name == "zero_drift":
        return {"rate_V_per_s": Estimate(v["rate_V_per_s"], s["rate_V_per_s"], "V/s"),
                "quadratic_V_per_s2": Estimate(v["quadratic_V_per_s2"], s["quadratic_V_per_s2"], "V/s^2")}
    if name == "mains_interference" and "frequency_hz" not in v:
        return _mains_per_step(fit)
    if name == "mains_interference":
        out = {"frequency_hz": Estimate(v["frequency_hz"], s["frequency_hz"], "Hz")}
        h = 1
        while f"re_{h}" in v:
            i, j = _idx(fit, f"re_{h}"), _idx(fit, f"im_{h}")
            C = fit.cov[np.ix_([i, j], [i, j])]
            re, im = v[f"re_{h}"], v[f"im_{h}"]
            a = math.hypot(re, im)
            ga = np.array([re, im]) / max(a, 1e-300)
            gp = np.array([-im, re]) / max(a, 1e-300) ** 2
            out[f"amplitude_V_{h}"] = Estimate(a, math.sqrt(float(ga @ C @ ga)), "V")
            phase = (math.atan2(im, re) + 1.5 * math.pi) % (2 * math.pi) - math.pi
            out[f"phase_rad_{h}"] = Estimate(phase, math.sqrt(float(gp @ C @ gp)),
                                             "rad")
            h += 1
        return out
    raise KeyError(name)


NO_CLOCK = ("the steps have their own time origins (their windows overlap on the recorded time axis): the "
            "phase of a line between steps is unknown, so its frequency (and phase) is not determined")


def _mains_per_step(fit: ModelFit) -> dict[str, Estimate]:
    """Mains lines fitted with a phasor per step (no common clock): frequency and phases not
    identifiable; the amplitude of line h as the mean of its per-step amplitudes (V), standard
    uncertainty from their scatter (or the fit's, if larger) over sqrt(n)."""
    v = fit.values
    out = {"frequency_hz": Estimate(math.nan, math.nan, "Hz", False, NO_CLOCK)}
    h = 1
    while f"re_{h}_s0" in v:
        amps, i = [], 0
        while f"re_{h}_s{i}" in v:
            amps.append(math.hypot(v[f"re_{h}_s{i}"], v[f"im_{h}_s{i}"]))
            i += 1
        a = np.array(amps)
        fit_sd = max(fit.std[f"re_{h}_s0"], fit.std[f"im_{h}_s0"])
        sd = max(float(a.std(ddof=1)) if a.size > 1 else 0.0, fit_sd) / math.sqrt(a.size)
        out[f"amplitude_V_{h}"] = Estimate(float(a.mean()), sd, "V")
        out[f"phase_rad_{h}"] = Estimate(math.nan, math.nan, "rad", False, NO_CLOCK)
        h += 1
    return out
