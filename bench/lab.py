"""Benchmark of the lab's bookkeeping; prints JSON.

1. Password hashing (scrypt, n=2^14, r=8, p=1): median time of one hash and one check.
2. The database (a real SQLite file in WAL mode, the daemon's Store): median time to append one
   audit entry (its own transaction), to read the newest 200 entries from a trail of ``--entries``,
   to look up a session and an API token, to build a run's setup from the register.
3. SHA-256 of a recording: MB/s over a file of ``--mb`` MiB (what closing a run and checking it
   before a report or certificate costs).
4. Upgrading the previous release's database (tests/data/station-v2.db copied, then opened).

Usage: python bench/lab.py [--entries 20000] [--mb 64] [--repeat 20]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any


def median_s(fn: Callable[[], Any], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--entries", type=int, default=20_000)
    ap.add_argument("--mb", type=int, default=64)
    ap.add_argument("--repeat", type=int, default=20)
    a = ap.parse_args()

    from station.config import default_config_path, load_config
    from station.lab import audit, register, users
    from station.lab.integrity import sha256_file
    from station.lab.store import Store

    out: dict[str, Any] = {}
    hashed = users.hash_password("a-password-of-some-length")
    out["scrypt_hash_ms"] = round(1e3 * median_s(lambda: users.hash_password("a-password-of-some-length"), 5), 1)
    out["scrypt_check_ms"] = round(1e3 * median_s(lambda: users.check_password("a-password-of-some-length", hashed),
                                                  5), 1)
    with tempfile.TemporaryDirectory() as tmp:
        store = Store(Path(tmp) / "station.db")
        cfg = load_config(default_config_path())
        register.seed(store, cfg)
        with store.transaction() as db:
            for i in range(a.entries):
                audit.record(db, "tina", audit.RUN_STARTED, f"run-{i}", {"steps": [[10.0, 0.001]]})
        out["audit_entries"] = a.entries
        out["audit_append_ms"] = round(1e3 * median_s(lambda: audit.append(store, "tina", audit.RUN_ABORTED, "r"),
                                                      a.repeat), 2)
        out["audit_read_200_ms"] = round(1e3 * median_s(lambda: audit.entries(store, limit=200), a.repeat), 2)
        out["audit_read_target_ms"] = round(1e3 * median_s(lambda: audit.entries(store, target="run-123"),
                                                           a.repeat), 2)
        users.put_user(store, "tina", users.Role.TECHNICIAN, "bench", password="tina-secret-pw")
        text, _, _ = users.login(store, "tina", "tina-secret-pw", 60)
        token = users.issue_token(store, "tina", "bench", "bench")
        out["session_lookup_ms"] = round(1e3 * median_s(lambda: users.session_user(store, text), a.repeat), 3)
        out["token_lookup_ms"] = round(1e3 * median_s(lambda: users.user_of_token(store, token), a.repeat), 3)
        out["run_setup_ms"] = round(1e3 * median_s(
            lambda: register.run_setup(store, cfg, cfg.transducer.id, None), a.repeat), 3)
        store.close()
        big = Path(tmp) / "rec.h5"
        with open(big, "wb") as f:
            f.write(os.urandom(a.mb * 2**20))
        t = median_s(lambda: sha256_file(big), 3)
        out["sha256_MB_per_s"] = round(a.mb * 2**20 / 1e6 / t)
        out["sha256_64MiB_s"] = round(t * 64 / a.mb, 3)
        old = Path(__file__).resolve().parents[1] / "tests" / "data" / "station-v2.db"
        dst = Path(tmp) / "old" / "station.db"
        dst.parent.mkdir()
        shutil.copy(old, dst)
        t0 = time.perf_counter()
        s2 = Store(dst)
        out["upgrade_v2_ms"] = round(1e3 * (time.perf_counter() - t0), 1)
        out["upgrade_runs_kept"] = len(s2.list_runs())
        s2.close()
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
