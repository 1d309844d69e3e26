"""Outside the catalogue is an answer: a name is given only when it makes physical sense and
explains the structure it claims.

After the selection, every named effect is checked:

* **bounds and sign** (``physical.implausible``): its parameters must lie where the effect is
  physically possible on this rig (e.g. a transducer nonlinearity of 5 % of capacity, a negative
  channel delay longer than a sample, a coupling softer than a tenth of the transducer are not what
  those names mean);
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
from station.discrepancy.physical import implausible
from station.discrepancy.ties import Model, Tie

CLAIMS: dict[str, tuple[str, ...]] = {
    "coupling_compliance": ("fundamental",), "conditioner_lowpass": ("fundamental",),
    "channel_delay": ("fundamental",), "transducer_nonlinearity": ("harmonic",),
    "mains_interference": ("mains line",), "zero_drift": ("offset and drift",),
    "displacement_resonance": ("fundamental",), "clock_skew": ("fundamental",),
}
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
