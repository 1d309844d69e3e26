"""Benchmark of the daemon's logins as a guesser meets them; prints JSON.

A real daemon (``station serve --sim`` in a subprocess, loopback) with four kinds of name:

1. **Login time per kind of name** (median and quartiles over ``--rounds`` rounds, the kinds
   interleaved so that the machine's load falls on all alike): a known user with the right
   password, the same with a wrong one, an unknown name, a disabled user, a password-less user and
   a locked-out user.  ``spread`` is (largest median - smallest) / smallest: the aim is <= 0.10, so
   that no kind of name can be told from another by the time a refusal takes.  Between timed
   logins the administrator lifts every lock-out but the locked user's (untimed).
2. **Lock-out threshold**: wrong passwords for one name until the first "locked" refusal.
3. **Guesses per second allowed**: one name guessed as fast as one client can for ``--guess-s``
   seconds: how many guesses were answered in that time (``guesses_answered``: the answers that
   were not a lock-out refusal, which says nothing of the password), and the guesses in the first
   hour the schedule allows (free failures, then one per
   lock-out, 2 s doubling to 15 min).  ``server_guesses_per_s`` is what the password check alone
   would allow without a lock-out (1 / the median of a refused login).

Usage: python bench/login.py [--rounds 25] [--guess-s 20]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from station.service import logins  # noqa: E402

TOKEN = "bench-token-0123456789"
USERS = {"tina": ("technician", "tina-secret-pw", False), "dora": ("technician", "dora-secret-pw", True),
         "tok": ("technician", None, False), "lotte": ("technician", "lotte-secret-pw", False)}
KINDS = {"right_password": ("tina", "tina-secret-pw"), "wrong_password": ("tina", "wrong-password-1"),
         "unknown": ("nobody", "wrong-password-1"), "disabled": ("dora", "wrong-password-1"),
         "password_less": ("tok", "wrong-password-1"), "locked": ("lotte", "lotte-secret-pw")}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def daemon(tmp: Path) -> Any:
    d = yaml.safe_load((ROOT / "config" / "sim-5kN.yaml").read_text())
    d["station"]["recordings_dir"] = str(tmp / "recordings")
    cfg = tmp / "station.yaml"
    cfg.write_text(yaml.safe_dump(d))
    port = _free_port()
    logf = (tmp / "daemon.log").open("wb")
    proc = subprocess.Popen([sys.executable, "-m", "station.cli", "serve", "--sim", "--config", str(cfg),
                             "--port", str(port)], stdout=logf, stderr=subprocess.STDOUT,
                            env={**os.environ, "STATION_TOKEN": TOKEN}, cwd=tmp)
    admin = httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {TOKEN}"},
                         timeout=60)
    try:
        deadline = time.monotonic() + 240  # a loaded machine starts it slowly
        while True:
            with contextlib.suppress(httpx.TransportError):
                if admin.get("/health").status_code == 200:
                    break
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError("daemon did not start: " + (tmp / "daemon.log").read_text()[-3000:])
            time.sleep(0.1)
        yield admin
    finally:
        admin.close()
        proc.terminate()
        proc.wait(60)
        logf.close()


def lift_all(admin: httpx.Client, keep: str = "") -> None:
    """Lift every lock-out but ``keep``'s, and forget the loopback address's failure count (every
    login here comes from it)."""
    keys = {x["key"] for x in admin.get("/logins/locks").json()} | {"client:127.0.0.1"}
    for key in keys - {keep}:
        admin.delete(f"/logins/locks/{key}")  # 404 when there is nothing to lift


def attempt(c: httpx.Client, name: str, password: str) -> tuple[float, httpx.Response]:
    t0 = time.perf_counter()
    r = c.post("/login", json={"name": name, "password": password})
    return time.perf_counter() - t0, r


def lock(admin: httpx.Client, c: httpx.Client, name: str) -> int:
    """Wrong passwords for ``name`` until it is locked out; returns the failures it took."""
    n = 0
    while True:
        _, r = attempt(c, name, "wrong-password-1")
        if "for this user: locked until" in r.json().get("detail", ""):
            return n
        n += 1
        lift_all(admin, keep=f"user:{name}")  # only the name's own count matters here


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=25)
    ap.add_argument("--guess-s", type=float, default=20.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp, daemon(Path(tmp)) as admin:
        for name, (role, pw, disabled) in USERS.items():
            body: dict[str, Any] = {"role": role, "disabled": disabled}
            if pw is not None:
                body["password"] = pw
            admin.put(f"/users/{name}", json=body).raise_for_status()
        c = httpx.Client(base_url=str(admin.base_url), timeout=60)
        attempt(c, "nobody", "warm-up-password")  # the hash nobody has is made once, on first use
        lift_all(admin)
        threshold = lock(admin, c, "lotte")
        times: dict[str, list[float]] = {k: [] for k in KINDS}
        for _ in range(args.rounds):
            for kind, (name, pw) in KINDS.items():
                lift_all(admin, keep="user:lotte")
                if kind == "locked" and not admin.get("/logins/locks").json():
                    lock(admin, c, "lotte")  # the lock-out ran out: locked again (untimed)
                dt, r = attempt(c, name, pw)
                locked = "locked until" in r.json().get("detail", "")
                if (kind == "right_password") != (r.status_code == 200) or (kind == "locked") != locked:
                    raise RuntimeError(f"{kind}: unexpected answer {r.status_code} {r.text}")
                times[kind].append(dt * 1e3)
                if kind == "right_password":
                    c.cookies.clear()
        med = {k: statistics.median(v) for k, v in times.items()}
        q = {k: [round(x, 1) for x in statistics.quantiles(v, n=4)] for k, v in times.items()}
        # guessing one name as fast as one client can (lock-outs are not lifted now)
        lift_all(admin)
        admin.delete("/logins/locks/user:tina")
        answered = total = 0
        t_end = time.monotonic() + args.guess_s
        while time.monotonic() < t_end:
            _, r = attempt(c, "tina", f"guess-{total}")
            total += 1
            answered += "locked until" not in r.json().get("detail", "")
        lift_all(admin)
        c.close()
    per_hour, t, fails = logins.FREE_FAILURES, 0.0, logins.FREE_FAILURES
    while True:  # the schedule: free failures at once, then one guess per lock-out's end
        fails += 1
        t += min(logins.MAX_LOCK_S, logins.BASE_LOCK_S * 2 ** (fails - logins.FREE_FAILURES - 1))
        if t > 3600:
            break
        per_hour += 1
    out = {
        "login_median_ms": {k: round(v, 1) for k, v in med.items()},
        "login_quartiles_ms": q,
        "spread": round((max(med.values()) - min(med.values())) / min(med.values()), 3),
        "spread_refusals": round((max(v for k, v in med.items() if k != "right_password")
                                  - min(v for k, v in med.items() if k != "right_password"))
                                 / min(v for k, v in med.items() if k != "right_password"), 3),
        "rounds": args.rounds,
        "lockout_after_failures": threshold,
        "guess_seconds": args.guess_s, "guess_attempts": total, "guesses_answered": answered,
        "guesses_per_s_allowed": round(answered / args.guess_s, 3),
        "guesses_first_hour_allowed": per_hour + 1,
        "server_guesses_per_s_without_lockout": round(1e3 / med["wrong_password"], 1),
        "load_average": [round(x, 1) for x in os.getloadavg()], "cpus": os.cpu_count(),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
