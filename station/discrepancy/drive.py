"""Check of the drive: is the recorded frame motion the slider crank's?

The force model takes the frame motion as recorded (``eiv``), so harmonics of the motion explain
nothing about the transducer; they say something about the drive.  The displacement harmonics
D_k (k = 2..K) of every step are compared with those of a slider crank of rod length L (paper Eq. 1
with the exact crank kinematics, ``model.crank_displacement_harmonics``; kappa = 1/L fitted by
weighted least squares, chi^2 = sum ||R_d (c_d - m_d(kappa)) / sigma_d||^2).  Outcomes:

* the harmonics are noise (kappa not distinct from 0): an ideal sine motion;
* a slider crank fits (chi^2 not significant at ``ALPHA``): rod length with its uncertainty;
* neither: the frame motion is distorted in a way the crank kinematics do not explain (e.g. a speed
  ripple of the drive): a finding on the displacement channel, by harmonic and step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypedDict

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.special import chdtrc

from station.discrepancy.data import RigData
from station.discrepancy.decompose import K_MAX
from station.discrepancy.estimates import EstimateJson
from station.discrepancy.model import crank_displacement_harmonics
from station.ident.result import Estimate

ALPHA = 1e-6


class DriveJson(TypedDict):
    """``DriveCheck.to_json``: the rod length (m) as an estimate, chi^2 (None if not finite), dof, findings,
    the summary."""

    rod_length_m: EstimateJson
    chi2: float | None
    dof: int
    findings: list[str]
    message: str


@dataclass(frozen=True)
class DriveCheck:
    """rod_length_m (not identifiable when the motion shows no crank harmonics), chi^2 and dof of the
    slider-crank fit to the displacement harmonics, findings (sentences, displacement channel), and a
    one-sentence summary."""

    rod_length_m: Estimate
    chi2: float
    dof: int
    findings: tuple[str, ...]
    message: str

    def to_json(self) -> DriveJson:
        return {"rod_length_m": self.rod_length_m.to_dict(), "chi2": _f(self.chi2), "dof": self.dof,
                "findings": list(self.findings), "message": self.message}


def _f(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _resid(data: RigData, kappa: float) -> np.ndarray:
    D = crank_displacement_harmonics(data.x1, kappa, K_MAX) * data.kmask
    md = np.zeros_like(data.cd)
    md[:, 0::2], md[:, 1::2] = D[:, 1:].real, -D[:, 1:].imag
    return np.einsum("sij,sj->si", data.Rd / data.sigma_d[:, None, None], data.cd - md)


def check_drive(data: RigData) -> DriveCheck:
    """Fit a slider crank to the recorded displacement harmonics (module docstring)."""
    valid = np.any(data.Rd != 0, axis=1)
    n_obs = int(valid.sum())
    if n_obs == 0:
        return DriveCheck(Estimate(math.nan, math.nan, "m", False, "no displacement harmonics below the "
                                   "Nyquist limit"), math.nan, 0, (), "drive not checked (no harmonics)")
    r = np.abs(data.x1)
    d2 = np.abs(data.cd[:, 0] - 1j * data.cd[:, 1])
    ok = data.kmask[:, 1] & (r > 0)
    k0 = float(np.median(4 * d2[ok] / r[ok] ** 2)) if np.any(ok) else 0.0
    span = max(abs(k0), 1.0) * 4

    def chi2(k: float) -> float:
        e = _resid(data, k)[valid]
        return float(e @ e)

    res = minimize_scalar(chi2, bounds=(-span, span), method="bounded", options={"xatol": 1e-9 * span})
    kap, c2 = float(res.x), float(res.fun)
    h = 1e-3 * max(abs(kap), 1e-3)
    curv = (chi2(kap + h) - 2 * c2 + chi2(kap - h)) / h**2
    sk = math.sqrt(2.0 / curv) if curv > 0 else math.inf
    dof = max(n_obs - 1, 1)
    if abs(kap) <= 3 * sk or kap <= 0:
        why = (f"1/L = {kap:.3g} ± {sk:.2g} 1/m is not distinct from 0" if abs(kap) <= 3 * sk else
               f"1/L = {kap:.3g} ± {sk:.2g} 1/m is negative: no slider crank")
        rod = Estimate(math.nan, math.nan, "m", False, why)
    else:
        rod = Estimate(1 / kap, sk / kap**2, "m")
    findings: list[str] = []
    if chdtrc(dof, c2) < ALPHA or (not rod.identifiable and kap < 0 and abs(kap) > 3 * sk):
        e = _resid(data, kap if kap > 0 else 0.0)
        idx = [s.index for s in data.steps]
        for k in range(2, K_MAX + 1):
            c2k = np.sum(e[:, 2 * k - 4 : 2 * k - 2] ** 2, axis=1)
            sig = [i for i in range(data.n_steps) if data.kmask[i, k - 1] and chdtrc(2, c2k[i]) < 1e-3]
            if not sig:
                continue
            amp = max(abs(complex(data.cd[i, 2 * k - 4], data.cd[i, 2 * k - 3])) for i in sig)
            steps = ", ".join(str(idx[i]) for i in sig)
            findings.append(f"displacement harmonic {k}: frame motion not a slider crank's, up to {amp:.3g} m "
                            f"in steps {steps} (chi2 {float(c2k[sig].sum()):.3g}); the drive distorts the "
                            f"motion (e.g. a speed ripple); the force model takes the motion as recorded")
    if findings:
        msg = f"drive: the recorded frame motion is not a slider crank's (chi2 {c2:.4g} for {dof} dof)"
    elif rod.identifiable:
        msg = f"drive: slider crank, rod length {rod.value:.4g} ± {rod.std:.2g} m (chi2 {c2:.4g} for {dof} dof)"
    else:
        msg = f"drive: the frame motion is a sine within the noise ({rod.reason})"
    return DriveCheck(rod, c2, dof, tuple(findings), msg)
