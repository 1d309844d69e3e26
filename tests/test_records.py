"""Records a lab can trust: the audit trail is a hash chain that finds an entry rewritten, deleted or
inserted around the database's triggers, and every recording, results file and certificate the
daemon serves or uses is compared with it first (a change outside the station is refused, 409,
naming the file).  The attacks are those an insider with write access to the recordings folder
and the database file would make."""

from __future__ import annotations

import asyncio
import itertools
import sqlite3
from pathlib import Path

import pytest

from station.lab import audit, chain
from station.lab.store import Store
from tests.recording_support import flip_bit


def _trail(tmp_path: Path, n: int = 5) -> Store:
    store = Store(tmp_path / "s.db")
    for i in range(n):
        audit.append(store, "tina", audit.RUN_STARTED, f"r{i}", {"i": i}, files={f"r{i}.h5": f"{i:064x}"})
    return store


def _state(store: Store) -> chain.ChainState:
    with store.reading() as db:
        return chain.verify_chain(db)


def _behind_the_triggers(path: Path, *stmts: str) -> None:
    """What an insider with the database file does: the triggers dropped, the trail changed, the
    triggers put back as they were."""
    db = sqlite3.connect(path)
    trig = [r[0] for r in db.execute("SELECT sql FROM sqlite_master WHERE type = 'trigger' AND tbl_name = 'audit'")]
    db.execute("DROP TRIGGER audit_no_update")
    db.execute("DROP TRIGGER audit_no_delete")
    for s in stmts:
        db.execute(s)
    for t in trig:
        db.execute(t)
    db.commit()
    db.close()


def test_a_clean_trail_verifies_and_each_entry_links_to_the_one_before(tmp_path: Path) -> None:
    store = _trail(tmp_path)
    st = _state(store)
    assert st.ok and st.entries == 5 and st.head_id == 5 and not st.breaks
    rows = store.query("SELECT * FROM audit ORDER BY id")
    assert rows[0]["prev"] == chain.GENESIS
    assert all(b["prev"] == a["hash"] == chain.entry_hash(a) for a, b in itertools.pairwise(rows))
    with store.reading() as db:
        assert chain.expected_files(db, "r3") == {"r3.h5": f"{3:064x}"}
    store.close()


@pytest.mark.parametrize(("stmts", "broken_at", "words"), [
    (("UPDATE audit SET who = 'mallory' WHERE id = 3",), 3, "content does not match"),
    (("DELETE FROM audit WHERE id = 2",), 2, "entries 2 to 2 are missing"),
    (("DELETE FROM audit WHERE id = 5",), 5, "deleted from the end"),
    (("INSERT INTO audit (id, at, who, action, target, details, files, prev, hash) SELECT 6, at, who, action, "
      "target, details, files, prev, hash FROM audit WHERE id = 2",), 6, "link to the entry before"),
    (("UPDATE audit SET files = '{\"r1.h5\": \"" + "f" * 64 + "\"}' WHERE id = 2",), 2, "content does not match"),
])
def test_a_change_behind_the_triggers_is_named_at_its_entry(tmp_path: Path, stmts: tuple[str, ...],
                                                            broken_at: int, words: str) -> None:
    store = _trail(tmp_path)
    store.close()
    _behind_the_triggers(tmp_path / "s.db", *stmts)
    store = Store(tmp_path / "s.db")
    st = _state(store)
    assert not st.ok and st.open_breaks[0].id == broken_at and words in st.open_breaks[0].reason
    assert f"broken at entry {broken_at}" in st.describe()
    with store.reading() as db:  # a page of /audit marks it too (not an entry deleted from the end: no page has it)
        assert chain.broken_among(db, range(1, 10)) == ([] if "from the end" in words else [broken_at])
    with pytest.raises(chain.ChainBrokenError, match=f"entry {broken_at}"):
        st.require()
    # an administrator's reviewed exception: still listed, no longer blocking; the exception is a link too
    audit.append(store, "ada", audit.AUDIT_EXCEPTION, "audit", {"entry": broken_at, "reason": "reviewed"})
    st = _state(store)
    assert st.ok and st.breaks[0].id == broken_at and st.breaks[0].excepted_by == st.head_id
    store.close()


def test_a_rewritten_entry_that_vouches_for_files_is_refused_where_it_is_used(tmp_path: Path) -> None:
    store = _trail(tmp_path)
    store.close()
    _behind_the_triggers(tmp_path / "s.db", "UPDATE audit SET files = '{\"r2.h5\": \"" + "e" * 64 + "\"}' WHERE id = 3")
    store = Store(tmp_path / "s.db")
    with store.reading() as db, pytest.raises(chain.ChainBrokenError, match="entry 3"):
        chain.expected_files(db, "r2")
    store.close()


