"""The attacks on the lab's records, each made on a real daemon (``station serve --sim`` in a
subprocess, loopback only) as an insider with write access to the recordings folder and the
database file, a careless approver or someone on the loopback interface would make them: each case
is one attack and shows it detected (409 naming what changed, ``/integrity``, ``/health``, the log)
or refused.  One daemon serves every case; each case puts back what it changed, so that the next
one starts from a station that verifies.  The attacks on issued certificates (an edited form with
its record recomputed, a hand-made withdrawal marker, deleted files, the refused issues and their
entries, the customer's check) are made on the same app in process (``tests/test_records.py``): an
issue renders three forms, and what the real processes add (a certificate issued, read back as PDF
and DCC) ``tests/test_web_readme.py`` shows on its daemon.

The login timing (the same work for every kind of name) is measured by ``bench/login.py``; here the
refusals are shown to be alike (tests never assert wall-clock times)."""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import httpx
import pytest

from tests.recording_support import flip_bit
from tests.station_support import AUTH, PASSWORDS, ROLES, Daemon, Seed, daemon_config

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("attacks")]  # with --dist loadgroup: one worker, one daemon

OPERATOR = "tina"
START_S = 300.0  # the daemon's start on a loaded machine (2 cores shared by many)
TIMEOUT_S = 300.0  # a request that reads a recording and its results, on a loaded machine
# one TLS context for the tests' many clients (each httpx client would load the CA bundle again:
# some 40 ms of CPU; these speak plain HTTP on the loopback)
TLS = httpx.create_ssl_context()


@dataclass
class Lab:
    """The daemon, its seeded runs (``a``: files attacked; ``b``: issue refusals, the same run as
    ``a``, whose files each attack puts back) and a client logged in per user."""

    d: Daemon
    a: str
    b: str
    users: dict[str, httpx.Client]

    @property
    def db(self) -> Path:
        return self.d.data_dir / "station.db"

    @property
    def rec(self) -> Path:
        return self.d.data_dir

    def get(self, url: str, **kw: Any) -> httpx.Response:
        return self.d.c().get(url, **kw)

    def client(self, name: str | None = None) -> httpx.Client:
        """A new client (logged in as ``name`` when given) of the daemon."""
        c = httpx.Client(base_url=self.d.url, timeout=TIMEOUT_S, verify=TLS)
        if name is not None:
            r = c.post("/login", json={"name": name, "password": PASSWORDS[name]})
            assert r.status_code == 200, r.text
        return c

    def assert_clean(self) -> None:
        r = self.get("/integrity")
        assert r.status_code == 200, r.text
        assert self.get("/health").json()["audit_chain"]["ok"] is True


def _sql(path: Path, *stmts: str, args: tuple[Any, ...] = ()) -> None:
    db = sqlite3.connect(path, timeout=10)
    for s in stmts:
        db.execute(s, args if "?" in s else ())
    db.commit()
    db.close()


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Lab]:
    tmp = tmp_path_factory.mktemp("attacks")
    cfg = daemon_config(tmp / "recordings")
    # the product's password cost, not the tests' cheaper one: the login flood is a flood of real
    # scrypt checks (about 0.1 s of CPU each), the load it must not pass on to other users
    cfg["simulation"]["password_cost_log2"] = 14
    d = Daemon(tmp, seeds=[Seed(seed=1)], config=cfg)
    [a] = d.seeded
    b = a  # refused issues write no file: run a serves them between the attacks on its files
    _sql(d.data_dir / "station.db", "UPDATE runs SET operator = ?", args=(OPERATOR,))
    d.start(timeout_s=START_S)
    try:
        d.c().timeout = httpx.Timeout(TIMEOUT_S)
        for name, role in ROLES.items():
            r = d.c().put(f"/users/{name}", json={"role": role, "password": PASSWORDS[name]})
            assert r.status_code == 200, r.text
        db = sqlite3.connect(d.data_dir / "station.db")
        stored = [r[0] for r in db.execute("SELECT password FROM users WHERE password != ''")]
        db.close()
        assert stored and all(h.startswith("scrypt$16384$") for h in stored), stored  # the product's cost
        users: dict[str, httpx.Client] = {}
        lab = Lab(d, a, b, users)
        for name in ROLES:
            users[name] = lab.client(name)
        lab.assert_clean()
        yield lab
        for cl in users.values():
            cl.close()
    finally:
        d.stop()


