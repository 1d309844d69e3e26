"""Ties and effects the data cannot rule out, and the transducer parameters averaged over them.

Tie.  In a round of the forward selection, the significant candidates whose chi^2 (scaled by the
round's Birge ratio B) is within ``TIE_CHI2`` of the best one fit equally: Delta BIC would then only
count parameters (k ln n) and always prefer the one-parameter explanation, which is no evidence.  For
each tied runner-up the final model is refitted with the named effect replaced by it.  The tied models
get equal weight.

Undetectable.  An effect of the last round that is not named, but improves the fit somewhat
(Delta chi^2 / B >= 1), is not ruled out either: its model
(the final one plus the effect) gets the weight exp(Delta BIC / 2) relative to the final model
(the BIC approximation of the posterior model probability, Schwarz 1978; Delta BIC = Delta chi^2 / B -
k ln n, as in the selection).  It is reported when it matters: when its term raises the combined
standard uncertainty of k_f or b_f by more than ``MATTERS`` (e.g. a delay of a few microseconds,
which below the resonance acts like damping).

Averaging (model averaging, e.g. Hoeting et al. 1999, Eq. 1-2): with weights w_m, values mu_m and
standard uncertainties u_m of one parameter in model m,
    mean = sum w mu / sum w,   u^2 = sum w (u_m^2 + (mu_m - mean)^2) / sum w,
so S, k_f and b_f in ``parameters_after`` carry the spread between the models, not the uncertainty
of one of them.  (Two equally weighted models A, B: u >= |A - B| / 2, so the truth of either lies
within 1 u of the mean.)
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from station.discrepancy.data import RigData
from station.discrepancy.fit import ModelFit, fit_model
from station.discrepancy.report import ORDER_AMBIGUITY, Candidate, Estimate, effect_estimates
from station.discrepancy.search import fit_candidate

log = logging.getLogger(__name__)
TIE_CHI2 = 10.0
MATTERS = 0.1
AVERAGED = (("S", "V/N"), ("k_f", "N/m"), ("b_f", "N*s/m"))


@dataclass(frozen=True)
class Model:
    """One model of a tie: its effects, the fit, its weight in the average."""

    fit: ModelFit
    weight: float

    def to_json(self, show: Sequence[str]) -> dict[str, Any]:
        f = self.fit
        params: dict[str, Any] = {}
        for name in show:
            if name in f.effects:
                params.update({k: v.to_dict() for k, v in effect_estimates(f, name).items()})
        return {"effects": list(f.effects), "parameters": params, "chi2": float(f.chi2),
                "bic": float(f.chi2 + f.n_par * math.log(f.n_obs)), "weight": float(self.weight),
                **{k: Estimate(f.values[k], f.std[k], u).to_dict() for k, u in AVERAGED}}


@dataclass(frozen=True)
class Tie:
    """A set of models the data do not decide between.  kind: "tie" (equally good explanations),
    "undetectable" (an effect neither named nor ruled out) or "unexplained" (a name withdrawn,
    ``plausible``: the models with and without the effect); ``differ``: the effects the models
    differ by; message: one sentence."""

    kind: str
    models: tuple[Model, ...]
    differ: tuple[str, ...]
    message: str

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "candidates": [m.to_json(self.differ) for m in self.models],
                "message": self.message}


def tied_names(ok: Sequence[Candidate], fits: Mapping[str, ModelFit], birge: float) -> tuple[str, ...]:
    """The candidates of ``ok`` whose scaled chi^2 is within ``TIE_CHI2`` of the best of them."""
    if not ok:
        return ()
    best = min(fits[c.name].chi2 for c in ok)
    return tuple(c.name for c in ok if (fits[c.name].chi2 - best) / birge < TIE_CHI2)


def _kf_bf(f: ModelFit) -> str:
    return f"k_f {f.values['k_f']:.6g} ± {f.std['k_f']:.2g} N/m, b_f {f.values['b_f']:.5g} ± {f.std['b_f']:.2g} N*s/m"


def tie_models(data: RigData, final: ModelFit, named: str, tied: Sequence[str]) -> Tie | None:
    """The final model and, for each tied runner-up, the final model with ``named`` replaced by it."""
    others = [t for t in tied if t != named and t not in final.effects]
    if not others:
        return None
    rest = {k: v for k, v in final.effects.items() if k != named}
    try:
        reduced = fit_model(data, rest, final.values)
    except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
        log.info("tie of %s: reduced model failed (%s)", named, exc)
        return None
    models = [Model(final, 1.0)]
    for name in others:
        alt = fit_candidate(data, reduced, name)
        if alt is not None and _usable(alt):
            models.append(Model(alt, 1.0))
    if len(models) < 2:
        return None
    names = (named, *[next(iter(set(m.fit.effects) - set(rest))) for m in models[1:]])
    text = "; ".join(f"{n}: {_kf_bf(m.fit)} (chi2 {m.fit.chi2:.5g})" for n, m in zip(names, models, strict=True))
    return Tie("tie", tuple(models), names,
               f"{' / '.join(names)} explain the data equally well (chi2 within {TIE_CHI2:g}); {text}; "
               f"k_f and b_f are averaged over them with their spread")


def _usable(f: ModelFit) -> bool:
    return all(math.isfinite(f.values[k]) and math.isfinite(f.std[k]) and f.std[k] < abs(f.values[k])
               for k, _ in AVERAGED)


def undetectable(final: ModelFit, last: Sequence[tuple[Candidate, ModelFit]]) -> list[Tie]:
    """Unnamed effects of the last round whose BIC weight makes k_f or b_f less certain than the final
    model alone says (module docstring)."""
    out = []
    for c, f in last:
        if c.delta_chi2 < 1.0 or not _usable(f):
            continue  # no trace of it in these data (fitted at its neutral value), or undetermined
        w = math.exp(min(c.delta_bic, 60.0) / 2)
        grow = []
        for k in ("k_f", "b_f"):
            mean = (final.values[k] + w * f.values[k]) / (1 + w)
            var = (final.std[k] ** 2 + (final.values[k] - mean) ** 2
                   + w * (f.std[k] ** 2 + (f.values[k] - mean) ** 2)) / (1 + w)
            grow.append(math.sqrt(var) / max(final.std[k], 1e-300) - 1)
        if max(grow) <= MATTERS:
            continue
        pars = "; ".join(f"{k} = {v.value:.3g} ± {v.std:.2g} {v.unit}" for k, v in effect_estimates(f, c.name).items()
                         if v.identifiable)
        out.append(Tie("undetectable", (Model(final, 1.0), Model(f, w)), (c.name,),
                       f"{c.name} is neither found nor ruled out (Delta chi2 {c.delta_chi2:.3g}, p = {c.p_value:.2g}; "
                       f"fitted {pars}); with it {_kf_bf(f)}, without it {_kf_bf(final)}; weight "
                       f"{w:.3g} (Delta BIC {c.delta_bic:.3g}) in the averaged k_f and b_f"))
    return out


def _with_orders(fit: ModelFit, weight: float) -> list[tuple[dict[str, float], dict[str, float], float]]:
    """(values, stds, weight) of a model and of its low-pass orders that fit as well (chi^2 within
    ``ORDER_AMBIGUITY`` B; their k_f, b_f with the model's uncertainties); they share the model's
    weight (one explanation, whose order the data do not fix, not several)."""
    out = [(fit.values, fit.std)]
    if "conditioner_lowpass" in fit.effects:
        order = fit.effects["conditioner_lowpass"]
        for o, chi2, kf, bf in fit.alternatives:
            if o != order and chi2 - fit.chi2 < ORDER_AMBIGUITY * fit.birge:
                out.append(({**fit.values, "k_f": kf, "b_f": bf}, fit.std))
    return [(v, u, weight / len(out)) for v, u in out]


def averaged(final: ModelFit, ties: Sequence[Tie]) -> dict[str, Estimate]:
    """S, k_f, b_f averaged over the final model and every model of the ties, each with its low-pass
    orders that fit as well (module docstring)."""
    models = _with_orders(final, 1.0)
    for t in ties:
        for m in t.models:
            if m.fit is not final:
                models += _with_orders(m.fit, m.weight)
    w = np.array([m[2] for m in models])
    out = {}
    for k, unit in AVERAGED:
        mu = np.array([m[0][k] for m in models])
        u = np.array([m[1][k] for m in models])
        mean = float(np.sum(w * mu) / w.sum())
        out[k] = Estimate(mean, float(math.sqrt(np.sum(w * (u**2 + (mu - mean) ** 2)) / w.sum())), unit)
    return out
