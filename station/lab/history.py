"""A transducer's calibration history: its runs, their results with uncertainties, the approvals,
and drift of each parameter against the earlier calibrations (the nightly batch's rule,
``station.batch.summary.drift_checks``)."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

from station.batch.summary import PARAMS, drift_checks
from station.lab import audit
from station.recording.stored import read_result
from station.service.store import RunRow, Store

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


def history(rows: list[RunRow], recordings_dir: Path, approved: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """The history document (reads the results beside the recordings: call it off the event loop)."""
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
    return {"runs": entries, "flagged": flagged, "units": dict(PARAMS)}