READS = ("/results", "/report", "/report.pdf", "/plots/bode.png", "/recording", "/certificate.html",
         "/certificate.pdf", "/discrepancy", "/integrity")


def _refused_everywhere(lab: Lab, run: str, name: str) -> None:
    """Every endpoint that serves or uses the run's files refuses, naming ``name``."""
    for url in READS:
        r = lab.get(f"/runs/{run}{url}")
        assert r.status_code == 409 and name in r.json()["detail"], (url, r.status_code, r.text[:300])
    r = lab.d.c().post("/campaigns", json={"runs": [run], "store": False})
    assert r.status_code == 409 and name in r.json()["detail"], r.text
    r = lab.d.c().post(f"/runs/{run}/discrepancy", json={})
    assert r.status_code in (409, 422) and (r.status_code == 422 or name in r.json()["detail"]), r.text
    r = lab.users["anton"].post(f"/runs/{run}/certificate", json={})
    assert r.status_code == 409 and name in r.json()["detail"], r.text
    r = lab.get("/integrity")
    assert r.status_code == 409 and name in r.json()["detail"]


# ---------------------------------------------------------------------------------------------- the files
def test_results_with_s_and_k_f_edited_are_refused(lab: Lab) -> None:
    path = next((lab.rec / f"{lab.a}.results").glob("results.identify_fd_sdof.h5"))
    old = path.read_bytes()
    with h5py.File(path, "r+") as f:
        doc = json.loads(f.attrs["json"])
        doc["parameters"]["S"]["value"] *= 1.01
        doc["parameters"]["k_f"]["value"] *= 0.9
        f.attrs["json"] = json.dumps(doc)
    try:
        _refused_everywhere(lab, lab.a, path.name)
    finally:
        path.write_bytes(old)
    assert lab.get(f"/runs/{lab.a}/results").status_code == 200
    lab.assert_clean()


def test_a_recording_flipped_with_its_hash_rewritten_in_the_runs_table_is_refused(lab: Lab) -> None:
    from station.lab.integrity import sha256_file

    path = lab.rec / f"{lab.a}.h5"
    good = sha256_file(path)
    old = flip_bit(path)
    _sql(lab.db, "UPDATE runs SET recording_sha256 = ? WHERE id = ?", args=(sha256_file(path), lab.a))
    try:
        _refused_everywhere(lab, lab.a, path.name)
    finally:
        path.write_bytes(old)
        _sql(lab.db, "UPDATE runs SET recording_sha256 = ? WHERE id = ?", args=(good, lab.a))
    lab.assert_clean()


def test_a_flipped_byte_in_a_recording_is_refused_by_every_endpoint(lab: Lab) -> None:
    path = lab.rec / f"{lab.a}.h5"
    old = flip_bit(path, 0.3)
    try:
        _refused_everywhere(lab, lab.a, path.name)
    finally:
        path.write_bytes(old)
    lab.assert_clean()


# ---------------------------------------------------------------------------------------------- the trail
def test_the_trail_rewritten_behind_its_triggers_is_found_by_integrity_health_and_audit(lab: Lab) -> None:
    # entries no later case relies on (a run's entries would leave its files unvouched for good)
    rows = sqlite3.connect(lab.db).execute("SELECT id FROM audit WHERE action = 'user.changed' ORDER BY id").fetchall()
    who_id, gone_id = int(rows[0][0]), int(rows[1][0])
    db = sqlite3.connect(lab.db, timeout=10)
    trig = [r[0] for r in db.execute("SELECT sql FROM sqlite_master WHERE type = 'trigger' AND tbl_name = 'audit'")]
    db.execute("DROP TRIGGER audit_no_update")
    db.execute("DROP TRIGGER audit_no_delete")
    db.execute("UPDATE audit SET who = 'mallory' WHERE id = ?", (who_id,))
    db.execute("DELETE FROM audit WHERE id = ?", (gone_id,))
    for t in trig:
        db.execute(t)
    db.commit()
    db.close()
    r = lab.get("/integrity")
    assert r.status_code == 409 and f"broken at entry {who_id}" in r.json()["detail"], r.text
    health = lab.get("/health").json()
    assert health["status"] == "degraded" and health["audit_chain"]["ok"] is False
    audit_page = lab.get("/audit", params={"limit": 1000}).json()
    assert {who_id, gone_id} <= set(audit_page["broken"]), audit_page.get("broken")
    r = lab.users["anton"].post(f"/runs/{lab.b}/certificate", json={})
    assert r.status_code == 409 and f"entry {who_id}" in r.json()["detail"]
    # reviewed by an administrator (not by an approver): the breaks stay listed, issuing is possible again
    for b in (who_id, gone_id):
        assert lab.users["anton"].post("/integrity/exceptions", json={"entry": b, "reason": "seen"}).status_code \
            in (403, 422)
        r = lab.users["ada"].post("/integrity/exceptions", json={"entry": b, "reason": "reviewed by QM today"})
        assert r.status_code == 200, r.text
    lab.assert_clean()


