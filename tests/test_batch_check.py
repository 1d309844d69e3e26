"""The nightly batch's check run: the register's check transducer calibrated on the rig through the
daemon's own run path, a night after another, on the simulated rig whose transducer ages as the test
sets it; its control chart goes out of control within the run length the theory predicts, the
certificates made since its last good check are held, a stable one raises no alarm, and a check run
that cannot be made is a named finding, never a silent skip."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import yaml

from drivers.clock import REAL_CLOCK
from drivers.rig.params import TransducerAgeing
from drivers.sim.clock import VirtualClock
from drivers.sim.rig import SimRig
from station.batch.check import check_body, check_runs, run_check, station_url
from station.config import parse_config, to_rig_physics
from station.lab import policy
from station.lab.store import Store
from station.trend.charts import first_alarm_probabilities
from tests.conftest import fast_dict
from tests.station_support import (
    CAPPED_SPEEDUP,
    IDLE_SPEEDUP,
    TOKEN,
    Seed,
    app_in_process,
    daemon_config,
    free_port,
    login,
    seed_runs,
)

TX = "TX5K-0001"
RATE = 5e-5  # S drifts by 0.005 % a day (0.15 % a month) ...
WEEK = 7.0  # ... checked once a week: about 1.2 stated u per check


def test_the_simulated_transducer_ages_by_the_rate_the_test_sets() -> None:
    d = fast_dict()
    d["simulation"]["effects"] = {"ageing": {"sensitivity_per_day": 1e-3 / 30, "k_f_per_day": -2e-5, "onset_day": 10}}
    physics = to_rig_physics(parse_config(d))
    assert physics.effects.active() == ["ageing"]
    s0, k0 = physics.transducer.sensitivity_V_per_N, physics.transducer.k_f
    clock = VirtualClock()
    rig = SimRig(physics=physics, wire=False, clock=clock)
    rig.load_physics(physics)
    assert rig.source.physics.transducer.sensitivity_V_per_N == s0  # before the onset: as built
    clock.advance(86_400.0 * 10)
    rig.let_days_pass(30.0)  # 40 days old: 30 days of drift
    rig.load_physics(physics)
    t = rig.source.physics.transducer
    assert t.sensitivity_V_per_N == pytest.approx(s0 * 1.001, rel=1e-12)
    assert t.k_f == pytest.approx(k0 * (1 - 30 * 2e-5), rel=1e-12)
    assert t.m_e == physics.transducer.m_e and rig.source.physics.effects == physics.effects
    with pytest.raises(ValueError, match="backwards"):
        rig.let_days_pass(-1.0)
    assert TransducerAgeing().factors(1e4) == (1.0, 1.0)
    d["simulation"]["effects"] = {"ageing": {"sensitivity_per_day": 0.5}}
    with pytest.raises(Exception, match="sensitivity_per_day"):
        parse_config(d)
    assert SimRig(physics=physics, wire=False, clock=REAL_CLOCK).age_days() < 1e-3


def test_the_check_plan_and_the_daemon_come_from_the_configuration() -> None:
    d = fast_dict()
    cfg = parse_config(d)
    body = check_body(cfg, TX)
    plan = [s.crank_frequency_hz for s in cfg.plan.steps]
    assert [s["crank_frequency_hz"] for s in body["steps"]] == [plan[0], plan[(len(plan) - 1) // 2], plan[-1]]
    assert body["top_mass_kg"] == cfg.rig.top_mass_kg and body["transducer_id"] == TX
    assert station_url(cfg) == f"http://127.0.0.1:{cfg.service.port}"
    d["batch"] = {"check_steps": [{"crank_frequency_hz": 12.0, "crank_radius_m": 0.002, "record_s": 1.0}],
                  "check_top_mass_kg": 10.0, "station_url": "http://rig-pc:8080/"}
    cfg = parse_config(d)
    assert check_body(cfg, TX) == {"transducer_id": TX, "top_mass_kg": 10.0, "steps": [
        {"crank_frequency_hz": 12.0, "crank_radius_m": 0.002, "record_s": 1.0}]}
    assert station_url(cfg) == "http://rig-pc:8080"
    d["batch"] = {"station_url": "ftp://x"}
    with pytest.raises(Exception, match="station_url"):
        parse_config(d)


def _station_files(tmp_path: Path, *, port: int, token: str | None) -> tuple[Path, Path]:
    rec = tmp_path / "rec"
    rec.mkdir(exist_ok=True)
    d = daemon_config(rec)
    d["service"]["port"] = port
    if token:
        d["service"]["token"] = token
    cfg = tmp_path / "station.yaml"
    cfg.write_text(yaml.safe_dump(d))
    return cfg, rec


def test_a_check_run_that_cannot_be_made_is_a_named_finding_and_the_batch_goes_on(tmp_path: Path, capsys,
                                                                                   monkeypatch) -> None:
    from station.cli import main

    monkeypatch.delenv("STATION_TOKEN", raising=False)
    cfg, rec = _station_files(tmp_path, port=free_port(), token=TOKEN)  # nothing listens there
    assert main(["batch", "--config", str(cfg), "--no-progress"]) == 0  # no database yet: nothing is marked
    assert "no station database" in capsys.readouterr().out
    store = Store(rec / "station.db")
    try:
        policy.put_policy(store, policy.Policy(TX, {}, None, True), "admin")
    finally:
        store.close()
    assert main(["batch", "--config", str(cfg), "--no-progress"]) == 1
    out = capsys.readouterr().out
    assert f"CHECK RUN NOT RUN {TX}: no station daemon reached at http://127.0.0.1:" in out
    assert "0 recordings in scope" in out  # the rest of the batch went on
    doc = json.loads((rec / "summary" / f"{TX}.json").read_text())
    assert [c["status"] for c in doc["check_runs"]] == ["not run"]
    assert main(["batch", "--config", str(cfg), "--no-progress", "--no-check"]) == 0  # asked not to: no finding
    cfg, _ = _station_files(tmp_path, port=free_port(), token=None)
    capsys.readouterr()
    assert main(["batch", "--config", str(cfg), "--no-progress", "--json"]) == 1
    printed = json.loads(capsys.readouterr().out)
    assert [c["status"] for c in printed["check_runs"]] == ["not run"]
    doc = json.loads((rec / "summary" / f"{TX}.json").read_text())
    assert [c["status"] for c in doc["check_runs"]] == ["not run", "not run"]
    assert "no API token" in doc["check_runs"][-1]["detail"]
    assert main(["batch", "--config", str(cfg), "--station", "rig-pc:8080"]) == 2


def _S_points(h: dict[str, Any]) -> dict[str, Any]:
    return h["trends"]["parameters"]["S"]


@pytest.mark.slow
@pytest.mark.waits  # runs on the app in-process at a capped clock: about 15 s
def test_nightly_check_runs_chart_a_drifting_check_transducer_and_hold_the_certificates(tmp_path: Path) -> None:
    """Eight earlier calibrations of the check transducer (simulated from the same physics, not by
    the rig) give the charts their reference; then each night the batch's check run is made on the
    rig: two weeks stable, then S drifts by RATE a day.  Only S goes out of control, within the run
    length the EWMA's Markov chain predicts for that drift in units of the chart's s; the run made
    since the last good check is held for review, an earlier one is not; the batch command's own
    check run lands in the history, the summary's charts and its HOLD line."""
    rec = tmp_path / "rec"
    rec.mkdir()
    cfg = daemon_config(rec)
    cfg["identification"] = {"methods": [{"method": "fd", "model": "auto"}]}
    cfg["simulation"]["effects"] = {"ageing": {"sensitivity_per_day": RATE, "onset_day": 2 * WEEK}}
    cfg["batch"] = {"check_steps": [{"crank_frequency_hz": 10.0, "crank_radius_m": 0.001},
                                    {"crank_frequency_hz": 20.0, "crank_radius_m": 0.001}]}
    earlier = seed_runs(cfg, [Seed(seed=i) for i in range(8)])
    config = parse_config(cfg)

    async def go() -> None:
        async with app_in_process(rec, config=cfg, workers=1, max_speedup=CAPPED_SPEEDUP,
                                  idle_speedup=IDLE_SPEEDUP) as (m, admin):
            app = admin._transport.app  # type: ignore[attr-defined]
            transport = httpx.ASGITransport(app=app)

            async def night() -> dict[str, Any]:
                m.link.rig.sim.let_days_pass(WEEK)
                [found] = await check_runs(config, [TX], TOKEN, transport=transport, poll_s=0.05)
                assert found.status == "completed", found
                return found.to_dict()

            r = await admin.put(f"/register/transducers/{TX}/policy", json={"check_standard": True})
            assert r.status_code == 200, r.text
            # a (long) check run on the rig: a second one finds the rig busy and says so, then the
            # first is aborted by an operator and the batch reports it failed, with the reason
            long = check_body(config, TX)
            for step in long["steps"]:
                step["record_s"] = 120.0  # far longer than the abort takes to arrive
            first = asyncio.create_task(run_check(admin, long, poll_s=0.05))
            while not (busy := (await admin.get("/runs", params={"limit": 1})).json()["runs"]) \
                    or busy[0]["state"] not in ("queued", "running"):
                await asyncio.sleep(0.01)
            [found] = await check_runs(config, [TX], TOKEN, transport=transport)
            assert found.status == "not run" and "rig is busy" in found.detail and busy[0]["id"] in found.detail
            await admin.post(f"/runs/{busy[0]['id']}/abort")
            found = await first
            assert (found.status, found.state, found.run_id) == ("failed", "aborted", busy[0]["id"]), found
            assert "aborted by admin" in found.detail  # the reason the run ended with

            await admin.put("/users/anton", json={"role": "approver", "password": "anton-secret-pw"})
            anton = await login(app, "anton")
            nights, detected, customer = [], None, None
            for i in range(2 + 6):
                nights.append(await night())
                h = (await admin.get(f"/transducers/{TX}/history")).json()
                late = {(o["parameter"], o["run_id"]) for o in h["out_of_control"]}
                if ("S", nights[-1]["run_id"]) in late:
                    detected = i - 1  # the drift's nights, 0 the first week of it
                    break
                # a customer's calibration after each good check (the register holds what follows it)
                customer = await _customer_run(m)
            assert detected is not None, "the drift was never flagged"
            assert detected >= 0, "a stable week was flagged"
            assert {p for p, _ in late} == {"S"}, late  # k_f, b_f and f_0 did not drift: no alarm
            s = _S_points(h)["ewma"]["s"]
            shift = _S_points(h)["ewma"]["centre"] * RATE * WEEK / s  # the drift per check in units of s
            p = np.cumsum(first_alarm_probabilities([shift * (j + 1) for j in range(10)], kind="ewma"))
            bound = int(np.argmax(p >= 0.999))
            assert detected <= bound, (detected, bound, shift)
            assert h["hold"]["transducer_id"] == TX and h["hold"]["run_id"] == nights[-1]["run_id"]  # the page says so
            assert h["hold"]["since"] == pytest.approx(max(x["created"] for x in h["runs"]
                                                           if x["run_id"] == nights[-2]["run_id"]))
            # the run made since the last good check is held, with the reason; an earlier one is not
            r = await anton.post(f"/runs/{customer}/approve", json={"note": "ok"})
            assert r.status_code == 409 and "held for review" in r.text and TX in r.text
            r = await anton.post(f"/runs/{earlier[0]}/approve", json={"note": "ok"})
            assert r.status_code == 200, r.text
            await _the_batch_command_makes_the_next_check_run(tmp_path, cfg, app, m)

    asyncio.run(go())


