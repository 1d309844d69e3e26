"""False-alarm rate of ``model_misfit`` through the real daemon on an ideal simulated rig; prints JSON.

A real ``station serve --sim`` process (the simulated rig's Modbus image and DAQ bridge through the
real drivers, 20 kHz, recording to HDF5, identification in the worker) runs ``--runs`` short
five-step runs of config/sim-5kN.yaml (effects off; the frequencies and radii of the configured
plan, settle 0.2 s, record 0.5 s, 100 Hz/s ramps; only the expert estimator, ``fd`` with model
``auto``) one after the other (each starts when the previous one leaves the rig; the worker
identifies meanwhile), while ``--busy`` processes spin in a busy loop so that both cores
are loaded.  Each run of the daemon's simulated rig draws its own noise (the seed advances per run).

Printed: ``runs`` (completed), ``alarms`` (runs whose result carries ``model_misfit``), ``rate``,
``stated_rate`` (the nominal false-alarm rate of the test: the chi^2 tail beyond its threshold,
``station.ident.response.frf.misfit_false_alarm_rate``), ``interval_95`` (Clopper-Pearson interval of
the rate), ``within_stated`` (the stated rate inside that interval), the chi^2/dof values (their mean
against 1 and a KS p-value against chi^2(dof)/dof), lost samples, stall lines in the daemon's log,
``load_average_1min`` and the wall time.

Usage: python bench/false_alarm.py [--runs 50] [--busy 2]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import yaml
from scipy.stats import beta, kstest
from scipy.stats import chi2 as chi2_dist

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from station.ident.response.frf import misfit_false_alarm_rate  # noqa: E402

TOKEN = "bench-token-0123456789"


def _config(data_dir: Path) -> dict[str, Any]:
    d = yaml.safe_load((ROOT / "config" / "sim-5kN.yaml").read_text())
    d["station"]["recordings_dir"] = str(data_dir)
    d["rig"]["acceleration_hz_per_s"] = 100.0
    d["plan"].update({"settle_s": 0.2, "record_s": 0.5})
    d["simulation"]["pre_roll_s"] = 0.2
    d["identification"]["methods"] = [{"method": "fd", "model": "auto"}]
    return d


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Two-sided Clopper-Pearson interval of a binomial rate k / n."""
    a = (1 - level) / 2
    lo = 0.0 if k == 0 else float(beta.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a, k + 1, n - k))
    return lo, hi


def _wait_health(c: httpx.Client, proc: subprocess.Popen[bytes], log: Path) -> None:
    deadline = time.monotonic() + 240
    while True:
        with contextlib.suppress(httpx.TransportError):
            if c.get("/health").status_code == 200:
                return
        if time.monotonic() > deadline or proc.poll() is not None:
            raise RuntimeError("daemon did not start: " + log.read_text()[-3000:])
        time.sleep(0.2)


def _submit(c: httpx.Client, steps: list[dict[str, float]]) -> str:
    """Start a run and wait until it leaves the rig (its identification goes on in the worker)."""
    deadline = time.monotonic() + 300
    while (r := c.post("/runs", json={"transducer_id": "TX5K-0001", "top_mass_kg": 25.717,
                                      "steps": steps})).status_code == 409 and time.monotonic() < deadline:
        time.sleep(0.5)  # the previous run still holds the rig (ramping down, closing its recording)
    if r.status_code != 202:
        raise RuntimeError(f"POST /runs answered {r.status_code}: {r.text[:500]}")
    run_id = str(r.json()["id"])
    while c.get(f"/runs/{run_id}").json()["state"] in ("queued", "running"):
        time.sleep(0.25)
    return run_id


def _outcome(c: httpx.Client, run_id: str) -> dict[str, Any]:
    while (st := c.get(f"/runs/{run_id}").json())["state"] in ("queued", "running", "identifying"):
        time.sleep(0.5)
    row: dict[str, Any] = {"id": run_id, "state": st["state"], "lost_samples": st.get("lost_samples")}
    if st["state"] != "completed":
        row["reason"] = st.get("reason")
        return row
    res = c.get(f"/runs/{run_id}/results").json()
    checks = res.get("checks") or (res.get("methods") or [{}])[0].get("checks") or []
    names = [ch["name"] for ch in checks]
    row.update({"misfit": "model_misfit" in names, "checks": names,
                "chi2_per_dof": (res.get("fit") or {}).get("chi2_per_dof")})
    return row