def test_a_policy_and_an_adjustment_edited_with_sqlite3_are_refused(lab: Lab) -> None:
    """The check-transducer mark and an as-left value are rows the chain vouches for: the daemon's
    history, its hold before an issue and /integrity find an edit made with sqlite3."""
    tx = lab.get(f"/runs/{lab.a}").json()["transducer_id"]
    r = lab.users["ada"].put(f"/register/transducers/{tx}/policy",
                             json={"tolerances": {"S": 0.005}, "interval_days": 365, "check_standard": False})
    assert r.status_code == 200, r.text
    r = lab.users["anton"].post(f"/runs/{lab.a}/as-left",
                                json={"parameter": "S", "value": 2.001e-6, "unit": "V/N", "note": "gain set"})
    assert r.status_code == 200, r.text
    h = lab.get(f"/transducers/{tx}/history")
    assert h.status_code == 200, h.text + lab.d.log()
    for stmt, words in (("UPDATE transducer_policy SET tolerances_json = '{\"S\": 0.5}'", "tolerances changed"),
                        ("UPDATE as_left SET value = value * 1.01", "value changed")):
        db = sqlite3.connect(lab.db, timeout=10)
        saved = [tuple(r) for r in db.execute(f"SELECT * FROM {stmt.split()[1]}")]
        db.close()
        _sql(lab.db, stmt)
        try:
            r = lab.get(f"/transducers/{tx}/history")
            assert r.status_code == 409 and words in r.json()["detail"], r.text
            r = lab.get("/integrity")
            assert r.status_code == 409 and words in r.json()["detail"]
        finally:
            table = stmt.split()[1]
            marks = ", ".join("?" * len(saved[0]))
            db = sqlite3.connect(lab.db, timeout=10)
            db.execute(f"DELETE FROM {table}")
            db.executemany(f"INSERT INTO {table} VALUES ({marks})", saved)
            db.commit()
            db.close()
        assert lab.get(f"/transducers/{tx}/history").status_code == 200
    lab.assert_clean()


def _entries(lab: Lab, action: str) -> list[dict[str, Any]]:
    return list(lab.get("/audit", params={"action": action, "limit": 1000}).json()["entries"])


def test_an_out_of_range_audit_cursor_is_422(lab: Lab) -> None:
    r = lab.get("/audit", params={"before_id": "99999999999999999999999"})
    assert r.status_code == 422 and "before_id" in r.text and "Traceback" not in r.text
    assert lab.get("/audit", params={"before_id": str(2**63 - 1)}).status_code == 200  # the largest is taken


# ---------------------------------------------------------------------------------------------- logins
def _lift(lab: Lab) -> None:
    """Lift every lock-out in force, and the loopback address's failure count even when its lock has
    run out meanwhile (a loaded machine takes seconds between a case's failures and its end): a count
    past the free failures would lock the next case's first failure out (``GET /logins/locks`` lists
    the locks in force only)."""
    for x in lab.get("/logins/locks").json():
        assert lab.d.c().delete(f"/logins/locks/{x['key']}").status_code == 200
    assert lab.d.c().delete("/logins/locks/client:127.0.0.1").status_code in (200, 404)  # 404: no count left