async def _customer_run(m: Any) -> str:
    """A completed calibration of another transducer, started now by a technician (its row only:
    the hold is decided by when it was made, before anything of its recording is read)."""
    from station.lab.store import RunRow

    rid = f"customer-{time.time_ns()}"
    row = RunRow(id=rid, state="completed", transducer_id="CUSTOMER-1", top_mass_kg=25.0, request_json="{}",
                 plan_json="{}", created=time.time(), n_steps=2, operator="tina")
    await m.db.call(lambda s: s.insert_run(row))
    return rid


async def _the_batch_command_makes_the_next_check_run(tmp_path: Path, cfg: dict[str, Any], app: Any, m: Any) -> None:
    """``station batch`` against the daemon on a socket: its check run is made, re-identified with the
    others and charted in the summary, and the hold is printed."""
    from station.cli import main
    from station.commands.connections import ConnectionBounds
    from tests.station_support import served_on_a_socket

    async with served_on_a_socket(app, ConnectionBounds(max_connections=64, header_timeout_s=10.0)) as port:
        d = json.loads(json.dumps(cfg, default=str))
        d["service"].update(port=port, token=TOKEN)
        path = tmp_path / "station.yaml"
        path.write_text(yaml.safe_dump(d))
        m.link.rig.sim.let_days_pass(WEEK)
        import contextlib
        import io

        buf = io.StringIO()

        def batch() -> int:
            with contextlib.redirect_stdout(buf):
                return main(["batch", "--config", str(path), "--no-progress", "--workers", "1"])
        assert await asyncio.to_thread(batch) == 0, buf.getvalue()
    out = buf.getvalue()
    assert f"CHECK RUN {TX}: run " in out and "HOLD: the check transducer" in out, out
    summary = json.loads((Path(cfg["station"]["recordings_dir"]) / "summary" / f"{TX}.json").read_text())
    [found] = summary["check_runs"]
    assert found["status"] == "completed" and "held for review" in found["hold"]
    assert found["run_id"] in summary["charts"]["fd"]["S"]["runs"]
    assert any(o["run_id"] == found["run_id"] and o["parameter"] == "S" for o in summary["out_of_control"])
