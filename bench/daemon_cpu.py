"""CPU a daemon start costs, per process; prints JSON.

The tests' daemon (``tests.station_support.Daemon``: ``station serve --sim``, the tests' short
configuration) is started ``--starts`` times; for each start, every process of its tree (the web
process, the rig process ``station.rigproc`` and its stream process, the emulators ``drivers.sim``,
the identification and render workers) is read from /proc: user+system CPU seconds when ``/health``
first answers, and again after ``--idle-s`` seconds of idling.  Then, with ``--run``, one short run
is made and identified, and the tree's CPU read again (the workers' start is in it).  Printed: per
start and per process role the CPU (s) at ready and after the idle time, the sums, and the medians
over the starts.

CPU seconds, not wall time: on a loaded machine the wall time to ready varies, the CPU a start
costs much less.

Usage: python bench/daemon_cpu.py [--starts 3] [--idle-s 5] [--workers 1] [--run]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.station_support import Daemon  # noqa: E402

TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")


def _tree(pid: int) -> list[int]:
    """``pid`` and its descendants (Linux: /proc/PID/task/*/children)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            continue
    return out


def role(pid: int) -> str:
    """Which of the daemon's processes ``pid`` is, by its command line."""
    cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    for word, name in (("station.rigproc.streamproc", "stream"), ("station.rigproc", "rig"),
                       ("drivers.sim", "emulator"), ("multiprocessing", "worker"), ("station.cli", "web")):
        if word in cmd:
            return name
    return "other"  # the orphan guard (setpriv) before it execs the daemon


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (its own threads, not its children)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) * TICK_S  # utime, stime (fields 14 and 15 of stat)


def tree_cpu(root: int) -> dict[str, float]:
    """CPU seconds (user + system) of every process under ``root`` (itself included), summed by role."""
    out: dict[str, float] = {}
    for p in _tree(root):
        try:
            r, c = role(p), cpu_s(p)
        except OSError:
            continue
        out[r] = round(out.get(r, 0.0) + c, 3)
    out["total"] = round(sum(out.values()), 3)
    return out


def one_start(tmp: Path, idle_s: float, workers: int, run: bool) -> dict[str, Any]:
    d = Daemon(tmp, workers=workers)
    t0 = time.monotonic()
    d.start(timeout_s=240)
    wall = time.monotonic() - t0
    assert d.proc is not None
    root = d.proc.pid
    try:
        ready = tree_cpu(root)
        time.sleep(idle_s)
        idle = tree_cpu(root)
        after_run = None
        if run:
            rid = d.start_run()
            d.wait_state(rid, ("completed",), timeout_s=120)
            after_run = tree_cpu(root)
    finally:
        d.stop()
    return {"wall_to_ready_s": round(wall, 2), "ready": ready, "idle": idle, "after_run": after_run}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--starts", type=int, default=3)
    ap.add_argument("--idle-s", type=float, default=5.0)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--run", action="store_true", help="make and identify one short run after the idle time")
    args = ap.parse_args()
    starts = []
    for i in range(args.starts):
        with tempfile.TemporaryDirectory(prefix="bench-daemon-cpu-") as tmp:
            starts.append(one_start(Path(tmp), args.idle_s, args.workers, args.run))
            print(json.dumps({"start": i, **starts[-1]}), file=sys.stderr)
    keys = ("ready", "idle", "after_run") if args.run else ("ready", "idle")
    medians = {k: {role: round(statistics.median(s[k].get(role, 0.0) for s in starts), 3)
                   for role in sorted({r for s in starts for r in s[k]})} for k in keys}
    print(json.dumps({"starts": starts, "median_cpu_s": medians, "load_avg_1m": round(os.getloadavg()[0], 2),
                      "workers": args.workers}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