def test_guessing_a_password_locks_the_name_out(lab: Lab) -> None:
    from station.service import logins

    c = lab.client()
    try:
        for _ in range(logins.FREE_FAILURES + 1):
            assert c.post("/login", json={"name": "tina", "password": "not-her-password"}).status_code == 401
        r = c.post("/login", json={"name": "tina", "password": PASSWORDS["tina"]})
        assert r.status_code == 401 and "locked until" in r.json()["detail"]
        assert {x["key"] for x in lab.get("/logins/locks").json()} >= {"user:tina", "client:127.0.0.1"}
        assert _lock_seconds(lab, "user:tina", 1)  # audited (by the daemon's writer, a moment later)
        assert "login lock-out: user:tina" in lab.d.log()
    finally:
        _lift(lab)
        c.close()
    assert lab.client("tina").get("/me").json()["user"]["name"] == "tina"


def test_every_kind_of_name_is_refused_alike(lab: Lab) -> None:
    """Unknown, known with a wrong password, disabled, password-less: the same status and words."""
    assert lab.d.c().put("/users/dora", json={"role": "technician", "password": "dora-secret-pw",
                                              "disabled": True}).status_code == 200
    assert lab.d.c().put("/users/tok", json={"role": "technician"}).status_code == 200
    c = lab.client()
    try:
        answers = {name: c.post("/login", json={"name": name, "password": "wrong-password-1"})
                   for name in ("nobody", "tina", "dora", "tok")}
        assert {(r.status_code, r.json()["detail"]) for r in answers.values()} == \
            {(401, answers["nobody"].json()["detail"])}, {k: r.text for k, r in answers.items()}
    finally:
        _lift(lab)
        c.close()


def test_a_password_typed_into_the_name_field_is_not_stored(lab: Lab) -> None:
    c = lab.client()
    try:
        r = c.post("/login", json={"name": "Sup3r Secret!", "password": "x"})
        assert r.status_code in (401, 422)
        assert "Sup3r" not in lab.get("/audit", params={"limit": 1000}).text
    finally:
        _lift(lab)
        c.close()


def test_a_new_password_or_a_disable_ends_sessions_and_tokens_are_revoked(lab: Lab) -> None:
    sessions = [lab.client("tina"), lab.client("tina")]
    assert all(s.get("/me").status_code == 200 for s in sessions)
    assert lab.d.c().put("/users/tina", json={"role": "technician", "password": "a-new-password-1"}).status_code == 200
    assert [s.get("/me").status_code for s in sessions] == [401, 401]
    assert lab.d.c().put("/users/tina", json={"role": "technician", "password": PASSWORDS["tina"]}).status_code == 200
    s = lab.client("tina")
    assert lab.d.c().put("/users/tina", json={"role": "technician", "disabled": True}).status_code == 200
    assert s.get("/me").status_code == 401
    assert lab.d.c().put("/users/tina", json={"role": "technician", "disabled": False}).status_code == 200
    text = lab.d.c().post("/users/tina/tokens", json={"label": "ci"}).json()["token"]
    bot = httpx.Client(base_url=lab.d.url, headers={"Authorization": f"Bearer {text}"}, timeout=30, verify=TLS)
    assert bot.get("/me").json()["user"]["name"] == "tina"
    [row] = [t for t in lab.get("/tokens", params={"user": "tina"}).json() if t["label"] == "ci"]
    assert text not in json.dumps(row)
    assert lab.d.c().delete(f"/tokens/{row['id']}").status_code == 200
    assert bot.get("/me").status_code == 401
    for c in (*sessions, s, bot):
        c.close()
    lab.users["tina"] = lab.client("tina")