def test_an_older_trail_is_chained_as_it_stands(tmp_path: Path) -> None:
    """A database from before the chain: its entries get their links once, and verify."""
    path = tmp_path / "old.db"
    store = Store(path)
    store.close()
    db = sqlite3.connect(path)
    db.execute("DROP TRIGGER audit_no_update")
    db.execute("DROP TABLE audit")
    db.execute("CREATE TABLE audit (id INTEGER PRIMARY KEY AUTOINCREMENT, at REAL NOT NULL, who TEXT NOT NULL, "
               "action TEXT NOT NULL, target TEXT NOT NULL DEFAULT '', details TEXT NOT NULL DEFAULT '{}')")
    for i in range(3):
        db.execute("INSERT INTO audit (at, who, action, target) VALUES (?, 'tina', 'run.started', ?)", (i, f"r{i}"))
    db.commit()
    db.close()
    store = Store(path)
    audit.append(store, "tina", audit.RUN_ENDED, "r2")
    st = _state(store)
    assert st.ok and st.entries == 4
    with pytest.raises(sqlite3.IntegrityError, match="append-only"), store.transaction() as t:
        t.execute("UPDATE audit SET who = 'x'")
    store.close()


# ---------------------------------------------------------------------------------------------- the daemon
@pytest.fixture(scope="module")
def seeded_once(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A recordings folder with one seeded, identified run (vouched for as the daemon vouches), made
    once for the module: the tests attack files and rows, so each works on a copy (:func:`seeded`)."""
    from tests.station_support import Seed, daemon_config, seed_runs

    rec = tmp_path_factory.mktemp("records-seeded") / "recordings"
    [rid] = seed_runs(daemon_config(rec), [Seed()])
    return rec, rid


def seeded(once: tuple[Path, str], tmp_path: Path) -> tuple[Path, str]:
    """A copy of the module's seeded recordings folder in ``tmp_path`` (the run's id)."""
    import shutil

    rec = tmp_path / "recordings"
    shutil.copytree(once[0], rec)
    return rec, once[1]


@pytest.mark.slow
@pytest.mark.xdist_group("records_seeded")  # the module's seeded run made once for both
def test_every_endpoint_refuses_files_changed_outside_the_station(tmp_path: Path,
                                                                  seeded_once: tuple[Path, str]) -> None:
    """A seeded, identified run (vouched for as the daemon vouches): its results file edited, its
    recording flipped with the runs table's SHA-256 rewritten to match, a results file added, the
    trail rewritten behind the triggers.  Every endpoint that reads the run refuses (409, the file
    named), /integrity names it, and all is served again once the files are restored."""
    from tests.station_support import CAPPED_SPEEDUP, IDLE_SPEEDUP, app_in_process

    rec, rid = seeded(seeded_once, tmp_path)
    results = sorted((rec / f"{rid}.results").glob("results.*.h5"))
    assert results
    reads = [f"/runs/{rid}/results", f"/runs/{rid}/report", f"/runs/{rid}/report.pdf", f"/runs/{rid}/plots/bode.png",
             f"/runs/{rid}/recording", f"/runs/{rid}/certificate.html", f"/runs/{rid}/certificate.pdf",
             f"/runs/{rid}/discrepancy", f"/runs/{rid}/integrity"]

    async def go() -> None:
        async with app_in_process(rec, max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (manager, c):
            assert (await c.get(f"/runs/{rid}/results")).status_code == 200
            assert (await c.get("/integrity")).status_code == 200
            assert (await c.get("/health")).json()["audit_chain"]["ok"] is True

            async def refused(name: str) -> None:
                for url in reads:
                    r = await c.get(url)
                    assert r.status_code == 409 and name in r.json()["detail"], (url, r.status_code, r.text[:300])
                r = await c.post("/campaigns", json={"runs": [rid], "store": False})
                assert r.status_code == 409 and name in r.json()["detail"]
                r = await c.get("/integrity")
                assert r.status_code == 409 and name in r.json()["detail"]

            # 1. S and k_f edited in a results file
            target = results[0]
            old = flip_bit(target, 0.9)
            await refused(target.name)
            target.write_bytes(old)
            assert (await c.get(f"/runs/{rid}/results")).status_code == 200
            # 2. a byte of the recording flipped and the runs table's SHA-256 rewritten to match
            recording = rec / f"{rid}.h5"
            old = flip_bit(recording)
            from station.lab.integrity import sha256_file
            db = sqlite3.connect(manager.settings.database)
            db.execute("UPDATE runs SET recording_sha256 = ? WHERE id = ?", (sha256_file(recording), rid))
            db.commit()
            db.close()
            manager.db.update_run(rid, {"recording_sha256": sha256_file(recording)})
            await refused(recording.name)
            recording.write_bytes(old)
            manager.db.update_run(rid, {"recording_sha256": sha256_file(recording)})
            assert (await c.get(f"/runs/{rid}/results")).status_code == 200
            # 3. a results file added beside the recording
            extra = rec / f"{rid}.results" / "results.identify_fd_2dof.h5"
            extra.write_bytes(results[0].read_bytes())
            await refused(extra.name)
            extra.unlink()
            assert (await c.get(f"/runs/{rid}/integrity")).status_code == 200
            # 4. the entry that vouches for the results rewritten behind the triggers
            entry = audit.entries(manager.store, target=rid, action=audit.RUN_IDENTIFIED)[0]
            _behind_the_triggers(manager.settings.database,
                                 f"UPDATE audit SET who = 'mallory' WHERE id = {entry.id}")
            r = await c.get(f"/runs/{rid}/results")
            assert r.status_code == 409 and f"audit entry {entry.id}" in r.json()["detail"]
            r = await c.get("/integrity")
            assert r.status_code == 409 and f"broken at entry {entry.id}" in r.json()["detail"]
            health = (await c.get("/health")).json()
            assert health["status"] == "degraded" and health["audit_chain"]["ok"] is False
            # only an administrator records the reviewed exception, and only for a real break
            r = await c.post("/integrity/exceptions", json={"entry": entry.id + 1, "reason": "reviewed by QM today"})
            assert r.status_code == 409
            r = await c.post("/integrity/exceptions", json={"entry": entry.id, "reason": "reviewed by QM today"})
            assert r.status_code == 200 and r.json()["breaks"][0]["excepted_by"] is not None
            assert (await c.get("/health")).json()["audit_chain"]["ok"] is True
    asyncio.run(go())


# ---------------------------------------------------------------------------------------------- issuing
def test_two_recordings_folders_of_one_lab_never_issue_the_same_number(tmp_path: Path) -> None:
    """One lab database, two recordings folders (two stations): one sequence; deleting a
    certificate's files gives its number to nobody; a number whose files exist is skipped."""
    from station.lab import certificates

    store = Store(tmp_path / "lab.db")
    a, b = tmp_path / "a" / "certificates", tmp_path / "b" / "certificates"
    for f in (a, b):
        f.mkdir(parents=True)
    got = [certificates.take_number(store, "SC", 2026, f"r{i}", (a, b)[i % 2]) for i in range(6)]
    assert got == [f"SC-2026-{i:04d}" for i in range(1, 7)]
    (b / "SC-2026-0007.json").write_text("{}")  # a number's files already there (an older database restored)
    assert certificates.take_number(store, "SC", 2026, "r6", b) == "SC-2026-0008"
    assert certificates.take_number(store, "SC", 2027, "r7", a) == "SC-2027-0001"
    assert certificates.take_number(store, "LAB2", 2026, "r8", a) == "LAB2-2026-0001"
    store.close()


