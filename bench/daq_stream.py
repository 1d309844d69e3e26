"""Lossless ceiling of the DAQ serial path per baud rate: emulator -> baud-limited link -> driver.

A pty ignores the baud rate, so the link is a relay between two ptys that paces the bridge's bytes
at ``baud / 10`` bytes per second (8N1: start, 8 data, stop bit), like a UART with a 4 KiB
transmit buffer: it takes bytes from the bridge's pty only while that buffer has room, so a stream
the link cannot carry backs up into the bridge's FIFO (64 KiB here) and overflows it, as on a real
link.  The emulator (rig physics,
steady 20 Hz crank) and the relay each run in their own subprocess; the driver runs here, with the
station's frames of 256 samples.

For each baud rate the rate ladder goes up in steps of 0.25 x 20 kHz from about half the nominal
ceiling until a step is not lossless.  A step is lossless when every repeat delivered every sample
(no gap, no CRC error, no FIFO overflow) *and* kept up: after the first second, the samples
arrived at >= 98 % of the production rate (least-squares slope of samples delivered over arrival
time; otherwise the link's buffers were still filling and the loss would only come later).

Prints JSON: per baud rate ``max_lossless_factor`` (multiple of the 20 kHz two-channel stream),
``link_use_max`` per step (bytes received per second / (baud / 10): near 1 when the link is the
limit, clearly below when the host starved the emulator or relay),
``max_lossless_rate_hz``, the computed ``nominal_ceiling_factor`` (no SLIP escapes) and
``worst_case_ceiling_factor`` (every byte escaped: what the configuration check admits), and the
per-step details.  ``--baud 0`` measures the unpaced pty (the driver's own ceiling).
"""

from __future__ import annotations

import argparse
import json
import os
import selectors
import statistics
import subprocess
import sys
import time
import tty

import numpy as np

BASE_RATE_HZ = 20_000.0
FRAME = 256
STEP = 0.25
DEFAULT_BAUDS = (921_600, 2_000_000, 3_000_000)
RELAY_BUFFER = 4096  # the link's transmit buffer (bytes) in front of the paced line
KEEP_UP = 0.98  # delivered rate after the first second (least-squares slope) / production rate


def run_emulator() -> int:
    """Subprocess mode: DAQ emulator on a pty; prints the pty path; runs until stdin closes."""
    from drivers.rig.presets import paper_5kN_physics
    from drivers.sim.daq_emulator import DaqEmulator
    from drivers.sim.daq_source import RigSource
    from drivers.sim.pty import open_pty

    pty = open_pty()
    src = RigSource(paper_5kN_physics(), seed=1, crank_radius_m=0.01)
    emu = DaqEmulator(pty.master, src, lambda t: 20.0, fifo_bytes=64 * 1024, on_close=pty.forget_master).start()
    print(pty.path, flush=True)
    sys.stdin.read()
    emu.close()
    pty.close()
    return 0