def test_a_login_flood_never_fails_another_users_request(lab: Lab) -> None:
    """16 clients guessing at once (more than the password checks' pool holds, its threads and its
    queue: 10) while an approver reads and writes: no 5xx for anyone, every one of the approver's
    requests answered, and logins refused at once as "too many logins at once" while the approver's
    requests go on (the pool was full then).  Each client guesses until the approver's requests are
    all answered (at least once, at most three times): the flood lasts as long as they do, and no
    longer keeps the password checks busy (each about 0.1 s of CPU).  (64 clients and 12 requests of
    the approver before: the pool is as full with 16, and the checks beyond the first ten were the
    same refusals.)"""
    statuses: list[int] = []
    overflowed: list[str] = []  # the "too many logins at once" answers while the approver's requests went on
    lock = threading.Lock()
    begun, answered = threading.Event(), threading.Event()

    def guess(i: int) -> None:
        with httpx.Client(base_url=lab.d.url, timeout=60, verify=TLS) as c:
            for k in range(3):
                if k and answered.is_set():
                    break
                r = c.post("/login", json={"name": f"user{i}", "password": "guess-guess-1"})
                during = begun.is_set() and not answered.is_set()
                with lock:
                    statuses.append(r.status_code)
                    if during and r.status_code == 401 and "too many logins at once" in r.json()["detail"]:
                        overflowed.append(r.json()["detail"])

    anton = lab.users["anton"]  # its keep-alive connection, idle since an earlier case, reused
    threads = [threading.Thread(target=guess, args=(i,)) for i in range(16)]
    for t in threads:
        t.start()
    mine: list[tuple[int, str, str | None]] = []
    try:
        begun.set()
        for _ in range(3):
            for r in (anton.get(f"/runs/{lab.a}"), anton.post(f"/runs/{lab.a}/approve", json={"note": "flood"})):
                mine.append((r.status_code, r.text[:200], r.headers.get("keep-alive")))
    finally:
        answered.set()
        for t in threads:
            t.join()
        _lift(lab)
    assert [m[0] for m in mine] == [200] * len(mine), mine
    assert {m[2] for m in mine} == {"timeout=9"}  # the idle limit announced (10 s header timeout)
    assert statuses and set(statuses) <= {401, 429, 503} and all(s < 500 or s == 503 for s in statuses)
    assert overflowed, statuses  # a real flood: the pool was full while the approver's requests went on
    assert "Traceback" not in lab.d.log()


# ---------------------------------------------------------------------------------------------- bounded input
def _station(*args: str, cwd: Path, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "STATION_TOKEN": AUTH["Authorization"].split()[1]}
    return subprocess.run([sys.executable, "-m", "station.cli", *args], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=timeout)


def test_a_duplicate_key_in_the_configuration_stops_the_daemon_naming_both_lines(lab: Lab) -> None:
    lines = lab.d.cfg_path.read_text().splitlines()
    at = next(i for i, ln in enumerate(lines) if ln.strip().startswith("capacity_N:"))
    indent = lines[at][: len(lines[at]) - len(lines[at].lstrip())]
    bad = lab.d.tmp / "dup.yaml"
    bad.write_text("\n".join([*lines[: at + 1], f"{indent}capacity_N: 50000.0", *lines[at + 1:]]) + "\n")
    out = _station("serve", "--sim", "--config", str(bad), "--port", "0", cwd=lab.d.tmp)
    assert out.returncode != 0
    text = out.stdout + out.stderr
    assert f"line {at + 1} and again on line {at + 2}" in text and "Traceback" not in text, text[-2000:]


RUN = ("format: sinecal-csv\nformat_version: 1\nsample_rate_hz: 1000\ntop_mass_kg: 1\nend_mass_kg: 0.1\n"
       "crank_radius_m: 0.001\ntransducer: {id: T, capacity_N: 5000, sensitivity_V_per_N: 2.0e-6}\nsteps:\n")


def test_an_import_of_a_fifo_is_refused_at_once(lab: Lab, tmp_path: Path) -> None:
    """``station import`` as a user runs it: a FIFO named as a signal file is refused at once (not
    read for ever), with a message and no traceback.  The symlink loop, the device and too many
    bytes are refused by the same import (tests/test_records.py); the command line adds nothing
    of its own for them."""
    os.mkfifo(tmp_path / "s.csv")
    files, words = ["s.csv"], "not a regular file"
    (tmp_path / "RUN.yaml").write_text(RUN + "".join(f"  - {{file: {f}, crank_frequency_hz: 10}}\n" for f in files))
    out = _station("import", str(tmp_path / "RUN.yaml"), "--out", str(tmp_path / "out"), cwd=tmp_path, timeout=30)
    assert out.returncode != 0 and words in out.stdout + out.stderr, out.stdout + out.stderr
    assert "Traceback" not in out.stderr
    assert not list((tmp_path / "out").glob("*.h5")) if (tmp_path / "out").exists() else True


