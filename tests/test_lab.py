"""The lab around the station, in process: the register chooses the transducer and the reference
standards of a run, named users with roles (a technician cannot approve or administer; a wrong
password, a wrong token and an expired session are refused with the reason), the audit trail lists
every state change of a scripted day and cannot be changed, and a tampered recording is refused."""

from __future__ import annotations

import asyncio
import sqlite3
from pathlib import Path
from typing import Any

import pytest

from station.lab import audit, users
from station.lab.store import Store
from tests.station_support import (
    CAPPED_SPEEDUP,
    IDLE_SPEEDUP,
    ON_RIG_DONE,
    PASSWORDS,
    app_in_process,
    asgi_client,
    daemon_config,
    login,
    run_body,
    wait_state,
)

STANDARDS = [
    {"id": "LVDT-7", "kind": "displacement_sensor", "certificate_id": "DKD-K-123/2026", "issuer": "DKD lab 12",
     "due_date": "2099-06-30", "uncertainty": 2e-7, "uncertainty_unit": "m"},
    {"id": "MASS-SET-2", "kind": "masses", "certificate_id": "M-88", "issuer": "PTB", "due_date": "2099-01-31",
     "uncertainty": 5e-5, "uncertainty_unit": "kg"},
]
OTHER = {"type": "HBM U9C", "serial": "SN-42", "capacity_N": 5000.0, "sensitivity_V_per_N": 2e-6,
         "end_mass_kg": 0.1, "end_mass_std_kg": 0.002, "owner": "ACME Weighing"}


def lab_config(rec: Path, **lab: Any) -> dict[str, Any]:
    d = daemon_config(rec)
    d["lab"] = {"standards": STANDARDS, **lab}
    return d


async def identified(manager: Any, rid: str) -> None:
    """Record the run's identification as the worker does (these tests run no worker process)."""
    manager.db.update_run(rid, {"state": "completed", "result_name": "x"})
    assert await asyncio.to_thread(manager.db.flush, 5.0)


@pytest.mark.slow
def test_a_scripted_day_is_in_the_audit_trail(tmp_path: Path) -> None:
    """Admin adds users and a transducer; the technician mounts it, runs it, stops and acknowledges;
    the approver approves; every change is in the trail with who did it, and the roles hold."""
    rec = tmp_path / "rec"

    async def day() -> None:
        async with app_in_process(rec, config=lab_config(rec), max_speedup=CAPPED_SPEEDUP,
                                  idle_speedup=IDLE_SPEEDUP) as (manager, admin):
            app = admin._transport.app  # type: ignore[attr-defined]
            for name, role in (("tina", "technician"), ("anton", "approver")):
                r = await admin.put(f"/users/{name}", json={"role": role, "password": PASSWORDS[name]})
                assert r.status_code == 200, r.text
            assert (await admin.put("/register/transducers/TX5K-0002", json=OTHER)).status_code == 200
            reg = (await admin.get("/register")).json()
            assert reg["mounted"] == "TX5K-0001" and {s["id"] for s in reg["standards"]} == {"LVDT-7", "MASS-SET-2"}

            tina, anton = await login(app, "tina"), await login(app, "anton")
            # a technician can neither administer nor approve
            r = await tina.put("/register/transducers/X1", json=OTHER)
            assert r.status_code == 403 and "admin" in r.json()["detail"]
            assert (await tina.put("/users/tina", json={"role": "admin"})).status_code == 403
            assert (await tina.post("/register/mount", json={"transducer_id": "TX5K-0002"})).status_code == 200
            body = run_body()
            body["transducer_id"] = "TX5K-0002"
            r = await tina.post("/runs", json=body)
            assert r.status_code == 202, r.text
            rid = r.json()["id"]
            st = await wait_state(tina, rid, ON_RIG_DONE)
            assert st["state"] == "identifying" and st["transducer_id"] == "TX5K-0002"
            row = await manager.runs.get(rid)
            assert row.operator == "tina" and row.recording_sha256 and '"LVDT-7"' in row.standards_json
            assert '"HBM U9C"' in row.transducer_json
            # the recording's start document names the transducer record, the standards and the operator
            from station.recording.reader import read_recording
            docs = read_recording(manager.artifacts.recording_path(row)).documents
            start = next(d for d in docs if d.get("kind") == "start")
            prov = (start.get("body") or start)["plan"]["provenance"]
            assert prov["operator"] == "tina" and prov["transducer"]["serial"] == "SN-42"
            assert [s["certificate_id"] for s in prov["standards"]] == ["DKD-K-123/2026", "M-88"]  # by kind
            await identified(manager, rid)

            assert (await tina.post(f"/runs/{rid}/approve", json={})).status_code == 403
            stop = await asgi_client(app, token=False).post("/stop")
            assert stop.status_code == 200
            assert (await tina.post("/stop/acknowledge", json={"note": "rig checked"})).status_code == 200
            r = await anton.post(f"/runs/{rid}/approve", json={"note": "ok"})
            assert r.status_code == 200, r.text
            assert r.json()["approved_by"] == "anton" and r.json()["sha256"] == row.recording_sha256

            hist = (await tina.get("/transducers/TX5K-0002/history")).json()
            assert [(r["run_id"], r["operator"], [a["by"] for a in r["approvals"]]) for r in hist["runs"]] == \
                [(rid, "tina", ["anton"])]
            assert hist["transducer"]["owner"] == "ACME Weighing" and hist["certificates"] == []
            await asyncio.to_thread(manager.db.flush, 5.0)
            trail = (await admin.get("/audit?limit=1000")).json()["entries"]
            seen = [(e["who"], e["action"], e["target"]) for e in reversed(trail)]
            expected = [("admin", audit.USER_CHANGED, "user:tina"), ("admin", audit.USER_CHANGED, "user:anton"),
                        ("admin", audit.REGISTER_CHANGED, "TX5K-0002"), ("tina", audit.LOGIN, "user:tina"),
                        ("anton", audit.LOGIN, "user:anton"), ("tina", audit.TRANSDUCER_MOUNTED, "TX5K-0002"),
                        ("tina", audit.RUN_STARTED, rid), ("system", audit.RUN_ENDED, rid),
                        ("anonymous", audit.ESTOP_RAISED, "station"), ("tina", audit.ESTOP_ACKNOWLEDGED, "station"),
                        ("anton", audit.CERTIFICATE_APPROVED, rid)]
            it = iter(seen)
            missing = [e for e in expected if e not in it]  # in this order, others may come between
            assert not missing, (missing, seen)
            # the start-up seeding is there too, by the system
            assert ("system", audit.REGISTER_CHANGED, "LVDT-7") in seen
            for c in (tina, anton):
                await c.aclose()
    asyncio.run(day())