def run_relay(baud: int, bridge_path: str) -> int:
    """Subprocess mode: a new pty for the driver, joined to ``bridge_path``.

    Bridge -> driver is a UART: bytes wait in a transmit buffer of ``RELAY_BUFFER`` bytes (read from
    the bridge's pty only while there is room: the rest backs up into the bridge's FIFO) and leave it
    at ``baud / 10`` bytes/s while it is not empty; an idle line banks no time (a burst of catch-up
    after the relay itself was descheduled is allowed for up to 10 ms).  Driver -> bridge (short
    commands) is copied unpaced."""
    from drivers.sim.pty import PtyBridge, open_pty

    bridge = os.open(bridge_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    tty.setraw(bridge)
    host = open_pty()
    print(host.path, flush=True)
    bps = baud / 10.0
    bank_max = 0.01 * bps
    batch = max(64.0, 0.001 * bps)  # write about 1 ms of bytes at a time (fewer wake-ups)
    tokens, last = 0.0, time.monotonic()
    buf = bytearray()
    sel = selectors.DefaultSelector()
    sel.register(host.master, selectors.EVENT_READ, "host")
    sel.register(sys.stdin.fileno(), selectors.EVENT_READ, "stdin")
    sel.register(bridge, selectors.EVENT_READ, "bridge")
    reading = True
    while True:
        now = time.monotonic()
        tokens = min(bank_max, tokens + (now - last) * bps) if buf else 0.0
        last = now
        if buf and tokens >= 1.0:
            n = min(len(buf), int(tokens))
            PtyBridge._write_all(host.master, bytes(buf[:n]))
            del buf[:n]
            tokens -= n
        room = len(buf) < RELAY_BUFFER
        if room != reading:
            (sel.register(bridge, selectors.EVENT_READ, "bridge") if room else sel.unregister(bridge))
            reading = room
        timeout = max(0.0005, (min(len(buf), batch) - tokens) / bps) if buf else 0.01
        for key, _ in sel.select(timeout=timeout):
            if key.data == "stdin":
                return 0
            try:
                if key.data == "host":
                    PtyBridge._write_all(bridge, os.read(host.master, 65536))
                else:
                    buf += os.read(bridge, RELAY_BUFFER - len(buf))
            except BlockingIOError:
                continue


def stream_once(port: str, baud: int, factor: float, seconds: float) -> dict[str, float]:
    """Stream ``seconds`` at ``factor`` x 20 kHz; counts, loss and the delivered rate after 1 s."""
    from drivers.daq import DaqBridge, SampleBlock, SampleGap, SerialLink

    rate = BASE_RATE_HZ * factor
    daq = DaqBridge(reply_timeout_s=5.0)
    daq.connect(SerialLink(port, baudrate=baud or 3_000_000))
    daq.configure(rate_hz=rate, frame_samples=FRAME, check_link_budget=False)
    got = gaps = 0
    arrivals: list[tuple[float, int]] = []  # (time after START in s, samples delivered so far)
    c0, w0 = time.process_time(), time.monotonic()
    daq.start()
    while time.monotonic() - w0 < seconds:
        ev = daq.get_event(0.1)
        if isinstance(ev, SampleBlock):
            got += ev.count
            arrivals.append((time.monotonic() - w0, got))
        elif isinstance(ev, SampleGap):
            gaps += 1
    link_bytes_per_s = daq.decoder.stats.bytes / (time.monotonic() - w0)
    summary = daq.stop()
    for ev in daq.events(0.3):
        if isinstance(ev, SampleBlock):
            got += ev.count
        elif isinstance(ev, SampleGap):
            gaps += 1
    cpu, wall = time.process_time() - c0, time.monotonic() - w0
    overflows = int(daq.status().get("overflows", "-1"))
    daq.close()
    late = np.array([a for a in arrivals if a[0] >= 1.0], float).reshape(-1, 2)
    slope = float(np.polyfit(late[:, 0], late[:, 1], 1)[0]) if len(late) >= 3 else 0.0
    return {"sent": summary.samples_sent, "received": got, "gaps": gaps, "overflows": overflows,
            "crc_errors": summary.stats.crc_errors, "expected": rate * seconds, "cpu_share": cpu / wall,
            "delivered_rate_ratio": slope / rate,
            "link_use": link_bytes_per_s / (baud / 10) if baud else 0.0}


def lossless(r: dict[str, float]) -> bool:
    return (r["gaps"] == 0 and r["overflows"] == 0 and r["crc_errors"] == 0 and r["received"] == r["sent"]
            and r["sent"] >= 0.9 * r["expected"] and r["delivered_rate_ratio"] >= KEEP_UP)


def ladder(port: str, baud: int, start: float, stop: float, seconds: float, repeats: int) -> dict[str, object]:
    details: dict[str, object] = {}
    best = 0.0
    factor = start
    while factor <= stop + 1e-9:
        runs = [stream_once(port, baud, factor, seconds) for _ in range(repeats)]
        ok = all(lossless(r) for r in runs)
        details[f"{factor:g}"] = {
            "lossless": ok,
            "samples_lost_max": max(int(r["sent"] - r["received"]) for r in runs),
            "delivered_rate_ratio_min": round(min(r["delivered_rate_ratio"] for r in runs), 4),
            "link_use_max": round(max(r["link_use"] for r in runs), 3),
            "cpu_share_median": round(statistics.median(r["cpu_share"] for r in runs), 4)}
        if not ok:
            break
        best = factor
        factor += STEP
    return {"max_lossless_factor": best, "max_lossless_rate_hz": best * BASE_RATE_HZ, "per_factor": details}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--emulator", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--relay", nargs=2, metavar=("BAUD", "BRIDGE_PTY"), help=argparse.SUPPRESS)
    ap.add_argument("--baud", type=int, nargs="*", default=list(DEFAULT_BAUDS),
                    help="baud rates to measure (0: unpaced pty)")
    ap.add_argument("--seconds", type=float, default=3.0, help="stream length per run (> 1 s)")
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    if args.emulator:
        return run_emulator()
    if args.relay:
        return run_relay(int(args.relay[0]), args.relay[1])
    from drivers.daq.protocol import link_budget

    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    emu = subprocess.Popen([sys.executable, __file__, "--emulator"], stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE, text=True, env=env)
    assert emu.stdout is not None and emu.stdin is not None
    bridge_port = emu.stdout.readline().strip()
    results: dict[str, object] = {}
    try:
        for baud in args.baud:
            relay = None
            port = bridge_port
            if baud:
                relay = subprocess.Popen([sys.executable, __file__, "--relay", str(baud), bridge_port],
                                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
                assert relay.stdout is not None
                port = relay.stdout.readline().strip()
            try:
                if baud:
                    b = link_budget(BASE_RATE_HZ, baud, FRAME)
                    nominal = baud / b.nominal_baud
                    start = max(STEP, STEP * round(0.5 * nominal / STEP))
                    entry = ladder(port, baud, start, nominal + 2 * STEP, args.seconds, args.repeats)
                    entry |= {"nominal_ceiling_factor": round(nominal, 3),
                              "worst_case_ceiling_factor": round(b.margin, 3)}
                else:
                    entry = ladder(port, 0, 1.0, 50.0, args.seconds, args.repeats)
                results[str(baud) if baud else "unpaced_pty"] = entry
            finally:
                if relay is not None:
                    assert relay.stdin is not None
                    relay.stdin.close()
                    relay.wait(timeout=10)
    finally:
        emu.stdin.close()
        emu.wait(timeout=10)
    print(json.dumps({
        "base_rate_hz": BASE_RATE_HZ, "channels": 2, "frame_samples": FRAME, "bits_per_byte": 10,
        "step_factor": STEP, "seconds": args.seconds, "repeats": args.repeats, "cores": os.cpu_count(),
        "per_baud": results,
    }, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