# ---------------------------------------------------------------------------------------------- a restart
def test_a_restart_after_a_crash_hashes_the_recovered_recording_and_logs_a_broken_chain(lab: Lab) -> None:
    """The daemon killed while it records: the partial recording is recovered at the next start and
    hashed into the chain; a break made while it was down is logged at that start and degrades
    /health; a lock-out made before is still in force (a restart forgets neither)."""
    from station.service import logins

    _lift(lab)
    with lab.client() as c:  # a name locked out: a restart neither lifts it nor starts its doubling again
        for _ in range(logins.FREE_FAILURES + 1):
            c.post("/login", json={"name": "lotte", "password": "guess-guess-1"})
    assert _lock_seconds(lab, "user:lotte", 1) == [logins.BASE_LOCK_S]
    for _ in range(3):  # a simulated run starved of CPU by a loaded machine may fail (the drive's watchdog)
        rid = lab.d.start_run()
        deadline = time.monotonic() + 120.0
        while time.monotonic() < deadline:
            st = lab.get(f"/runs/{rid}").json()
            if st["state"] not in ("queued", "running") or st["step_state"] == "recording":
                break
            time.sleep(0.1)
        if st["state"] == "running" and st["step_state"] == "recording":
            break
    assert st["state"] == "running" and st["step_state"] == "recording", st
    lab.d.kill()
    entry = sqlite3.connect(lab.db).execute("SELECT max(id) FROM audit WHERE action = 'user.login'").fetchone()[0]
    db = sqlite3.connect(lab.db, timeout=10)
    db.execute("DROP TRIGGER audit_no_update")
    db.execute("UPDATE audit SET details = '{}' WHERE id = ?", (entry,))
    db.execute("CREATE TRIGGER audit_no_update BEFORE UPDATE ON audit "
               "BEGIN SELECT RAISE(ABORT, 'the audit trail is append-only'); END")
    db.commit()
    db.close()
    lab.d.start(timeout_s=START_S)
    assert f"audit chain broken at entry {entry}" in lab.d.log()
    health = lab.get("/health").json()
    assert health["status"] == "degraded" and health["audit_chain"]["ok"] is False
    run = lab.get(f"/runs/{rid}").json()
    assert run["state"] == "interrupted" and run["recording"], run
    [rec] = _entries_of(lab, rid, "run.recovered")
    assert rec["files"] == {run["recording"]: hashlib.sha256((lab.rec / run["recording"]).read_bytes()).hexdigest()}
    assert lab.get(f"/runs/{rid}/integrity").status_code == 200
    time.sleep(logins.BASE_LOCK_S)  # the first lock-out has run out by now; the next failure doubles it
    with lab.client() as c:
        r = c.post("/login", json={"name": "lotte", "password": "guess-guess-1"})
    assert r.status_code == 401
    assert _lock_seconds(lab, "user:lotte", 2) == [2 * logins.BASE_LOCK_S, logins.BASE_LOCK_S]
    _lift(lab)
    r = lab.d.c().post("/integrity/exceptions", json={"entry": entry, "reason": "reviewed by QM today"})
    assert r.status_code == 200, r.text
    lab.users.update({name: lab.client(name) for name in ROLES})
    lab.assert_clean()


def _lock_seconds(lab: Lab, key: str, n: int) -> list[float]:
    """The lengths of the lock-outs of ``key`` the trail records, newest first, once it holds ``n``
    (the daemon's writer appends them a moment after the refusal)."""
    deadline = time.monotonic() + 60.0
    while True:
        got = [e["details"]["seconds"] for e in _entries_of(lab, key, "user.login_locked")
               if "seconds" in e["details"]]  # not the lifts
        if len(got) >= n or time.monotonic() > deadline:
            return got
        time.sleep(0.2)


def _entries_of(lab: Lab, target: str, action: str) -> list[dict[str, Any]]:
    return list(lab.get("/audit", params={"target": target, "action": action}).json()["entries"])