def _inprocess(d: dict[str, Any], tmp: Path, runs: int) -> list[dict[str, Any]]:
    """The same runs through the simulated rig in-process on a virtual clock (the real drivers, the
    run procedure, the DAQ emulator, no HTTP and no real-time watchdog), one seed per run."""
    import asyncio

    from drivers.sim.clock import VirtualClock
    from station.config import parse_config
    from station.run.calibrate import run_and_identify
    from station.run.request import RunRequest, StepSpec

    rows = []
    for i in range(runs):
        d["simulation"]["seed"] = 3000 + i
        cfg = parse_config(d)
        req = RunRequest(transducer_id=cfg.transducer.id, top_mass_kg=cfg.rig.top_mass_kg,
                         steps=[StepSpec(**s.model_dump(exclude_none=True)) for s in cfg.plan.steps],
                         methods=[{"method": "fd", "model": "auto"}])  # type: ignore[list-item]
        res = asyncio.run(run_and_identify(cfg, req, tmp / f"run{i}", sim=True, sim_clock=VirtualClock()))
        r = res.identification
        row: dict[str, Any] = {"id": i, "state": "completed" if r is not None else "failed"}
        if r is None:
            row["reason"] = res.outcome.reason
        else:
            names = [c.name for c in r.checks]
            row.update({"misfit": "model_misfit" in names, "checks": names,
                        "chi2_per_dof": float(r.fit.chi2_per_dof)})
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--busy", type=int, default=2, help="busy-loop processes loading the cores")
    ap.add_argument("--inprocess", action="store_true",
                    help="the simulated rig in-process on a virtual clock instead of the daemon")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-false-alarm-"))
    d = _config(tmp / "recordings")
    steps = [{"crank_frequency_hz": s["crank_frequency_hz"], "crank_radius_m": s["crank_radius_m"]}
             for s in d["plan"]["steps"]]
    cfg = tmp / "station.yaml"
    cfg.write_text(yaml.safe_dump(d))
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy)]
    if args.inprocess:
        t0 = time.monotonic()
        try:
            ran = _inprocess(d, tmp, args.runs)
        finally:
            for p in busy:
                p.kill()
                p.wait()
            shutil.rmtree(tmp, ignore_errors=True)
        _report(ran, args, 0, "in-process simulated rig (virtual clock)", t0)
        return
    port = _free_port()
    log = tmp / "daemon.log"
    logf = log.open("wb")
    proc = subprocess.Popen([sys.executable, "-m", "station.cli", "serve", "--sim", "--config", str(cfg),
                             "--port", str(port)], stdout=logf, stderr=subprocess.STDOUT,
                            env={**os.environ, "STATION_TOKEN": TOKEN}, cwd=tmp)
    t0 = time.monotonic()
    rows: list[dict[str, Any]] = []
    try:
        c = httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {TOKEN}"},
                         timeout=60)
        _wait_health(c, proc, log)
        ids = []
        for i in range(args.runs):
            ids.append(_submit(c, steps))
            print(f"run {i + 1}/{args.runs} off the rig", file=sys.stderr, flush=True)
        for run_id in ids:
            rows.append(_outcome(c, run_id))
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    finally:
        for p in busy:
            p.kill()
            p.wait()
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
        logf.close()
        stalls = sum("stalled" in line for line in log.read_text(errors="replace").splitlines())
        shutil.rmtree(tmp, ignore_errors=True)
    _report(rows, args, stalls, "daemon (station serve --sim)", t0)


def _report(rows: list[dict[str, Any]], args: argparse.Namespace, stalls: int, path: str, t0: float) -> None:
    done = [r for r in rows if r["state"] == "completed"]
    n, k = len(done), sum(bool(r["misfit"]) for r in done)
    x = np.array([r["chi2_per_dof"] for r in done if r["chi2_per_dof"] is not None], float)
    dof = 7  # five steps: 10 real numbers, 3 parameters of Eq. 9
    stated = misfit_false_alarm_rate(dof)
    lo, hi = clopper_pearson(k, n) if n else (float("nan"), float("nan"))
    print(json.dumps({
        "path": path, "runs": n, "alarms": k, "rate": k / n if n else None, "stated_rate": stated,
        "interval_95": [lo, hi], "within_stated": bool(lo <= stated <= hi),
        "not_completed": [{"state": r["state"], "reason": r.get("reason")} for r in rows if r["state"] != "completed"],
        "dof": dof, "chi2_per_dof_mean": float(x.mean()) if x.size else None,
        "chi2_per_dof_max": float(x.max()) if x.size else None,
        "chi2_per_dof_mean_expected": [1.0, float(np.sqrt(2 / dof / max(x.size, 1)))],
        "ks_pvalue_chi2": float(kstest(x * dof, chi2_dist(dof).cdf).pvalue) if x.size > 2 else None,
        "other_checks": sorted({name for r in done for name in r["checks"]} - {"model_misfit"}),
        "lost_samples": sum(int(r.get("lost_samples") or 0) for r in rows), "stall_lines_in_log": stalls,
        "busy_processes": args.busy, "load_average_1min": os.getloadavg()[0],
        "wall_s": round(time.monotonic() - t0, 1)}, indent=2))


if __name__ == "__main__":
    main()