def _customer_checks(folder: Path, number: str, public_pem: str, where: Path) -> None:
    """`station verify CERTIFICATE --key` on copies, as a customer would (no station, no database):
    each form passes; any byte changed in it, or in the signature file, fails; another key fails."""
    import shutil

    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    from station.cli import main
    from station.lab import signing

    where.mkdir()
    key = where / "lab.pem"
    key.write_text(public_pem)
    for ext in ("pdf", "xml", "html", "sig"):
        shutil.copy(folder / f"{number}.{ext}", where / f"{number}.{ext}")
    for ext in ("pdf", "xml", "html"):
        cert = where / f"{number}.{ext}"
        assert main(["verify", str(cert), "--key", str(key)]) == 0
        good = cert.read_bytes()
        for at in (0, len(good) // 3, len(good) - 1):
            flip_bit(cert, at / len(good))
            assert main(["verify", str(cert), "--key", str(key)]) == 1
            cert.write_bytes(good)
    sig = where / f"{number}.sig"
    good = sig.read_bytes()
    sig.write_bytes(good.replace(b'"number": "', b'"number": "X'))
    assert main(["verify", str(where / f"{number}.pdf"), "--key", str(key)]) == 1
    sig.write_bytes(good)
    other = where / "other.pem"
    other.write_text(signing.public_pem(Ed25519PrivateKey.generate().public_key()))
    assert main(["verify", str(where / f"{number}.pdf"), "--key", str(other)]) == 1
    assert main(["verify", str(where / f"{number}.pdf"), "--key", str(key)]) == 0


def test_the_signing_key_is_the_owners_alone_and_rotation_keeps_the_old_one(tmp_path: Path) -> None:
    import stat

    from station.lab import signing

    path = tmp_path / "k" / "signing-key.pem"
    key, retired = signing.init_key(path)
    assert retired is None and stat.S_IMODE(path.stat().st_mode) == 0o600
    with pytest.raises(signing.SigningError, match="never overwritten"):
        signing.init_key(path)
    new, retired = signing.init_key(path, rotate=True)
    assert retired is not None and stat.S_IMODE(retired.stat().st_mode) == 0o600
    assert signing.fingerprint(signing.load_key(retired).public_key()) == signing.fingerprint(key.public_key())
    assert signing.fingerprint(signing.load_key(path).public_key()) == signing.fingerprint(new.public_key())
    path.chmod(0o644)
    with pytest.raises(signing.SigningError, match="readable by others"):
        signing.load_key(path)


@pytest.mark.slow
@pytest.mark.xdist_group("records_seeded")  # the module's seeded run made once for both
def test_the_issuing_rules_hold_and_the_register_is_the_audit_trail(tmp_path: Path,
                                                                   seeded_once: tuple[Path, str]) -> None:
    """Free-text preparer, a technician, the operator approving, a second live certificate: each
    refused with one refusal entry; an issue names its number and the SHA-256 of its files; an
    issued file edited with its record's hashes recomputed is refused; a hand-made withdrawal
    marker changes nothing; withdrawal only through the station; deleted files never give their
    number again."""
    import hashlib
    import json

    from tests.station_support import CAPPED_SPEEDUP, IDLE_SPEEDUP, PASSWORDS, app_in_process, login

    rec, rid = seeded(seeded_once, tmp_path)

    async def go() -> None:
        async with app_in_process(rec, max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (manager, c):
            app = c._transport.app  # type: ignore[attr-defined]
            for name, role in (("tina", "technician"), ("anton", "approver")):
                r = await c.put(f"/users/{name}", json={"role": role, "password": PASSWORDS[name]})
                assert r.status_code == 200
            manager.db.update_run(rid, {"operator": "tina"})
            tina, anton = await login(app, "tina"), await login(app, "anton")

            def trail(action: str) -> list[audit.AuditEntry]:
                return audit.entries(manager.store, action=action)

            async def refused(client: object, body: dict[str, object], status: int, words: str,
                              entries: int = 1) -> None:
                n = len(trail(audit.CERTIFICATE_REFUSED))
                r = await client.post(f"/runs/{rid}/certificate", json=body)  # type: ignore[attr-defined]
                assert r.status_code == status and words in r.json()["detail"], r.text
                assert len(trail(audit.CERTIFICATE_REFUSED)) == n + entries
                assert not trail(audit.CERTIFICATE_APPROVED)

            await refused(anton, {"prepared_by": "Mickey Mouse"}, 409, "not an enabled user of the lab")
            await refused(tina, {}, 403, "approve", entries=0)  # refused at the door: no issue was attempted
            await refused(anton, {"prepared_by": "anton"}, 403, "second person")
            assert not trail(audit.CERTIFICATE_ISSUED)
            ok = await anton.post(f"/runs/{rid}/certificate", json={})
            assert ok.status_code == 201, ok.text
            number = ok.json()["number"]
            assert ok.json()["prepared_by"] == "tina" and ok.json()["approved_by"] == "anton"
            [entry] = trail(audit.CERTIFICATE_ISSUED)
            folder = rec / "certificates"
            assert entry.details["number"] == number and entry.who == "anton"
            assert entry.files == {f"certificates/{number}.{e}": hashlib.sha256((folder / f"{number}.{e}").read_bytes())
                                   .hexdigest() for e in ("html", "pdf", "xml", "json", "sig")}
            # signed: the public key published, its fingerprint on the certificate, the DCC names the signature
            key = (await c.get("/signing-key", headers={"Authorization": ""})).json()
            assert key["algorithm"] == "Ed25519" and key["fingerprint"] in (folder / f"{number}.html").read_text()
            assert f"{number}.sig" in (folder / f"{number}.xml").read_text()
            assert entry.details["chain_head"]["id"] == entry.id - 1
            _customer_checks(folder, number, key["public_key"], tmp_path / "customer")
            await refused(anton, {}, 409, f"in force ({number})")
            # an issued certificate edited and its record's hashes recomputed: refused where served
            html = folder / f"{number}.html"
            old_html, old_json = html.read_bytes(), (folder / f"{number}.json").read_bytes()
            forged = old_html.replace(b"anton", b"boss")
            html.write_bytes(forged)
            record = json.loads(old_json)
            record["approved_by"] = "boss"
            record["sha256"]["html"] = hashlib.sha256(forged).hexdigest()
            (folder / f"{number}.json").write_text(json.dumps(record))
            for url in (f"/certificates/{number}.html", f"/runs/{rid}/certificate.html"):
                r = await c.get(url)
                assert r.status_code == 409 and f"{number}.html" in r.json()["detail"], (url, r.text)
            r = await c.get("/integrity")
            detail = r.json()["detail"]
            assert r.status_code == 409 and f"{number}.html" in detail and f"{number}.json" in detail
            listed = (await c.get("/certificates")).json()["certificates"]
            assert [(x["number"], x["approved_by"], x["withdrawn"]) for x in listed] == [(number, "anton", None)]
            html.write_bytes(old_html)
            (folder / f"{number}.json").write_bytes(old_json)
            assert (await c.get(f"/certificates/{number}.html")).status_code == 200
            # a hand-made withdrawal marker changes nothing (still in force); withdrawal is the station's,
            # with a reason
            (folder / f"{number}.replaced").write_text(json.dumps({"replaced_by": "X", "reason": "forged"}))
            assert (await c.get("/certificates")).json()["certificates"][0]["withdrawn"] is None
            await refused(anton, {}, 409, f"in force ({number})")
            # the files of a certificate in force deleted: found missing, and it is still in force by the chain
            saved = {p: p.read_bytes() for p in folder.glob(f"{number}.*")}
            for p in saved:
                p.unlink()
            r = await c.get("/integrity")
            assert r.status_code == 409 and f"certificates/{number}.pdf: missing" in r.json()["detail"]
            await refused(anton, {}, 409, f"in force ({number})")
            for p, data in saved.items():
                p.write_bytes(data)
            assert (await c.get("/integrity")).status_code == 200
            r = await tina.post(f"/certificates/{number}/withdraw", json={"reason": "the customer asked for it"})
            assert r.status_code == 403
            r = await anton.post(f"/certificates/{number}/withdraw", json={"reason": "the customer asked for it"})
            assert r.status_code == 200 and "customer asked" in r.json()["withdrawn"]
            assert trail(audit.CERTIFICATE_WITHDRAWN)[0].details["number"] == number
            # its files deleted: the number is not given again
            for p in folder.glob(f"{number}.*"):
                p.unlink()
            r = await c.get("/integrity")
            assert r.status_code == 409 and f"certificates/{number}.pdf: missing" in r.json()["detail"]
            again = await anton.post(f"/runs/{rid}/certificate", json={})
            assert again.status_code == 201 and again.json()["number"] != number
            assert again.json()["number"].endswith("-0002")
            for t in (tina, anton):
                await t.aclose()
    asyncio.run(go())


# ---------------------------------------------------------------------------------------------- bounded input
def test_a_key_written_twice_is_refused_naming_both_lines(tmp_path: Path) -> None:
    """The station's configuration (the force limit raised tenfold by a second capacity_N), a drive
    profile, a RUN.yaml: every YAML the station reads."""
    from sinecal_config import config_file

    from drivers.motor.errors import RegisterMapError
    from drivers.motor.profile import load_profile
    from station.config import default_config_path, load_config
    from station.errors import ConfigError

    text = default_config_path().read_text()
    lines = text.splitlines()
    at = next(i for i, ln in enumerate(lines) if ln.strip().startswith("capacity_N:"))
    indent = lines[at][: len(lines[at]) - len(lines[at].lstrip())]
    lines.insert(at + 1, f"{indent}capacity_N: 50000.0")
    bad = tmp_path / "station.yaml"
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError, match=f"key 'capacity_N' on line {at + 1} and again on line {at + 2}"):
        load_config(bad)
    prof = config_file("drives/sinecal-crank.yaml").read_text().splitlines()
    key = next(ln for ln in prof if ln and not ln.startswith((" ", "#")) and ":" in ln)
    (tmp_path / "drive.yaml").write_text("\n".join([*prof, key]) + "\n")
    with pytest.raises(RegisterMapError, match="again on line"):
        load_profile(tmp_path / "drive.yaml")


def test_an_import_refuses_fifos_loops_and_too_many_bytes(tmp_path: Path) -> None:
    import os

    from station.errors import RecordingFormatError
    from station.interchange import MAX_RUN_BYTES, import_run

    run = ("format: sinecal-csv\nformat_version: 1\nsample_rate_hz: 1000\ntop_mass_kg: 1\nend_mass_kg: 0.1\n"
           "crank_radius_m: 0.001\ntransducer: {id: T, capacity_N: 5000, sensitivity_V_per_N: 2.0e-6}\n"
           "steps:\n{steps}")

    def attempt(files: list[str]) -> str:
        (tmp_path / "RUN.yaml").write_text(run.replace("{steps}", "".join(
            f"  - {{file: {f}, crank_frequency_hz: 10}}\n" for f in files)))
        with pytest.raises(RecordingFormatError) as exc:
            import_run(tmp_path / "RUN.yaml", tmp_path / "out")
        return str(exc.value)

    os.mkfifo(tmp_path / "fifo.csv")
    assert "not a regular file" in attempt(["fifo.csv"])
    os.symlink(tmp_path / "loop2.csv", tmp_path / "loop1.csv")
    os.symlink(tmp_path / "loop1.csv", tmp_path / "loop2.csv")
    assert "cannot be opened" in attempt(["loop1.csv"])
    assert "must lie beside" in attempt(["/dev/zero"])  # a device elsewhere, or a link to one
    big = tmp_path / "big.csv"
    with open(big, "wb") as f:  # sparse: the size is what counts, nothing is read
        f.truncate(MAX_RUN_BYTES // 4 + 1)
    assert f"the limit is {MAX_RUN_BYTES} bytes per run" in attempt(["big.csv"] * 4)
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())


# ---------------------------------------------------------------------------------------------- logins
def _count_scrypt(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """hashlib.scrypt counted from now on: one 1 in the list per call."""
    import hashlib

    calls: list[int] = []
    real = hashlib.scrypt

    def counted(*a: object, **k: object) -> bytes:
        calls.append(1)
        return real(*a, **k)  # type: ignore[arg-type]
    monkeypatch.setattr(hashlib, "scrypt", counted)
    return calls


@pytest.mark.slow  # ten password checks and 64 refusals written
def test_a_flood_of_logins_leaves_the_database_to_everyone_else(tmp_path: Path) -> None:
    """Twice as many logins at once as the database takes reads in flight: the logins beyond the
    password check's own bound are refused at once, before they read anything, and the other users'
    requests sent among them are all answered."""
    from station.service.db import MAX_READS_IN_FLIGHT
    from tests.station_support import CAPPED_SPEEDUP, IDLE_SPEEDUP, app_in_process, asgi_client

    async def go() -> None:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (_, c):
            anon = asgi_client(c._transport.app, token=False)  # type: ignore[attr-defined]
            floods = [anon.post("/login", json={"name": f"user{i}", "password": "guess-guess-1"})
                      for i in range(2 * MAX_READS_IN_FLIGHT)]
            mine = [c.get("/runs") for _ in range(4)]
            answers = await asyncio.gather(*floods, *mine)
            await anon.aclose()
        assert [r.status_code for r in answers[len(floods):]] == [200] * len(mine), answers[-1].text
        statuses = {r.status_code for r in answers[:len(floods)]}
        assert statuses <= {401, 429}, statuses
        assert any("too many logins at once" in r.text for r in answers[:len(floods)])
    asyncio.run(go())


@pytest.mark.slow
def test_every_kind_of_name_costs_one_password_check(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Unknown, known (wrong password), disabled and password-less names: one scrypt each, so no
    name can be told from another by the time a refusal takes (the measured medians are in
    docs/operations.md)."""
    from station.lab import users

    store = Store(tmp_path / "s.db")
    users.put_user(store, "tina", users.Role.TECHNICIAN, "admin", password="tina-secret-pw")
    users.put_user(store, "dora", users.Role.TECHNICIAN, "admin", password="dora-secret-pw", disabled=True)
    users.put_user(store, "tok", users.Role.TECHNICIAN, "admin")
    users.login_candidate(store, "nobody")  # the dummy hash made once
    calls = _count_scrypt(monkeypatch)
    for name in ("nobody", "tina", "dora", "tok", "Tina-Secret-PW!"):
        calls.clear()
        assert users.check_login(store, name, "wrong-password-1") is None
        assert len(calls) == 1, name
    calls.clear()
    assert users.check_login(store, "tina", "tina-secret-pw") is not None and len(calls) == 1
    store.close()


def test_the_password_pool_refuses_at_once_when_full() -> None:
    import threading

    from station.service.logins import PasswordPool

    async def login(pool: PasswordPool, fn: object, *args: object) -> object:  # as the lab logs in
        async with pool.admitted() as ok:
            return await pool.check(fn, *args) if ok else None

    async def go() -> None:
        pool = PasswordPool(workers=1, queue=0)
        gate = threading.Event()
        busy = asyncio.ensure_future(login(pool, gate.wait, 5.0))
        await asyncio.sleep(0.05)
        assert pool.full() and await login(pool, lambda: True) is None  # refused at once, not queued
        gate.set()
        assert await busy is True and await login(pool, lambda: True) is True
        pool.close()
    asyncio.run(go())


@pytest.mark.slow
def test_guessing_locks_out_the_name_and_the_address_until_lifted(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """Five wrong passwords, then each further one locks the name and the address out for a
    growing time (the right password is refused meanwhile, after the same password check and the same
    audited refusal as any other login); the lock-out is
    audited and listed for an administrator, who lifts it; a locked login costs the same one
    password check as any other.  A password typed into the name field
    never reaches the trail; a new password ends the user's sessions; tokens are listed and revoked."""
    from station.service import logins
    from tests.station_support import CAPPED_SPEEDUP, IDLE_SPEEDUP, PASSWORDS, app_in_process, asgi_client, login

    async def go() -> None:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP,
                                  idle_speedup=IDLE_SPEEDUP) as (manager, c):
            app = c._transport.app  # type: ignore[attr-defined]
            r = await c.put("/users/tina", json={"role": "technician", "password": PASSWORDS["tina"]})
            assert r.status_code == 200
            anon = asgi_client(app, token=False)
            for _ in range(logins.FREE_FAILURES):
                r = await anon.post("/login", json={"name": "tina", "password": "not-her-password"})
                assert r.status_code == 401 and "wrong user name or password" in r.json()["detail"]
            r = await anon.post("/login", json={"name": "tina", "password": "not-her-password"})
            assert r.status_code == 401
            calls = _count_scrypt(monkeypatch)
            r = await anon.post("/login", json={"name": "tina", "password": PASSWORDS["tina"]})
            assert r.status_code == 401 and "locked until" in r.json()["detail"]
            assert len(calls) == 1  # the same password check as any login: a lock-out is not told by its time
            monkeypatch.undo()
            # and the same write: each refusal, the locked one too, is in the trail before its answer
            refused = audit.entries(manager.store, action=audit.LOGIN_REFUSED, target="user:tina")
            assert len(refused) == logins.FREE_FAILURES + 2 and refused[0].details.get("locked") is True
            assert not any(e.details.get("locked") for e in refused[1:])
            locks = (await c.get("/logins/locks")).json()
            assert {x["key"] for x in locks} == {"user:tina", "client:127.0.0.1"}
            assert audit.entries(manager.store, action=audit.LOGIN_LOCKED)
            for x in locks:
                assert (await c.delete(f"/logins/locks/{x['key']}")).status_code == 200
            tina = await login(app, "tina")
            assert (await tina.get("/me")).json()["user"]["name"] == "tina"
            # a password typed into the name field
            r = await anon.post("/login", json={"name": "Sup3r Secret!", "password": "x"})
            assert r.status_code in (401, 422)
            assert "Sup3r" not in str([e.to_dict() for e in audit.entries(manager.store, limit=1000)])
            # a new password ends her sessions
            r = await c.put("/users/tina", json={"role": "technician", "password": "a-new-password-1"})
            assert r.status_code == 200
            assert (await tina.get("/me")).status_code == 401
            # tokens: listed (never their text), revoked, refused after
            text = (await c.post("/users/tina/tokens", json={"label": "ci"})).json()["token"]
            bot = asgi_client(app, token=False)
            bot.headers["Authorization"] = f"Bearer {text}"
            assert (await bot.get("/me")).json()["user"]["name"] == "tina"
            [row] = [t for t in (await c.get("/tokens", params={"user": "tina"})).json() if t["label"] == "ci"]
            assert text not in str(row) and row["revoked"] is None
            assert (await c.delete(f"/tokens/{row['id']}")).status_code == 200
            assert (await bot.get("/me")).status_code == 401
            assert audit.entries(manager.store, action=audit.TOKEN_REVOKED)[0].details["token"] == row["id"]
            for cl in (anon, tina, bot):
                await cl.aclose()
    asyncio.run(go())


def test_the_command_line_lists_and_revokes_tokens(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    import json

    import yaml

    from station.cli import main
    from station.lab import users
    from tests.station_support import daemon_config

    cfg = tmp_path / "station.yaml"
    cfg.write_text(yaml.safe_dump(daemon_config(tmp_path / "rec")))
    monkeypatch.setenv("STATION_PASSWORD", "bot-secret-password")
    assert main(["users", "add", "bot", "--role", "technician", "--config", str(cfg)]) == 0
    assert main(["users", "token", "bot", "--label", "nightly", "--config", str(cfg), "--json"]) == 0
    text = json.loads(capsys.readouterr().out.split("\n", 1)[1])["token"]
    assert main(["users", "tokens", "bot", "--config", str(cfg), "--json"]) == 0
    [row] = json.loads(capsys.readouterr().out)
    assert text not in json.dumps(row) and row["revoked"] is None
    assert main(["users", "revoke", row["id"], "--config", str(cfg)]) == 0
    assert main(["users", "revoke", row["id"], "--config", str(cfg)]) == 1  # no live token with that id
    store = Store(tmp_path / "rec" / "station.db")
    assert users.user_of_token(store, text) is None
    store.close()


# ---------------------------------------------------------------------------------------------- the lab's tables
def _sql(path: Path, *stmts: str) -> None:
    """What an insider with the database file does to a table the station keeps (no trigger there)."""
    db = sqlite3.connect(path)
    for s in stmts:
        db.execute(s)
    db.commit()
    db.close()


@pytest.mark.parametrize(("stmt", "words"), [
    ("UPDATE transducer_policy SET check_standard = 0", "transducer_policy TX-CHECK-1: check_standard changed"),
    ("UPDATE transducer_policy SET tolerances_json = '{\"S\": 0.5}'", "tolerances changed"),
    ("UPDATE transducer_policy SET updated_by = 'mallory'", "updated_by changed"),
    ("DELETE FROM transducer_policy", "transducer_policy TX-CHECK-1: deleted outside the station"),
    ("UPDATE as_left SET value = value * 1.01", "as_left run001/S: value changed"),
    ("DELETE FROM as_left", "as_left run001/S: deleted outside the station"),
    ("INSERT INTO as_left SELECT 'run002', transducer_id, 'k_f', 1.0, 'N/m', '', at, by FROM as_left",
     "as_left run002/k_f: not in the audit trail"),
    ("UPDATE as_left SET transducer_id = 'OTHER'", "as_left run001/S: transducer_id changed"),
])
def test_policies_and_adjustments_changed_outside_the_station_are_refused(tmp_path: Path, stmt: str,
                                                                         words: str) -> None:
    """The chain vouches for every row of transducer_policy and as_left: an edit with sqlite3 is
    refused by the reads (the history, the check transducers) and named by the integrity check; the
    next change through the station records what it found and overwrote."""
    from station.lab import policy
    from tests.history_support import TX, add_runs, add_transducer

    store = Store(tmp_path / "s.db")
    add_transducer(store)
    ids = add_runs(store, tmp_path, 3)
    policy.put_policy(store, policy.Policy(TX, {"S": 0.005}, 365.0, True), "ada")
    policy.record_as_left(store, policy.AsLeft(ids[1], TX, "S", 2.001e-3, "V/N", "gain set", 1.8e9, "anton"))
    with store.reading() as db:
        assert policy.record_mismatches(db) == [] and chain.verify_chain(db).ok
    assert policy.check_transducers(store) == [TX] and policy.as_left_of(store, TX)[ids[1]]["S"].value == 2.001e-3
    store.close()

    _sql(tmp_path / "s.db", stmt)
    store = Store(tmp_path / "s.db")
    with store.reading() as db:
        found = policy.record_mismatches(db)
        report = chain.integrity_report(chain.verify_chain(db), {}, tmp_path, found)
    assert len(found) == 1 and words in found[0], found
    assert report["chain_ok"] and not report["ok"] and words in report["detail"]
    with pytest.raises(policy.RecordTamperedError, match=words.split(":")[0]):
        if "as_left" in stmt:
            policy.as_left_of(store, TX)
        else:
            policy.check_transducers(store)
    if "transducer_policy" in stmt:
        with pytest.raises(policy.RecordTamperedError, match=r"changed outside|deleted outside"):
            policy.policy(store, TX)
        # the administrator sets the policy again: the entry says what was found and overwritten
        policy.put_policy(store, policy.Policy(TX, {"S": 0.005}, 365.0, True), "ada")
        e = audit.entries(store, action=policy.POLICY_CHANGED)[0]
        assert e.details["found_changed_outside"] == found
        assert policy.policy(store, TX).check_standard
        with store.reading() as db:
            assert policy.record_mismatches(db) == []
    store.close()


def test_a_lock_out_outlives_a_restart_and_its_doubling_goes_on(tmp_path: Path) -> None:
    """A lock-out is kept in the database and loaded by the next daemon: still in force, and the
    next failure after it runs out doubles it as before; lifting it forgets it there too.  Counts
    below the first lock-out are not kept."""
    from station.lab import users
    from station.service.logins import BASE_LOCK_S, FREE_FAILURES, LoginThrottle

    store = Store(tmp_path / "s.db")
    now = [1000.0]

    def throttle() -> LoginThrottle:
        t = LoginThrottle(clock=lambda: now[0], save=lambda k, n, u: users.keep_lock(store, k, n, u))
        t.load(users.kept_locks(store))
        return t

    t = throttle()
    for _ in range(FREE_FAILURES):
        assert t.failed(["user:tina", "user:other"]) == []
    t.succeeded("user:other")
    assert users.kept_locks(store) == []  # nothing kept below the first lock-out
    assert t.failed(["user:tina"]) == [("user:tina", BASE_LOCK_S)]
    assert users.kept_locks(store) == [("user:tina", FREE_FAILURES + 1, now[0] + BASE_LOCK_S)]
    t = throttle()  # the daemon restarted
    assert t.refusal(["user:tina"]) is not None and [x["key"] for x in t.locks()] == ["user:tina"]
    now[0] += BASE_LOCK_S + 0.1
    assert t.refusal(["user:tina"]) is None
    assert t.failed(["user:tina"]) == [("user:tina", 2 * BASE_LOCK_S)]
    assert throttle().refusal(["user:tina"]) is not None
    assert t.lift("user:tina") and users.kept_locks(store) == []
    store.close()


@pytest.mark.slow
def test_each_user_lists_and_revokes_their_own_tokens_and_an_admin_all(tmp_path: Path) -> None:
    from tests.station_support import CAPPED_SPEEDUP, IDLE_SPEEDUP, PASSWORDS, app_in_process, login

    async def go() -> None:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (_, c):
            app = c._transport.app  # type: ignore[attr-defined]
            for name, role in (("tina", "technician"), ("anton", "approver")):
                assert (await c.put(f"/users/{name}", json={"role": role, "password": PASSWORDS[name]})).status_code \
                    == 200
                assert (await c.post(f"/users/{name}/tokens", json={"label": f"{name}-ci"})).status_code == 201
            tina = await login(app, "tina")
            mine = (await tina.get("/tokens")).json()
            assert [(t["user"], t["label"]) for t in mine] == [("tina", "tina-ci")]
            assert (await tina.get("/tokens", params={"user": "anton"})).status_code == 403
            every = (await c.get("/tokens")).json()
            assert {t["user"] for t in every} >= {"tina", "anton"}
            [anton_token] = [t["id"] for t in every if t["user"] == "anton"]
            r = await tina.delete(f"/tokens/{anton_token}")
            assert r.status_code == 404 and "of user tina" in r.json()["detail"]
            assert (await tina.delete(f"/tokens/{mine[0]['id']}")).status_code == 200
            assert (await tina.get("/tokens")).json()[0]["revoked"] is not None
            assert (await c.get("/tokens", params={"user": "anton"})).json()[0]["revoked"] is None
            await tina.aclose()
    asyncio.run(go())


def test_station_verify_passes_on_a_clean_station_and_names_a_row_edited_outside(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import yaml

    from station.cli import main
    from station.lab import policy
    from tests.history_support import TX, add_runs, add_transducer
    from tests.station_support import daemon_config

    cfg = tmp_path / "station.yaml"
    cfg.write_text(yaml.safe_dump(daemon_config(tmp_path / "rec")))
    (tmp_path / "rec").mkdir()
    store = Store(tmp_path / "rec" / "station.db")
    add_transducer(store)
    ids = add_runs(store, tmp_path / "rec", 3)
    policy.put_policy(store, policy.Policy(TX, {"S": 0.005}, 365.0, True), "ada")
    policy.record_as_left(store, policy.AsLeft(ids[2], TX, "S", 2.001e-3, "V/N", "gain set", 1.9e9, "anton"))
    store.close()
    assert main(["verify", "--config", str(cfg)]) == 0
    out = capsys.readouterr().out
    assert "audit chain intact" in out and out.rstrip().endswith("OK")
    _sql(tmp_path / "rec" / "station.db", "UPDATE as_left SET note = 'set by nobody'")
    assert main(["verify", "--config", str(cfg)]) == 1
    out = capsys.readouterr().out
    assert "audit chain intact" in out and f"row as_left {ids[2]}/S: note changed" in out and "FAILED" in out
