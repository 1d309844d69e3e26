"""Kills while results are written: ``station identify`` and ``station discrepancy --save`` on one
recording, each killed (SIGKILL) at a random instant of its run, as a power cut or an OOM kill would;
then a process that does nothing but store results (``write_result`` of an identification, H(f)
and a model-gap result, over and over) killed at random instants, so that the kills land inside
the writes themselves.

After every kill: the recording must be byte for byte what it was and open normally with plain h5py
(no "open for writing" flag), and every result beside it must read whole (the identification back
into an ``IdentificationResult``).  A kill that lands while a result file is being written leaves a
temporary file, which is counted (it shows the kills reached the writes) and never read as a result.
Prints JSON.

    PYTHONPATH=$PWD python3 bench/result_kills.py [--kills 30] [--seed 1]
"""


from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py

WRITER = r"""
import sys
import numpy as np
from station.recording import write_result
rec, i = sys.argv[1], 0
print("ready", flush=True)
while True:
    a = np.random.default_rng(i).standard_normal(20_000)
    for name, group in (("identify_fd_sdof", "results"), ("steps", "processed"), ("discrepancy", "results")):
        write_result(rec, name, {"method": "fd", "model": "sdof", "parameters": {}, "i": i, "sum": float(a.sum())},
                     {"a": a}, group=group)
    i += 1
"""


def _station() -> list[str]:
    exe = Path(sys.executable).parent / "station"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "station.cli"]


def _digest(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _check(rec: Path, digest: str) -> dict[str, bool]:
    from station.ident.result import IdentificationResult
    from station.recording import read_recording, read_stored

    out = {"recording_unchanged": _digest(rec) == digest, "recording_opens": True, "results_read": True}
    try:
        with h5py.File(rec, "r"):
            pass
        read_recording(rec)
    except Exception:
        out["recording_opens"] = False
    try:
        for name, s in read_stored(rec).items():
            if name.startswith("identify_"):
                IdentificationResult.from_dict(s.doc)
    except Exception:
        out["results_read"] = False
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kills", type=int, default=30)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    from station.config import default_config_path, load_config
    from station.recording.stored import stale_temporaries
    from station.simulate import simulate_run

    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory() as td:
        folder = Path(td)
        rec = simulate_run(load_config(default_config_path()), folder)
        digest = _digest(rec)
        commands = {"identify": [*_station(), "identify", str(rec), "--json"],
                    "discrepancy --save": [*_station(), "discrepancy", str(rec), "--save", "--no-plot",
                                           "--max-effects", "1"]}
        durations = {}
        for name, cmd in commands.items():  # how long each runs when not killed: the kills fall inside
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            durations[name] = time.perf_counter() - t0
        bad: list[dict[str, object]] = []
        mid_write = 0
        for k in range(args.kills):
            name = list(commands)[k % len(commands)]
            proc = subprocess.Popen(commands[name], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            # half the kills anywhere in the run, half near its end, where the results are written
            time.sleep((rng.uniform(0.2, 1.05) if k % 4 < 2 else rng.uniform(0.9, 1.02)) * durations[name])
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            left = stale_temporaries(folder)
            mid_write += bool(left)
            for q in left:
                os.unlink(q)
            state = _check(rec, digest)
            if not all(state.values()):
                bad.append({"kill": k, "command": name, **state})
        loop_bad, loop_mid = 0, 0
        for k in range(args.kills):  # kills inside the writes
            proc = subprocess.Popen([sys.executable, "-c", WRITER, str(rec)], stdout=subprocess.PIPE,
                                    stderr=subprocess.DEVNULL, text=True)
            assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
            time.sleep(rng.uniform(0.0, 0.2))
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            left = stale_temporaries(folder)
            loop_mid += bool(left)
            for q in left:
                os.unlink(q)
            state = _check(rec, digest)
            if not all(state.values()):
                loop_bad += 1
                bad.append({"kill": k, "command": "write_result loop", **state})
        print(json.dumps({"cli_kills": args.kills, "cli_kills_during_a_result_write": mid_write,
                          "writer_kills": args.kills, "writer_kills_during_a_result_write": loop_mid,
                          "unreadable_recordings": sum(1 for b in bad if not b["recording_opens"]),
                          "changed_recordings": sum(1 for b in bad if not b["recording_unchanged"]),
                          "unreadable_results": sum(1 for b in bad if not b["results_read"]),
                          "command_s": {n: round(v, 2) for n, v in durations.items()}, "failures": bad}, indent=2))


if __name__ == "__main__":
    main()
