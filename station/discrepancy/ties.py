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

Every model that fits is kept, however poorly it determines k_f: a model whose k_f or b_f is
barely determined (e.g. k_f against a free coupling stiffness) widens the spread, it is never dropped;
a parameter whose uncertainty in one of the models is not finite is reported not identifiable.  Only
a fit that is physically impossible (``plausible.implausible``: e.g. a negative delay longer than a
sample, a coupling far softer than the transducer) is not a possible truth: it stays listed with the
reason (``implausible`` in the JSON) and is left out of the average.

Averaging (model averaging, e.g. Hoeting et al. 1999, Eq. 1-2): with weights w_m, values mu_m and
standard uncertainties u_m of one parameter in model m,
    mean = sum w mu / sum w,   u^2 = sum w (u_m^2 + (mu_m - mean)^2) / sum w,
so S, k_f and b_f in ``parameters_after`` carry the spread between the models, not the uncertainty
of one of them.  The models of a tie (and of a withdrawn name) are equally good explanations, so the
stated uncertainty covers each of their values: u >= max |mu_m - mean| over them (two models A, B:
u >= |A - B| / 2, the truth of either within 1 u of the mean).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TypedDict

import numpy as np

from station.discrepancy.data import RigData
from station.discrepancy.estimates import ORDER_AMBIGUITY, EstimateJson, effect_estimates
from station.discrepancy.fit import ModelFit, fit_model
from station.discrepancy.physical import implausible
from station.discrepancy.search import Candidate, fit_candidate
from station.ident.result import Estimate

log = logging.getLogger(__name__)
TIE_CHI2 = 10.0
MATTERS = 0.1
AVERAGED = (("S", "V/N"), ("k_f", "N/m"), ("b_f", "N*s/m"))


class ModelJson(TypedDict):
    """A tied model: its effects and their shown parameters as estimates, chi^2, BIC, its weight in the
    average, why it is implausible (or None), and the transducer's S (V/N), k_f (N/m), b_f (N s/m) under it."""

    effects: list[str]
    parameters: dict[str, EstimateJson]
    chi2: float
    bic: float
    weight: float
    implausible: str | None
    S: EstimateJson
    k_f: EstimateJson
    b_f: EstimateJson


class TieJson(TypedDict):
    kind: str
    candidates: list[ModelJson]
    message: str


@dataclass(frozen=True)
class Model:
    """One model of a tie: its effects, the fit, its weight in the average."""

    fit: ModelFit
    weight: float
    implausible: str = ""  # why the fit is physically impossible ('' if it is not): not averaged

    def to_json(self, show: Sequence[str]) -> ModelJson:
        f = self.fit
        params: dict[str, EstimateJson] = {}
        for name in show:
            if name in f.effects:
                params.update({k: v.to_dict() for k, v in effect_estimates(f, name).items()})
        S, k_f, b_f = (Estimate(f.values[k], f.std[k], u).to_dict() for k, u in AVERAGED)
        return {"effects": list(f.effects), "parameters": params, "chi2": float(f.chi2),
                "bic": float(f.chi2 + f.n_par * math.log(f.n_obs)), "weight": float(self.weight),
                "implausible": self.implausible or None, "S": S, "k_f": k_f, "b_f": b_f}


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

    def to_json(self) -> TieJson:
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
    models = [Model(final, 1.0, implausible(named, final, data))]
    names = [named]
    for name in others:
        alt = fit_candidate(data, reduced, name)
        if alt is not None and _finite(alt):
            models.append(Model(alt, 1.0, implausible(name, alt, data)))
            names.append(name)
    if len(models) < 2:
        return None

    def one(n: str, m: Model) -> str:
        why = f"; not physical ({m.implausible}), left out of the average" if m.implausible else ""
        return f"{n}: {_kf_bf(m.fit)} (chi2 {m.fit.chi2:.5g}){why}"

    text = "; ".join(one(n, m) for n, m in zip(names, models, strict=True))
    return Tie("tie", tuple(models), tuple(names),
               f"{' / '.join(names)} explain the data equally well (chi2 within {TIE_CHI2:g}); {text}; "
               f"k_f and b_f are averaged over them with their spread")


def _finite(f: ModelFit) -> bool:
    """A fit with finite S, k_f, b_f values (their uncertainties may be anything: a poorly determined
    k_f widens the average, it does not remove the model)."""
    return all(math.isfinite(f.values[k]) for k, _ in AVERAGED)


def undetectable(data: RigData, final: ModelFit, last: Sequence[tuple[Candidate, ModelFit]]) -> list[Tie]:
    """Unnamed effects of the last round whose BIC weight makes k_f or b_f less certain than the final
    model alone says (module docstring)."""
    out = []
    for c, f in last:
        if c.delta_chi2 < 1.0 or not _finite(f):
            continue  # no trace of it in these data (fitted at its neutral value)
        why = implausible(c.name, f, data)
        if why:
            log.info("undetectable %s left out: %s", c.name, why)
            continue  # not a possible truth
        w = math.exp(min(c.delta_bic, 60.0) / 2)
        grow = []
        for k in ("k_f", "b_f"):
            mean = (final.values[k] + w * f.values[k]) / (1 + w)
            var = (final.std[k] ** 2 + (final.values[k] - mean) ** 2
                   + w * (f.std[k] ** 2 + (f.values[k] - mean) ** 2)) / (1 + w)
            grow.append(math.sqrt(var) / max(final.std[k], 1e-300) - 1 if math.isfinite(var) else math.inf)
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


def averaged(final: ModelFit, ties: Sequence[Tie], final_implausible: str = "") -> dict[str, Estimate]:
    """S, k_f, b_f averaged over the final model and every model of the ties, each with its low-pass
    orders that fit as well (module docstring); physically impossible models are left out (the final
    model too, when a physical model of a tie remains).  The uncertainty covers every equally weighted model's value."""
    entries: list[tuple[ModelFit, float, bool]] = []  # (fit, weight, equally good: covered by u)
    alternative = any(t.kind == "tie" and any(m.fit is not final and not m.implausible for m in t.models)
                      for t in ties)
    if not (final_implausible and alternative):
        entries.append((final, 1.0, True))
    for t in ties:
        for m in t.models:
            if m.fit is not final and not m.implausible and all(m.fit is not e[0] for e in entries):
                entries.append((m.fit, m.weight, t.kind != "undetectable"))
    models: list[tuple[dict[str, float], dict[str, float], float, bool]] = []
    for fit, weight, equal in entries:
        models += [(v, u, w, equal) for v, u, w in _with_orders(fit, weight)]
    w = np.array([m[2] for m in models])
    out = {}
    for k, unit in AVERAGED:
        mu = np.array([m[0][k] for m in models])
        u = np.array([m[1][k] for m in models])
        mean = float(np.sum(w * mu) / w.sum())
        if not np.all(np.isfinite(u)):
            out[k] = Estimate(mean, math.nan, unit, False, "a model that fits as well leaves it undetermined "
                              "(its uncertainty is not finite there); see ties")
            continue
        std = float(math.sqrt(np.sum(w * (u**2 + (mu - mean) ** 2)) / w.sum()))
        cover = [abs(m - mean) for m, e in zip(mu, (m[3] for m in models), strict=True) if e]
        out[k] = Estimate(mean, max([std, *cover]), unit)
    return out
