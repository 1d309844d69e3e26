"""Outside the catalogue is an answer: a name is given only when it makes physical sense and
explains the structure it claims.

After the selection, every named effect is checked:

* **bounds and sign** (``implausible``): its parameters must lie where the effect is physically
  possible on this rig (``BOUNDS``; e.g. a transducer nonlinearity of 5 % of capacity, a channel
  delay of more than a millisecond, a coupling softer than a tenth of the transducer, a mains line
  more than 2 % off 50 or 60 Hz are not what those names mean);
* **structure left in its band** (``left_in_band``): the final model's residual must not keep
  significant structure (``locate.in_basis``, p < 1e-6 over the steps) in the components the
  effect claims to explain (``CLAIMS``): an effect that explains part of a distortion of another
  form (e.g. the cubic term of a saturation) leaves the rest there.

A name failing either is withdrawn: the effect stays in the fitted model (it describes part of the
data), but it is not given as the explanation; the structure is reported as unexplained with where it
is, and the transducer parameters are averaged over the models with and without it (``ties``), so
that they carry the extra uncertainty.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from station.discrepancy.data import RigData
from station.discrepancy.fit import ModelFit, fit_model
from station.discrepancy.locate import Finding
from station.discrepancy.ties import Model, Tie

CLAIMS: dict[str, tuple[str, ...]] = {
    "coupling_compliance": ("fundamental",), "conditioner_lowpass": ("fundamental",),
    "channel_delay": ("fundamental",), "transducer_nonlinearity": ("harmonic",),
    "mains_interference": ("mains line",), "zero_drift": ("offset and drift",),
}
NONLINEARITY_MAX = 0.05  # |q|, |c| (relative to capacity)
DELAY_MAX_S = 1e-3
COUPLING_MIN = 0.1  # k_c / k_f
MAINS_REL = 0.02  # relative distance from 50 or 60 Hz
CUTOFF_MIN_HZ = 10.0


def implausible(name: str, fit: ModelFit, data: RigData) -> str:
    """Why the effect's fitted parameters are not physically plausible, or ''."""
    v = fit.values
    if name == "transducer_nonlinearity":
        big = [k for k in ("quadratic", "cubic") if abs(v[k]) > NONLINEARITY_MAX]
        if big:
            return (f"{', '.join(f'{k} = {v[k]:.3g}' for k in big)}: a nonlinearity above "
                    f"{100 * NONLINEARITY_MAX:g} % of capacity is not a transducer's")
    if name == "channel_delay" and abs(v["delay_s"]) > DELAY_MAX_S:
        return f"delay {v['delay_s']:.3g} s is beyond {DELAY_MAX_S:g} s"
    if name == "coupling_compliance" and v["k_c"] < COUPLING_MIN * v["k_f"]:
        return f"k_c = {v['k_c']:.3g} N/m is below {COUPLING_MIN:g} k_f"
    if name == "conditioner_lowpass" and v["cutoff_hz"] < CUTOFF_MIN_HZ:
        return f"cut-off {v['cutoff_hz']:.3g} Hz is below {CUTOFF_MIN_HZ:g} Hz"
    if name == "mains_interference" and "frequency_hz" in v:
        f = v["frequency_hz"]
        if min(abs(f / 50 - 1), abs(f / 60 - 1)) > MAINS_REL:
            return f"frequency {f:.4g} Hz is not within {100 * MAINS_REL:g} % of 50 or 60 Hz"
    return ""


def left_in_band(name: str, findings: Sequence[Finding]) -> list[Finding]:
    """The findings (of the final model) in the components ``name`` claims to explain."""
    claims = CLAIMS.get(name, ())
    return [f for f in findings if f.channel == "force" and f.component.startswith(claims)]


def check(name: str, fit: ModelFit, data: RigData, findings: Sequence[Finding]) -> str:
    """Why the name is withdrawn ('' when it stands): bounds, or structure left in its band."""
    why = implausible(name, fit, data)
    if why:
        return f"{name} not given: {why}"
    left = left_in_band(name, findings)
    if left:
        where = "; ".join(f.text for f in left[:3])
        return (f"{name} not given: after adding it, significant structure is left in the band it claims "
                f"({where}): a distortion of a form the catalogue lacks")
    return ""


def withdraw(data: RigData, final: ModelFit, named: Sequence[str], findings: Sequence[Finding]
             ) -> tuple[dict[str, str], list[Tie]]:
    """The names withdrawn (name -> reason) and, per withdrawn name, the models with and without it
    (equal weights) for the transducer parameters' average."""
    out: dict[str, str] = {}
    ties: list[Tie] = []
    for name in named:
        why = check(name, final, data, findings)
        if not why:
            continue
        out[name] = why
        rest = {k: v for k, v in final.effects.items() if k != name}
        try:
            without = fit_model(data, rest, final.values)
        except (ValueError, np.linalg.LinAlgError, FloatingPointError):
            continue
        ties.append(Tie("unexplained", (Model(final, 1.0), Model(without, 1.0)), (name,),
                        f"{why}; k_f and b_f are averaged over the models with and without it"))
    return out, ties
