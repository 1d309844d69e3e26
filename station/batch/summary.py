"""Each transducer's parameters over time, with drift flagged against its history (docs/batch.md).

Drift rule, per parameter (S, k_f, b_f) and identification method, over the runs in start-time order:
the history of a run is every earlier run whose value was not itself flagged.  With n >= min_history
values x_i (standard uncertainties u_i, sample standard deviation s, mean m) a new value x with
standard uncertainty u is flagged when

    |x - m| > k * u_c,   u_c^2 = max(u^2, s^2) + u_m^2,   u_m^2 = max(sum(u_i^2) / n^2, s^2 / n)

with k = 3: u_c is the combined standard uncertainty of x - m.  The new value scatters by its own
uncertainty or by the run-to-run scatter of the history, whichever is larger (a transducer whose
remounting changes k_f by more than the noise-limited u is not "drifting" at every run); the mean is
known to its propagated uncertainty or to its scatter-based standard error, whichever is larger.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import statistics
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from station.batch.items import BatchItem

PARAMS: tuple[tuple[str, str], ...] = (("S", "V/N"), ("k_f", "N/m"), ("b_f", "N*s/m"))
COLUMN_UNIT = {"V/N": "V_per_N", "N/m": "N_per_m", "N*s/m": "N_s_per_m"}
K_DEFAULT = 3.0
MIN_HISTORY = 3
MAX_CHECK_RUNS = 1000  # check-run findings kept per transducer (about three years of nights)


@dataclass(frozen=True)
class DriftCheck:
    """The check of one value against its history.  deviation = value - history_mean and u_c in the
    parameter's unit; note says why a value was not judged ("" when it was)."""

    value: float | None
    u: float | None
    n_history: int
    history_mean: float | None
    u_c: float | None
    deviation: float | None
    flagged: bool
    note: str = ""


def drift_checks(series: Sequence[tuple[float | None, float | None]], *, k: float = K_DEFAULT,
                 min_history: int = MIN_HISTORY) -> list[DriftCheck]:
    """Checks of a time-ordered series of (value, standard uncertainty); None value = not identified."""
    hist: list[tuple[float, float]] = []
    out = []
    for x, u in series:
        if x is None or not math.isfinite(x):
            out.append(DriftCheck(None, None, len(hist), None, None, None, False, "no value"))
            continue
        uu = float(u) if u is not None and math.isfinite(u) else 0.0
        n = len(hist)
        if n < min_history:
            out.append(DriftCheck(x, uu, n, None, None, None, False, f"history too short ({n} < {min_history})"))
            hist.append((x, uu))
            continue
        xs = [h[0] for h in hist]
        m, s = statistics.fmean(xs), statistics.stdev(xs)
        u_m2 = max(sum(h[1] ** 2 for h in hist) / n**2, s**2 / n)
        u_c = math.sqrt(max(uu**2, s**2) + u_m2)
        flagged = abs(x - m) > k * u_c
        out.append(DriftCheck(x, uu, n, m, u_c, x - m, flagged))
        if not flagged:
            hist.append((x, uu))
    return out


def _row(it: BatchItem) -> dict[str, Any]:
    return {"run_id": it.run_id, "start_time": it.start_time, "recording": str(it.path), "status": it.status,
            "method": it.method, "model": it.model, "error": it.error, "parameters": it.parameters,
            "structure": it.structure, "findings": it.findings}


def _key(row: dict[str, Any]) -> tuple[str, str]:
    """A row per run and method: a re-identified run replaces its row of that method only (a run
    identified before methods were listed, or that failed to read, has one row with method "")."""
    return row["run_id"], row.get("method") or ""


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.\-]", "_", name) or "unknown"


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def _checked(rows: list[dict[str, Any]], k: float, min_history: int) -> list[dict[str, Any]]:
    rows = sorted(rows, key=lambda r: (r["start_time"], r["run_id"], r.get("method") or ""))
    for r in rows:
        r["drift"] = {}
    for name, _unit in PARAMS:
        for method in sorted({r["method"] for r in rows if r["status"] == "ok"}):
            sel = [r for r in rows if r["status"] == "ok" and r["method"] == method]
            ser = [((r["parameters"].get(name) or {}).get("value"), (r["parameters"].get(name) or {}).get("std"))
                   for r in sel]
            for r, c in zip(sel, drift_checks(ser, k=k, min_history=min_history), strict=True):
                r["drift"][name] = asdict(c)
    return rows


