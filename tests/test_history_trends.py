"""A transducer's history as the lab reads it, on a real SQLite store and real result files: control
charts of S, k_f, b_f and f_0, the as-found comparisons against the previous as-left value (an
adjustment recorded after a run), the drift risk and the interval recommendations; the policy and the
adjustments are audited; the CLI and the API show them."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from station.lab import audit, history, policy
from station.lab.store import Store
from station.lab.trends import DAY_S, natural_frequency
from tests.history_support import K0, S0, TX, U_REL, add_runs, add_transducer


def _doc(store: Store, rec: Path, **kw: float) -> dict:
    rows = history.runs_of(store, TX)
    return history.history(rows, rec, history.approvals(store, [r.id for r in rows]), policy.policy(store, TX),
                           policy.as_left_of(store, TX), **kw)


@pytest.fixture
def lab(tmp_path: Path):
    rec = tmp_path / "rec"
    rec.mkdir()
    store = Store(rec / "station.db")
    add_transducer(store)
    yield store, rec
    store.close()


def test_a_step_in_s_is_out_of_control_and_a_stable_k_f_is_not(lab) -> None:
    store, rec = lab
    add_runs(store, rec, 16, step_at=10)
    doc = _doc(store, rec)
    t = doc["trends"]["parameters"]
    assert set(t) == {"S", "k_f", "b_f", "f_0"}
    late = {p["run_id"] for p in doc["out_of_control"] if p["parameter"] == "S"}
    assert late and min(late) >= "run010"
    assert not [p for p in doc["out_of_control"] if p["parameter"] == "k_f"]
    # the chart's limits come from the first 10 values, never tighter than their stated u
    assert t["S"]["shewhart"]["reference"] == 10 and t["S"]["shewhart"]["s"] >= U_REL * S0 * 0.999
    # f_0 with the end mass of the register's record, its u from u(k_f) and u(m_e)
    f0, u = natural_frequency(K0, 3e-3 * K0, 0.12, 0.006)  # type: ignore[misc]
    assert t["f_0"]["points"][0]["value"] == pytest.approx(f0, rel=1e-2)
    assert u == pytest.approx(f0 * 0.5 * math.hypot(3e-3, 0.05))
    # without a policy's tolerance, no interval is made up
    assert "note" in t["S"]["intervals"]


def test_as_found_against_the_recorded_as_left_value_and_the_intervals(lab) -> None:
    store, rec = lab
    ids = add_runs(store, rec, 12, drift_per_day=1e-3 / 30, days=30.0)  # 0.1 % a month
    policy.put_policy(store, policy.Policy(TX, {"S": 0.005}, 365.0), "admin")
    # the user set S = 1.001·S0 in the instrument after run 5: run 6's as-found is judged against it
    policy.record_as_left(store, policy.AsLeft(ids[5], TX, "S", 1.001 * S0, "V/N", "gain set", 1.8e9, "anton"))
    doc = _doc(store, rec)
    s = doc["trends"]["parameters"]["S"]
    f6 = next(f for f in s["as_found"] if f["run_id"] == ids[6])
    assert f6["as_left_source"] == "adjusted" and f6["as_left"] == pytest.approx(1.001 * S0)
    assert f6["difference"] == pytest.approx(f6["as_found"] - 1.001 * S0)
    assert f6["tolerance"] == pytest.approx(0.005 * 1.001 * S0) and f6["in_tolerance"] is True
    risk = s["drift_risk"]
    # the fitted drift covers the simulated 0.1 %/month within 3 u
    assert abs(risk["slope_per_day"] - S0 * 1e-3 / 30) < 3 * risk["u_slope_per_day"]
    assert 0 <= risk["probability_out_of_tolerance"] <= 1
    assert s["intervals"]["variables"]["interval_days"] > 0
    assert "note" in s["intervals"]["a3"]  # no calibration 365 days after the previous one
    actions = [e.action for e in audit.entries(store, limit=50)]
    assert policy.POLICY_CHANGED in actions and policy.AS_LEFT_RECORDED in actions


def test_bad_policy_and_adjustments_are_refused(lab) -> None:
    store, rec = lab
    ids = add_runs(store, rec, 2)
    with pytest.raises(policy.PolicyError, match="relative"):
        policy.put_policy(store, policy.Policy(TX, {"S": 5.0}), "admin")
    with pytest.raises(policy.PolicyError, match="no tolerance can be set"):
        policy.put_policy(store, policy.Policy(TX, {"capacity": 0.1}), "admin")
    with pytest.raises(policy.PolicyError, match="not a run of"):
        policy.record_as_left(store, policy.AsLeft(ids[0], "OTHER", "S", 1.0, "V/N", "", 0.0, "anton"))
    with pytest.raises(policy.PolicyError, match="finite"):
        policy.record_as_left(store, policy.AsLeft(ids[0], TX, "S", math.nan, "V/N", "", 0.0, "anton"))


def test_station_history_prints_the_charts_and_sets_the_policy(tmp_path: Path, capsys) -> None:
    from station.cli import main
    from tests.station_support import daemon_config

    rec = tmp_path / "rec"
    rec.mkdir()
    cfg = tmp_path / "station.yaml"
    import yaml

    cfg.write_text(yaml.safe_dump(daemon_config(rec)))
    store = Store(rec / "station.db")
    add_transducer(store)
    ids = add_runs(store, rec, 14, step_at=10)
    store.close()
    assert main(["history", TX, "--config", str(cfg), "--tolerance", "S=0.005", "--interval-days", "30",
                 "--check-standard", "yes"]) == 0
    out = capsys.readouterr().out
    assert "check transducer: yes" in out and "S (V/N): 14 calibrations" in out
    assert "ewma:" in out and "run010" in out
    assert main(["history", TX, "--config", str(cfg), "--as-left", ids[-1], "S=0.002", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["trends"]["policy"]["check_standard"] is True
    assert doc["trends"]["parameters"]["S"]["intervals"]["a3"]["n"] == 13
    assert main(["history", TX, "--config", str(cfg), "--tolerance", "S=abc"]) == 2


@pytest.mark.slow
def test_the_api_sets_the_policy_records_an_adjustment_and_serves_the_trends(tmp_path: Path) -> None:
    import asyncio

    from tests.station_support import CAPPED_SPEEDUP, IDLE_SPEEDUP, app_in_process, login

    rec = tmp_path / "rec"
    rec.mkdir()

    async def go() -> None:
        async with app_in_process(rec, max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (manager, admin):
            def seed(s: Store) -> list[str]:
                add_transducer(s)
                return add_runs(s, rec, 16, step_at=10)
            ids = await manager.db.call(seed)
            r = await admin.put(f"/register/transducers/{TX}/policy",
                                json={"tolerances": {"S": 0.005}, "interval_days": 30, "check_standard": True})
            assert r.status_code == 200, r.text
            assert (await admin.put(f"/register/transducers/{TX}/policy",
                                    json={"tolerances": {"S": 2.0}})).status_code == 409
            assert (await admin.put(f"/register/transducers/{TX}/policy",
                                    json={"interval_days": 0})).status_code == 422
            assert (await admin.put("/register/transducers/NOPE/policy", json={})).status_code == 404
            await admin.put("/users/anton", json={"role": "approver", "password": "anton-secret-pw"})
            await admin.put("/users/tina", json={"role": "technician", "password": "tina-secret-pw"})
            tina, anton = await login(admin._transport.app, "tina"), await login(admin._transport.app, "anton")
            body = {"parameter": "S", "value": 0.002, "unit": "V/N", "note": "gain set"}
            assert (await tina.post(f"/runs/{ids[-1]}/as-left", json=body)).status_code == 403
            r = await anton.post(f"/runs/{ids[-1]}/as-left", json=body)
            assert r.status_code == 200, r.text
            h = (await admin.get(f"/transducers/{TX}/history", params={"lam": 0.3})).json()
            assert h["trends"]["parameters"]["S"]["ewma"]["parameters"]["lambda"] == 0.3
            assert h["trends"]["policy"]["check_standard"] is True
            assert any(p["parameter"] == "S" for p in h["out_of_control"])
            assert (await admin.get(f"/transducers/{TX}/history", params={"lam": 2})).status_code == 422
            # the check transducer is out of control: a run made since its last good point is not approved
            r = await anton.post(f"/runs/{ids[-1]}/approve", json={"note": "ok"})
            assert r.status_code == 409 and "held for review" in r.text

    asyncio.run(go())


@pytest.mark.slow
def test_an_out_of_control_check_transducer_holds_the_certificates_since_its_last_good_point(lab) -> None:
    store, rec = lab
    ids = add_runs(store, rec, 14, step_at=13, step_u=8.0)
    assert history.check_hold(store, rec) is None  # not marked as the check transducer yet
    policy.put_policy(store, policy.Policy(TX, {}, None, True), "admin")
    hold = history.check_hold(store, rec)
    assert hold is not None and hold.run_id == ids[13] and hold.parameter == "S"
    assert hold.since == pytest.approx(1.7e9 + 12 * 30 * DAY_S)
    assert "held for review" in hold.reason
