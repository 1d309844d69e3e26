"""A transducer's history read as a lab reads it (``docs/batch.md``): per parameter (S, k_f, b_f and
the natural frequency f_0 with its end mass), the control charts (``station.trend.charts``), each
calibration's as-found comparison with the previous one's as-left value, the drift fitted with its
uncertainty and the risk of being out of tolerance at the next due date, and the interval each method
recommends (``station.trend.intervals``).  The intervals are recommendations for a person: nothing
here changes the interval in the register.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from station.lab.policy import TRENDED, AsLeft, Policy
from station.trend import charts, intervals

DAY_S = 86_400.0
RELIABILITY_TARGET = 0.95  # RP-1's usual end-of-period reliability target
CONFIDENCE = 0.9  # the variables method's confidence (NASA-HDBK-8739.19-5's example)
MIN_CHART = 3  # values before a chart is drawn
REFERENCE = 10  # values that set a chart's centre and s (phase I), at most


@dataclass(frozen=True)
class Point:
    """One calibration's value of one parameter: run, UNIX time, value and standard uncertainty."""

    run_id: str
    at: float
    value: float
    u: float


def natural_frequency(k_f: float, u_k_f: float, end_mass_kg: float | None,
                      u_end_mass_kg: float | None) -> tuple[float, float] | None:
    """f_0 = sqrt(k_f / m_e) / 2π of the transducer with its own end mass (Hz) and its standard
    uncertainty from u(k_f) and u(m_e); None without an end mass."""
    if not end_mass_kg or end_mass_kg <= 0 or not k_f or k_f <= 0:
        return None
    f0 = math.sqrt(k_f / end_mass_kg) / (2 * math.pi)
    rel = 0.5 * math.hypot(u_k_f / k_f, (u_end_mass_kg or 0.0) / end_mass_kg)
    return f0, f0 * rel


def _as_found(points: Sequence[Point], adjusted: dict[str, float], tol: float | None) -> list[dict[str, Any]]:
    out = []
    for prev, cur in itertools.pairwise(points):
        left = adjusted.get(prev.run_id)
        ref, source = (left, "adjusted") if left is not None else (prev.value, "identified")
        u_ref = prev.u
        diff = cur.value - ref
        u = math.hypot(cur.u, u_ref)
        row: dict[str, Any] = {"run_id": cur.run_id, "previous_run_id": prev.run_id, "as_left": ref,
                               "as_left_source": source, "as_found": cur.value, "difference": diff, "u": u,
                               "z": diff / u if u > 0 else None, "days": (cur.at - prev.at) / DAY_S}
        if tol is not None:
            limit = tol * abs(ref)
            row |= {"tolerance": limit, "in_tolerance": abs(diff) <= limit}
        out.append(row)
    return out