def _csv(rows: list[dict[str, Any]]) -> str:
    import io

    head = ["run_id", "start_time", "status", "method", "model"]
    for name, unit in PARAMS:
        head += [f"{name}_{COLUMN_UNIT[unit]}", f"u_{name}_{COLUMN_UNIT[unit]}", f"{name}_drift"]
    head += ["recording", "error"]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(head)
    for r in rows:
        line = [r["run_id"], r["start_time"], r["status"], r["method"], r["model"]]
        for name, _unit in PARAMS:
            p, c = r["parameters"].get(name) or {}, r["drift"].get(name) or {}
            flag = "DRIFT" if c.get("flagged") else (c.get("note") or "")
            line += [p.get("value") if p.get("value") is not None else "", p.get("std") if p.get("std") is not None
                     else "", flag]
        w.writerow([*line, r["recording"], r["error"]])
    return buf.getvalue()


def _charts(rows: list[dict[str, Any]]) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Shewhart and EWMA charts (``station.trend.charts``, default λ, L; the first up to 10 values, never
    the newest, set the limits) per method and parameter over the rows identified, and their out-of-control points."""
    from station.trend import charts

    out: dict[str, Any] = {}
    late: list[dict[str, Any]] = []
    for method in sorted({r["method"] for r in rows if r["status"] == "ok"}):
        for name, _unit in PARAMS:
            sel = [r for r in rows if r["status"] == "ok" and r["method"] == method
                   and isinstance((r["parameters"].get(name) or {}).get("value"), (int, float))
                   and isinstance((r["parameters"].get(name) or {}).get("std"), (int, float))]
            if len(sel) < 3:
                continue
            x = [r["parameters"][name]["value"] for r in sel]
            u = [r["parameters"][name]["std"] for r in sel]
            ref = min(len(x) - 1, 10)  # the limits come from earlier values, never from the newest
            doc: dict[str, Any] = {"runs": [r["run_id"] for r in sel],
                   "shewhart": charts.shewhart(x, uncertainties=u, reference=ref).to_dict(),
                   "ewma": charts.ewma(x, uncertainties=u, reference=ref).to_dict()}
            out.setdefault(method, {})[name] = doc
            late += [{"method": method, "parameter": name, "chart": kind, "run_id": sel[i]["run_id"]}
                     for kind in ("shewhart", "ewma") for i in doc[kind]["out_of_control"]]
    return out, late


def write_summaries(items: Iterable[BatchItem], out_dir: Path, *, k: float = K_DEFAULT,
                    min_history: int = MIN_HISTORY,
                    check_runs: Iterable[dict[str, Any]] = ()) -> dict[str, dict[str, Any]]:
    """Merge the items into ``<out_dir>/<transducer>.json`` (rows keyed by run id and method: a
    re-identified run replaces its earlier row of that method; each method is its own drift
    series), recompute the drift checks over the whole history, and write the JSON and
    ``<transducer>.csv``.  ``check_runs``: the night's check-run findings (``batch.check.CheckRun``
    as dicts), appended to their transducer's ``check_runs`` (the newest last, at most
    ``MAX_CHECK_RUNS`` kept).  Returns transducer id -> the JSON document written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    by_tx: dict[str, list[BatchItem]] = {}
    for it in items:
        by_tx.setdefault(it.transducer_id or "unknown", []).append(it)
    checks: dict[str, list[dict[str, Any]]] = {}
    for c in check_runs:
        checks.setdefault(str(c["transducer_id"]), []).append(dict(c))
        by_tx.setdefault(str(c["transducer_id"]), [])
    written = {}
    for tx, its in sorted(by_tx.items()):
        jpath = out_dir / f"{_safe(tx)}.json"
        before = json.loads(jpath.read_text(encoding="utf-8")) if jpath.exists() else {}
        old = before.get("runs", [])
        rows = {_key(r): {k_: v for k_, v in r.items() if k_ != "drift"} for r in old}
        rows.update({_key(r): r for r in map(_row, its)})
        checked = _checked(list(rows.values()), k, min_history)
        flagged = [{"run_id": r["run_id"], "start_time": r["start_time"], "method": r["method"], "parameter": name,
                    **{key: r["drift"][name][key] for key in ("value", "history_mean", "deviation", "u_c")}}
                   for r in checked for name, _u in PARAMS if (r["drift"].get(name) or {}).get("flagged")]
        doc = {"transducer_id": tx, "updated": datetime.now(UTC).isoformat(timespec="seconds"),
               "rule": {"k": k, "min_history": min_history,
                        "text": "|x - m| > k u_c, u_c^2 = max(u^2, s^2) + max(sum u_i^2 / n^2, s^2 / n); "
                                "history = earlier unflagged runs of the same method"},
               "units": dict(PARAMS), "flagged": flagged, "runs": checked}
        found = [*before.get("check_runs", []), *checks.get(tx, [])]
        if found:
            doc["check_runs"] = found[-MAX_CHECK_RUNS:]
        doc["charts"], doc["out_of_control"] = _charts(checked)
        _atomic_write(jpath, json.dumps(doc, indent=1))
        _atomic_write(out_dir / f"{_safe(tx)}.csv", _csv(checked))
        written[tx] = doc
    return written
