"""Backup while a run records, restore into an empty folder: the same runs, every closed recording
reads and matches its stored SHA-256, every issued certificate reads with its hashes; a damaged or
partial backup, or a folder that is not empty, is refused and nothing is written.

The daemon's app runs in-process (the simulated rig on a virtual clock); the backup runs in a thread
beside the run, as the command would beside the daemon."""

from __future__ import annotations

import asyncio
import json
import sqlite3
from pathlib import Path
from typing import Any

import pytest

from station.backup import MANIFEST, BackupError, backup, check_backup, restore
from station.certificate.issue import issue
from station.cli import main
from station.lab.integrity import sha256_file
from station.lab.issued import FOLDER, read_issued
from station.recording import read_recording
from tests.station_support import (
    CAPPED_SPEEDUP,
    IDLE_SPEEDUP,
    Seed,
    asgi_client,
    daemon_config,
    run_body,
    running_app,
    seed_runs,
)

# a simulated, identified run seeded, one recorded on the virtual clock (~10 s)
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("backup")]


class Roles:
    def role_of(self, name: str) -> str | None:
        return {"tina": "technician", "anton": "approver"}.get(name)


def _runs(db: Path) -> dict[str, tuple[str, str | None, str | None]]:
    con = sqlite3.connect(db)
    try:
        return {r[0]: (r[1], r[2], r[3]) for r in
                con.execute("SELECT id, state, recording, recording_sha256 FROM runs")}
    finally:
        con.close()


@pytest.fixture(scope="module")
def backed_up(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Any, str]:
    """(the station's recordings folder, its backup taken while a run recorded, the backup's report,
    the number of the certificate issued before)."""
    tmp = tmp_path_factory.mktemp("backup")
    rec = tmp / "recordings"
    cfg = daemon_config(rec)
    cfg["plan"]["record_s"] = 5.0  # long in virtual time: the backup catches the run recording
    [rid] = seed_runs(cfg, [Seed()])
    number = issue(rec / f"{rid}.h5", prepared_by="tina", approver="anton", roles=Roles()).number
    dest = tmp / "backup"

    async def go() -> Any:
        # no identification worker: the run ends its acquisition (closes its recording) at "identifying";
        # what a backup must leave untouched is the recording, not the identification that follows it
        async with running_app(rec, config=cfg, workers=0, max_speedup=CAPPED_SPEEDUP,
                               idle_speedup=IDLE_SPEEDUP) as app, asgi_client(app) as c:
            r = await c.post("/runs", json=run_body(record_s=5.0))
            assert r.status_code == 202, r.text
            run = r.json()["id"]
            for _ in range(2000):
                st = (await c.get(f"/runs/{run}")).json()
                if st["state"] == "running" and st["samples"] > 0:
                    break
                await asyncio.sleep(0.005)
            assert st["state"] == "running", st
            report = await asyncio.to_thread(backup, rec, rec / "station.db", dest)
            for _ in range(4000):  # the run goes on, untouched by the backup
                if (await c.get(f"/runs/{run}")).json()["state"] in ("identifying", "failed", "aborted"):
                    break
                await asyncio.sleep(0.01)
            done = (await c.get(f"/runs/{run}")).json()
            assert done["state"] == "identifying" and done["step_state"] == "done", done
            return report
    return rec, dest, asyncio.run(go()), number


def test_a_backup_taken_during_a_run_restores_the_same_state(backed_up: tuple[Path, Path, Any, str],
                                                              tmp_path: Path) -> None:
    _, dest, report, number = backed_up
    assert report.in_progress and all(p.endswith(".partial") for p in report.in_progress)  # the run recording
    manifest = json.loads((dest / MANIFEST).read_text())
    assert "station.db" in manifest["files"] and any(k.startswith(f"data/{FOLDER}/") for k in manifest["files"])
    target = tmp_path / "restored"
    assert main(["restore", str(dest), "--into", str(target)]) == 0
    before = _runs(dest / "station.db")
    after = _runs(target / "station.db")
    assert after == before and len(after) == 2
    completed = [(rid, name, sha) for rid, (state, name, sha) in after.items() if state == "completed"]
    assert completed
    for _, name, sha in completed:  # every closed recording reads, and is the file the station closed
        assert name is not None and read_recording(target / name).steps
        assert sha256_file(target / name) == sha
    it = read_issued(target / FOLDER, number)  # its hashes checked
    assert it.record["content"] and it.path("pdf").exists()


def test_a_damaged_or_partial_backup_or_a_full_folder_is_refused(backed_up: tuple[Path, Path, Any, str],
                                                                 tmp_path: Path) -> None:
    import shutil

    _, dest, _, number = backed_up
    bad = tmp_path / "bad"
    shutil.copytree(dest, bad)
    pdf = bad / "data" / FOLDER / f"{number}.pdf"
    data = bytearray(pdf.read_bytes())
    data[len(data) // 2] ^= 0xFF
    pdf.write_bytes(bytes(data))
    with pytest.raises(BackupError, match=rf"damaged or partial: data/{FOLDER}/{number}.pdf: altered"):
        restore(bad, tmp_path / "r1")
    assert not (tmp_path / "r1").exists()
    pdf.unlink()
    with pytest.raises(BackupError, match=rf"data/{FOLDER}/{number}.pdf: missing"):
        check_backup(bad)
    (bad / MANIFEST).unlink()
    with pytest.raises(BackupError, match="partial"):
        restore(bad, tmp_path / "r2")
    assert main(["restore", str(bad), "--into", str(tmp_path / "r3")]) != 0 and not (tmp_path / "r3").exists()
    full = tmp_path / "full"
    full.mkdir()
    (full / "something.h5").write_bytes(b"x")
    with pytest.raises(BackupError, match="not empty"):
        restore(dest, full)
    assert [p.name for p in full.iterdir()] == ["something.h5"]
    with pytest.raises(BackupError, match="not empty"):
        backup(dest, dest / "station.db", full)


def test_a_recording_archive_holds_its_results_and_certificates_with_hashes(
        backed_up: tuple[Path, Path, Any, str]) -> None:
    import hashlib
    import io
    import zipfile

    from station.recording.archive import recording_archive

    rec, _, _, number = backed_up
    it = read_issued(rec / FOLDER, number)
    recording = rec / it.record["recording"]
    with zipfile.ZipFile(io.BytesIO(recording_archive(recording))) as z:
        manifest = json.loads(z.read("MANIFEST.json"))
        names = set(z.namelist()) - {"MANIFEST.json"}
        assert names == set(manifest["files"])
        for name in names:  # each file as the manifest states it, and as it is on the station
            data = z.read(name)
            assert hashlib.sha256(data).hexdigest() == manifest["files"][name]["sha256"], name
        assert z.read(recording.name) == recording.read_bytes()
    assert {f"{FOLDER}/{number}.{ext}" for ext in ("json", "pdf", "html", "xml")} <= names
    assert any(n.startswith(f"{recording.stem}.results/") for n in names)
    assert not any(n.startswith(f"{FOLDER}/") and number not in n for n in names)  # only this run's certificate
