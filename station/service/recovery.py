"""Start-up recovery: runs cut off by the end of the previous daemon become ``interrupted`` (their
partial recordings recovered into readable files), runs that had ended get their final state, jobs
left running go back to the queue (or fail after ``max_attempts``)."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from station.lab import audit
from station.lab.integrity import sha256_file
from station.lab.store import ACTIVE_STATES, Store
from station.recording import read_recording, recover_partial

log = logging.getLogger(__name__)


def recover(store: Store, recordings_dir: Path, max_attempts: int) -> dict[str, list[str]]:
    """Bring the database in line with the recordings after a restart; returns what was done."""
    out: dict[str, list[str]] = {"interrupted": [], "ended": [], "identifying": [], "requeued": [],
                                 "failed_jobs": []}
    for row in store.list_runs(states=ACTIVE_STATES, limit=1_000_000):
        name, status, file_reason = recover_recording(recordings_dir, row.id)
        if name is not None and name.endswith(".h5"):
            _hash_into_chain(store, recordings_dir / name, row.id, status)
        if status in ("aborted", "failed"):  # the run had ended; the daemon died before noting it
            store.update_run(row.id, state=status, recording=name, reason=file_reason, message=file_reason,
                             ended=time.time())
            out["ended"].append(row.id)
            continue
        if status == "completed":  # the run ended, the daemon died before recording it
            store.update_run(row.id, state="identifying", recording=name,
                             message="acquisition completed; identification queued after a restart")
            store.enqueue_job(row.id)
            out["identifying"].append(row.id)
            continue
        reason = "the station daemon stopped during the run" + ("" if name else "; no recording was written")
        store.update_run(row.id, state="interrupted", recording=name, reason=reason, ended=time.time(),
                         message=reason)
        out["interrupted"].append(row.id)
    requeued, failed = store.requeue_running_jobs(max_attempts)
    out["requeued"] = [j.run_id for j in requeued]
    for j in failed:
        store.update_run(j.run_id, state="failed", ended=time.time(),
                         reason=f"identification stopped {j.attempts} times; not retried")
        out["failed_jobs"].append(j.run_id)
    pending = {j.run_id for j in store.jobs(states=("queued", "running"))}
    for row in store.list_runs(states=("identifying",), limit=1_000_000):
        if row.id not in pending:
            store.enqueue_job(row.id)
            out["requeued"].append(row.id)
    if any(out.values()):
        log.info("start-up recovery: %s", json.dumps(out))
    return out


def _hash_into_chain(store: Store, path: Path, run_id: str, status: str | None) -> None:
    """A recording closed without the daemon (recovered from its partial file, or closed as the
    daemon died): its SHA-256 stored with the run and in the audit chain, like any closed one."""
    try:
        sha = sha256_file(path)
    except OSError as exc:
        log.error("run %s: recovered recording %s not hashed (%s)", run_id, path.name, exc)
        return
    store.update_run(run_id, recording_sha256=sha)
    audit.append(store, audit.SYSTEM, audit.RECORDING_RECOVERED, run_id,
                 {"recording": path.name, "sha256": sha, "exit_status": status}, files={path.name: sha})


def recover_recording(recordings_dir: Path, run_id: str) -> tuple[str | None, str | None, str]:
    """(file name, exit status, reason) of a run's recording, a partial file recovered first."""
    final, partial = recordings_dir / f"{run_id}.h5", recordings_dir / f"{run_id}.h5.partial"
    if partial.exists() and not final.exists():
        try:
            recover_partial(partial)
        except Exception as exc:
            log.error("run %s: the partial recording cannot be recovered: %s", run_id, exc)
            return partial.name, None, ""
    if final.exists():
        try:
            rec = read_recording(final)
            return final.name, rec.exit_status, rec.reason
        except Exception as exc:
            log.error("run %s: recording unreadable: %s", run_id, exc)
            return final.name, None, ""
    return None, None, ""