@pytest.mark.slow
def test_credentials_are_refused_with_the_reason(tmp_path: Path) -> None:
    rec = tmp_path / "rec"

    async def go() -> None:
        async with app_in_process(rec, config=lab_config(rec, session_minutes=5),
                                  max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (manager, admin):
            app = admin._transport.app  # type: ignore[attr-defined]
            await admin.put("/users/tina", json={"role": "technician", "password": PASSWORDS["tina"]})
            anon = asgi_client(app, token=False)
            r = await anon.post("/login", json={"name": "tina", "password": "wrong-password"})
            assert r.status_code == 401 and "wrong user name or password" in r.json()["detail"]
            r = await anon.post("/runs", json=run_body(), headers={"Authorization": "Bearer not-the-token"})
            assert r.status_code == 401 and "token is not valid" in r.json()["detail"]
            tina = await login(app, "tina")
            assert (await tina.get("/me")).json()["user"]["role"] == "technician"
            # the session's end passes: refused with the time it expired
            with manager.store.transaction() as db:
                db.execute("UPDATE sessions SET expires = 1000")
            r = await tina.get("/me")
            assert r.status_code == 401 and "session expired at 1970-01-01 00:16 UTC" in r.json()["detail"]
            r = await tina.post("/runs", json=run_body())
            assert r.status_code == 401 and "expired" in r.json()["detail"]
            # the password is stored as a scrypt hash, never in clear
            pw = manager.store.query("SELECT password FROM users WHERE name = 'tina'")[0]["password"]
            secret = PASSWORDS["tina"]
            assert pw.startswith("scrypt$") and secret not in pw and users.check_password(secret, pw)
            # a token issued to a user acts for that user
            tok = (await admin.post("/users/tina/tokens", json={"label": "ci"})).json()["token"]
            me = (await anon.get("/me", headers={"Authorization": f"Bearer {tok}"})).json()
            assert me["user"]["name"] == "tina" and me["via"] == "token"
            await anon.aclose()
            await tina.aclose()
    asyncio.run(go())


@pytest.mark.slow
def test_the_users_list_names_each_last_change_and_the_rules_are_published(tmp_path: Path) -> None:
    """GET /users: each user's last change (when, by whom) from the trail; GET /users/policy: the roles
    with their permissions and the password rule the API applies; both for administrators only."""
    rec = tmp_path / "rec"

    async def go() -> None:
        async with app_in_process(rec, config=lab_config(rec), max_speedup=CAPPED_SPEEDUP,
                                  idle_speedup=IDLE_SPEEDUP) as (manager, admin):
            app = admin._transport.app  # type: ignore[attr-defined]
            pol = (await admin.get("/users/policy")).json()
            assert {r["name"]: r["permissions"] for r in pol["roles"]} == \
                {str(r): sorted(str(p) for p in users.GRANTS[r]) for r in users.Role}
            short = "x" * (pol["min_password"] - 1)
            assert (await admin.put("/users/tina", json={"role": "technician", "password": short})).status_code == 422
            await admin.put("/users/tina", json={"role": "technician", "password": PASSWORDS["tina"]})
            await admin.put("/users/ada", json={"role": "admin", "password": PASSWORDS["ada"]})
            ada = await login(app, "ada")
            assert (await ada.put("/users/tina", json={"role": "approver"})).status_code == 200
            rows = {u["name"]: u for u in (await ada.get("/users")).json()}
            last = audit.entries(manager.store, target="user:tina", action=audit.USER_CHANGED, limit=1)[0]
            assert (rows["tina"]["role"], rows["tina"]["changed"], rows["tina"]["changed_by"]) == \
                ("approver", last.at, "ada")
            assert rows["ada"]["changed_by"] == "admin"  # the station token's administrator
            tina = await login(app, "tina")
            for path in ("/users", "/users/policy"):
                assert (await tina.get(path)).status_code == 403
            for c in (ada, tina):
                await c.aclose()
    asyncio.run(go())


@pytest.mark.parametrize("policy", ["refuse", "warn"])
@pytest.mark.slow
def test_a_standard_past_its_due_date_refuses_or_warns(tmp_path: Path, policy: str) -> None:
    rec = tmp_path / "rec"
    late = [{**STANDARDS[0], "due_date": "2020-03-31"}, STANDARDS[1]]

    async def go() -> None:
        d = lab_config(rec, overdue_standards=policy)
        d["lab"]["standards"] = late
        async with app_in_process(rec, config=d, max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (manager, c):
            r = await c.post("/runs", json=run_body())
            if policy == "refuse":
                assert r.status_code == 422
                msg = r.json()["errors"][0]["msg"]
                assert "LVDT-7" in msg and "2020-03-31" in msg and r.json()["errors"][0]["loc"] == ["body", "standards"]
                # naming only the standards that are in date lets it run
                ok = await c.post("/runs", json={**run_body(), "standards": ["MASS-SET-2"]})
                assert ok.status_code == 202, ok.text
                await wait_state(c, ok.json()["id"], ON_RIG_DONE)
            else:
                assert r.status_code == 202, r.text
                st = await wait_state(c, r.json()["id"], ON_RIG_DONE)
                row = await manager.runs.get(st["id"])
                assert "2020-03-31" in row.plan_json  # the warning travels with the run's record
            r = await c.post("/runs", json={**run_body(), "transducer_id": "NOPE-1"})
            assert r.status_code == 422 and "not in the register" in r.json()["errors"][0]["msg"]
    asyncio.run(go())


@pytest.mark.slow
def test_a_tampered_recording_is_refused_naming_the_file(tmp_path: Path) -> None:
    rec = tmp_path / "rec"

    async def go() -> None:
        async with app_in_process(rec, config=lab_config(rec), max_speedup=CAPPED_SPEEDUP,
                                  idle_speedup=IDLE_SPEEDUP) as (manager, c):
            rid = (await c.post("/runs", json=run_body())).json()["id"]
            await wait_state(c, rid, ON_RIG_DONE)
            assert (await c.get(f"/runs/{rid}/integrity")).status_code == 200
            path = manager.artifacts.recording_path(await manager.runs.get(rid))
            data = bytearray(path.read_bytes())
            data[len(data) // 2] ^= 0x01  # one bit of the raw data
            path.write_bytes(bytes(data))
            r = await c.get(f"/runs/{rid}/integrity")
            assert r.status_code == 409 and path.name in r.json()["detail"] and "changed" in r.json()["detail"]
            await identified(manager, rid)
            await c.put("/users/anton", json={"role": "approver", "password": PASSWORDS["anton"]})
            anton = await login(c._transport.app, "anton")  # type: ignore[attr-defined]
            r = await anton.post(f"/runs/{rid}/approve", json={})
            assert r.status_code == 409 and path.name in r.json()["detail"]
            await anton.aclose()
    asyncio.run(go())


def test_the_audit_trail_is_append_only(tmp_path: Path) -> None:
    store = Store(tmp_path / "s.db")
    with store.transaction() as db:
        audit.record(db, "tina", audit.RUN_STARTED, "r1")
    for stmt in ("UPDATE audit SET who = 'mallory'", "DELETE FROM audit"):
        with pytest.raises(sqlite3.IntegrityError, match="append-only"), store.transaction() as db:
            db.execute(stmt)
    assert [e.who for e in audit.entries(store)] == ["tina"]
    store.close()
    # and no code path writes anything but INSERT to it (but the one-time chaining of an older trail)
    src = "\n".join(p.read_text() for p in Path("station").rglob("*.py") if p != Path("station/lab/chain.py"))
    assert "UPDATE audit" not in src.replace("'UPDATE audit", "") and "DELETE FROM audit" not in src


def test_a_database_of_the_previous_release_is_upgraded_without_losing_runs(tmp_path: Path) -> None:
    """``tests/data/station-v2.db``: made by the previous release's store (schema 2: three runs, a
    job, an emergency stop).  The daemon opens it, keeps a copy as it was, and adds the lab."""
    import shutil

    rec = tmp_path / "rec"
    rec.mkdir()
    shutil.copy(Path(__file__).parent / "data" / "station-v2.db", rec / "station.db")

    async def go() -> None:
        async with app_in_process(rec, config=lab_config(rec), max_speedup=CAPPED_SPEEDUP,
                                  idle_speedup=IDLE_SPEEDUP) as (manager, c):
            runs = (await c.get("/runs")).json()["runs"]
            assert sorted(r["state"] for r in runs) == ["aborted", "completed", "interrupted"]
            assert manager.store.jobs()[0].run_id == "20260101T000000-TX5K-0001-000000"
            assert manager.store.last_estop().detail == "test stop"  # type: ignore[union-attr]
            up = (await c.get("/audit?action=database.upgraded")).json()["entries"]
            assert up and up[0]["details"]["from_schema"] == 2
            assert (await c.get("/register")).json()["mounted"] == "TX5K-0001"
    asyncio.run(go())
    backup = rec / "station.db.v2.bak"
    old = sqlite3.connect(backup)
    assert old.execute("PRAGMA user_version").fetchone()[0] == 2
    assert old.execute("SELECT count(*) FROM runs").fetchone()[0] == 3
    old.close()
    new = sqlite3.connect(rec / "station.db")
    assert new.execute("PRAGMA user_version").fetchone()[0] == 3
    new.close()


def test_the_command_line_manages_users_and_the_register(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    import json

    import yaml

    from station.cli import main

    cfg = tmp_path / "station.yaml"
    cfg.write_text(yaml.safe_dump(lab_config(tmp_path / "rec")))
    monkeypatch.setenv("STATION_PASSWORD", "tina-secret-pw")
    assert main(["users", "add", "tina", "--role", "technician", "--config", str(cfg)]) == 0
    assert main(["register", "standard", "DAQ-1", "--kind", "daq", "--certificate", "C-9", "--issuer", "PTB",
                 "--due-date", "2031-02-28", "--uncertainty", "1e-4", "--unit", "relative", "--config", str(cfg)]) == 0
    assert main(["register", "transducer", "TX-9", "--capacity-N", "2000", "--sensitivity-V-per-N", "1e-6",
                 "--config", str(cfg)]) == 0
    assert main(["register", "mount", "TX-9", "--config", str(cfg)]) == 0
    capsys.readouterr()
    assert main(["register", "list", "--json", "--config", str(cfg)]) == 0
    reg = json.loads(capsys.readouterr().out)
    assert reg["mounted"] == "TX-9" and {s["id"] for s in reg["standards"]} == {"LVDT-7", "MASS-SET-2", "DAQ-1"}
    # bad input: one line saying what is wrong, nothing written
    assert main(["register", "standard", "X", "--kind", "daq", "--certificate", "C", "--issuer", "I",
                 "--due-date", "31.12.2030", "--uncertainty", "1", "--unit", "m", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--due-date '31.12.2030': expected an ISO date" in err[0]
    store = Store(tmp_path / "rec" / "station.db")
    who = {e.who for e in audit.entries(store)}
    assert any(w.startswith("cli:") for w in who) and users.get_user(store, "tina") is not None
    store.close()