def _intervals(found: list[dict[str, Any]], pol: Policy, tol: float | None,
               last: Point, adjusted_last: float | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if tol is None:
        return {"note": "no tolerance in the register's policy for this parameter: no interval is computed"}
    judged = [f for f in found if "in_tolerance" in f]
    i0 = pol.interval_days
    if i0 is None:
        out["a3"] = {"note": "no interval assigned in the register's policy"}
    else:
        window = min(56.0, i0 / 2)
        at_i0 = [f for f in judged if abs(f["days"] - i0) <= window]
        if at_i0:
            r = intervals.a3(sum(bool(f["in_tolerance"]) for f in at_i0), len(at_i0), i0, target=RELIABILITY_TARGET)
            out["a3"] = {"interval_days": r.interval, "calculated_days": r.calculated,
                         "rejection_confidence": r.rejection_confidence,
                         "observed_reliability": r.observed_reliability,
                         "reliability_range": list(r.reliability_range), "n": r.n, "in_tolerance": r.in_tolerance}
        else:
            out["a3"] = {"note": f"no calibration {i0:g} ± {window:g} days after the previous one"}
    days = np.array([f["days"] for f in judged])
    if days.size >= 6:
        edges = np.unique(np.quantile(days, [0, 1 / 3, 2 / 3, 1]))
        bins = np.clip(np.searchsorted(edges, days, side="right") - 1, 0, edges.size - 2)
        ti, ri, ni = [], [], []
        for b in range(edges.size - 1):
            sel = bins == b
            if sel.sum() >= 2:
                ti.append(float(np.mean(days[sel])))
                ni.append(float(sel.sum()))
                ri.append(float(np.mean([bool(judged[i]["in_tolerance"]) for i in np.flatnonzero(sel)])))
        if len(ti) >= 2 and min(ti) > 0:
            models = intervals.s2(ti, ri, ni, target=RELIABILITY_TARGET)
            out["s2"] = {"interval_days": models[0].interval, "model": models[0].name,
                         "models": [{"name": m.name, "parameters": list(m.parameters), "interval_days": m.interval,
                                     "log_likelihood": m.log_likelihood} for m in models]}
    if "s2" not in out:
        out["s2"] = {"note": "the binomial method needs at least 6 judged calibrations at two or more intervals"}
    if len(found) >= 3:
        y0 = adjusted_last if adjusted_last is not None else last.value
        v = intervals.variables([f["days"] for f in found], [f["difference"] for f in found], u0=last.u, y0=y0,
                                order=1, limits=(y0 - tol * abs(y0), y0 + tol * abs(y0)), confidence=CONFIDENCE)
        var: dict[str, Any] = {"drift_per_day": v.fit.coefficients[0], "s_yx": v.fit.s_yx,
                               "u_drift_per_day": math.sqrt(v.fit.covariance[0][0]), "confidence": CONFIDENCE}
        horizon = 10 * max(f["days"] for f in found)
        if math.isnan(v.reliability_interval):
            var["note"] = f"the confidence bound stays within the tolerance for {horizon:.0f} d (10x the longest gap)"
        elif v.reliability_interval == 0:
            var["note"] = "the confidence bound is outside the tolerance already at the as-left value"
        else:
            var["interval_days"] = v.reliability_interval
        out["variables"] = var
    else:
        out["variables"] = {"note": "the variables method needs at least 3 as-found comparisons"}
    out["reliability_target"] = RELIABILITY_TARGET
    return out


def transducer_trends(series: dict[str, tuple[str, list[Point]]], pol: Policy,
                      as_left: dict[str, dict[str, AsLeft]], *, lam: float = charts.EWMA_LAMBDA,
                      L: float = charts.EWMA_L, now: float | None = None) -> dict[str, Any]:
    """Per parameter ({name: (unit, time-ordered points)}): charts, as-found, drift risk, intervals."""
    out: dict[str, Any] = {"check_standard": pol.check_standard, "policy": pol.to_dict(), "parameters": {},
                           "note": "intervals are recommendations for a person's decision; none is applied"}
    for name in TRENDED:
        if name not in series:
            continue
        unit, points = series[name]
        points = sorted(points, key=lambda p: p.at)
        adjusted = {run: a[name].value for run, a in as_left.items() if name in a}
        tol = pol.tolerances.get(name)
        doc: dict[str, Any] = {"unit": unit, "tolerance_relative": tol,
                               "points": [p.__dict__ for p in points]}
        if len(points) >= MIN_CHART:
            values = [p.value for p in points]
            us = [p.u for p in points]
            ref = min(len(points) - 1, REFERENCE)  # limits from earlier values, never the newest
            doc["shewhart"] = charts.shewhart(values, uncertainties=us, reference=ref).to_dict()
            doc["ewma"] = charts.ewma(values, uncertainties=us, reference=ref, lam=lam, L=L).to_dict()
        else:
            doc["charts_note"] = f"{len(points)} calibrations: a chart needs {MIN_CHART}"
        found = _as_found(points, adjusted, tol)
        doc["as_found"] = found
        if points:
            last = points[-1]
            left = adjusted.get(last.run_id)
            if pol.interval_days is not None and tol is not None and len(points) >= 3 \
                    and len({p.at for p in points}) > 1:
                due = last.at / DAY_S + pol.interval_days
                nominal = left if left is not None else last.value
                r = intervals.drift_risk([p.at / DAY_S for p in points], [p.value for p in points],
                                         [max(p.u, 1e-300) for p in points], due_day=due, nominal=nominal,
                                         tolerance=tol * abs(nominal))
                doc["drift_risk"] = {"slope_per_day": r.slope_per_day, "u_slope_per_day": r.u_slope_per_day,
                                     "due": due * DAY_S, "predicted": r.predicted, "u_predicted": r.u_predicted,
                                     "probability_out_of_tolerance": r.probability_out_of_tolerance}
            else:
                doc["drift_risk"] = {"note": "needs a tolerance, an assigned interval and 3 calibrations "
                                             "at different times"}
            doc["intervals"] = _intervals(found, pol, tol, last, left)
        out["parameters"][name] = doc
    return out


def out_of_control(trends: dict[str, Any]) -> list[dict[str, Any]]:
    """The out-of-control points of every chart: parameter, chart kind, run."""
    flagged = []
    for name, doc in trends.get("parameters", {}).items():
        for kind in ("shewhart", "ewma"):
            chart = doc.get(kind)
            if not chart:
                continue
            for i in chart["out_of_control"]:
                flagged.append({"parameter": name, "chart": kind, "run_id": doc["points"][i]["run_id"],
                                "index": i})
    return flagged
