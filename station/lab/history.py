"""A transducer's calibration history: its runs, their results with uncertainties, the approvals,
and drift of each parameter against the earlier calibrations (the nightly batch's rule,
``station.batch.summary.drift_checks``)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from station.batch.summary import PARAMS, drift_checks
from station.lab import audit
from station.lab.policy import AsLeft, Policy
from station.lab.store import RunRow, Store
from station.recording.stored import read_result

if TYPE_CHECKING:  # the trends (scipy's statistics) load with the first history that has them, not with the daemon
    from station.lab import trends

PARAM_NAMES = tuple(name for name, _ in PARAMS)


def runs_of(store: Store, transducer_id: str, limit: int = 500) -> list[RunRow]:
    """The transducer's runs, oldest first (at most the ``limit`` newest)."""
    rows = store.list_runs_of(transducer_id, limit)
    return sorted(rows, key=lambda r: (r.created, r.id))


def approvals(store: Store, run_ids: list[str]) -> dict[str, list[dict[str, Any]]]:
    """The approvals (audit trail) of each run: who, when, note (a certificate's issue is one)."""
    out: dict[str, list[dict[str, Any]]] = {}
    for action in (audit.CERTIFICATE_APPROVED, audit.CERTIFICATE_ISSUED):
        for e in audit.entries(store, action=action, limit=10_000):
            if e.target in run_ids:
                note = e.details.get("note", "") or (f"certificate {e.details['number']}" if "number" in e.details
                                                     else "")
                out.setdefault(e.target, []).append({"by": e.who, "at": e.at, "note": note})
    return out


def parameters_of(path: Path, result_name: str | None) -> dict[str, dict[str, Any]]:
    """S, k_f, b_f (value, std, unit) of a stored identification result; {} if none is readable."""
    if not result_name or not path.is_file():
        return {}
    try:
        doc = read_result(path, result_name)
    except (OSError, ValueError, KeyError):
        return {}
    params = (doc or {}).get("parameters") or {}
    if isinstance(params, list):  # older layout: a list of {name, ...}
        params = {p.get("name"): p for p in params}
    return {n: {"value": p.get("value"), "std": p.get("std"), "unit": p.get("unit", "")}
            for n, p in params.items() if n in PARAM_NAMES and isinstance(p, dict)}


def series_of(rows: list[RunRow], entries: list[dict[str, Any]]) -> dict[str, tuple[str, list[trends.Point]]]:
    """The completed runs' values per parameter (S, k_f, b_f and f_0 from k_f with the end mass of the
    register's record the run used), time-ordered, for the trends."""
    from station.lab import trends

    out: dict[str, tuple[str, list[trends.Point]]] = {}
    for r, e in zip(rows, entries, strict=True):
        if e["state"] != "completed":
            continue
        params = e["parameters"]
        for name, unit in PARAMS:
            p = params.get(name) or {}
            if isinstance(p.get("value"), (int, float)) and isinstance(p.get("std"), (int, float)):
                out.setdefault(name, (unit, []))[1].append(trends.Point(r.id, r.created, p["value"], p["std"]))
        k = params.get("k_f") or {}
        record = json.loads(r.transducer_json or "{}")
        if isinstance(k.get("value"), (int, float)) and isinstance(k.get("std"), (int, float)):
            f0 = trends.natural_frequency(k["value"], k["std"], record.get("end_mass_kg"),
                                          record.get("end_mass_std_kg"))
            if f0 is not None:
                out.setdefault("f_0", ("Hz", []))[1].append(trends.Point(r.id, r.created, *f0))
    return out


def history(rows: list[RunRow], recordings_dir: Path, approved: dict[str, list[dict[str, Any]]],
            policy: Policy | None = None, as_left: dict[str, dict[str, AsLeft]] | None = None,
            **chart_options: float) -> dict[str, Any]:
    """The history document (reads the results beside the recordings: call it off the event loop).
    With the transducer's ``policy`` (and its adjustments), it carries the trends: control charts,
    as-found comparisons, drift risk and interval recommendations (``station.lab.trends``)."""
    entries: list[dict[str, Any]] = []
    for r in rows:
        params = parameters_of(recordings_dir / r.recording, r.result_name) if r.recording else {}
        entries.append({"run_id": r.id, "state": r.state, "created": r.created, "operator": r.operator,
                        "top_mass_kg": r.top_mass_kg, "recording": r.recording,
                        "recording_sha256": r.recording_sha256,
                        "standards": [s.get("id") for s in json.loads(r.standards_json or "[]")],
                        "parameters": params, "approvals": approved.get(r.id, []), "drift": {}})
    flagged = []
    for name in PARAM_NAMES:
        with_value = [e for e in entries if e["state"] == "completed"]
        series = [((e["parameters"].get(name) or {}).get("value"), (e["parameters"].get(name) or {}).get("std"))
                  for e in with_value]
        for e, check in zip(with_value, drift_checks(series), strict=True):
            e["drift"][name] = asdict(check)
            if check.flagged:
                flagged.append({"run_id": e["run_id"], "parameter": name, "deviation": check.deviation,
                                "u_c": check.u_c})
    doc: dict[str, Any] = {"runs": entries, "flagged": flagged, "units": dict(PARAMS)}
    if policy is not None:
        from station.lab import trends

        doc["trends"] = trends.transducer_trends(series_of(rows, entries), policy, as_left or {}, **chart_options)
        doc["out_of_control"] = trends.out_of_control(doc["trends"])
    return doc


@dataclass(frozen=True)
class CheckHold:
    """The check transducer out of control: certificates of runs started after ``since`` (UNIX s, its
    last good point) are held for review until a later check point is in control again."""

    transducer_id: str
    since: float
    run_id: str
    parameter: str
    reason: str


def check_hold(store: Store, recordings_dir: Path) -> CheckHold | None:
    """Whether a check transducer's newest point is out of control on any chart (S, k_f, b_f, f_0)."""
    from station.lab import policy as pol

    for tx in pol.check_transducers(store):
        rows = runs_of(store, tx)
        doc = history(rows, recordings_dir, {}, pol.policy(store, tx), pol.as_left_of(store, tx))
        for name, p in doc["trends"]["parameters"].items():
            pts = p["points"]
            if not pts:
                continue
            newest = len(pts) - 1
            if any(newest in (p.get(kind) or {}).get("out_of_control", []) for kind in ("shewhart", "ewma")):
                bad = {i for kind in ("shewhart", "ewma") for i in (p.get(kind) or {}).get("out_of_control", [])}
                good = [i for i in range(newest) if i not in bad]
                since = pts[good[-1]]["at"] if good else pts[0]["at"]
                return CheckHold(tx, since, pts[newest]["run_id"], name,
                                 f"the check transducer {tx} is out of control ({name}, run {pts[newest]['run_id']}): "
                                 "certificates of runs made since its last good check are held for review")
    return None
