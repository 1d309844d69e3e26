"""The DAQ-bridge emulator: speaks ``docs/daq-protocol.md`` on a pty (or any fd), streams in real time.

Samples come from a :class:`~drivers.sim.daq_source.SampleSource` (the rig physics) in blocks of a
fixed length; the crank frequency at a block's end is the motor emulator's speed at that sample's
own instant (start time + index / rate), so both channels move with the motor, and what a sample
holds depends on its index only, never on when the emulator got round to computing it (a host
that stalls the emulator delays the samples, it does not change them).
Fault injection (thread-safe): dropped and corrupted frames, garbage between frames, a stalled
stream and a closed port.  Every sample the emulator does not deliver intact is recorded in
:attr:`DaqEmulator.lost` as ``(first_sample_index, count)``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import threading
from collections.abc import Callable, Iterable

import numpy as np

from drivers.clock import REAL_CLOCK, Clock
from drivers.daq.protocol import (
    CHANNELS,
    END_BYTE,
    PKT_COMMAND,
    DaqProtocolError,
    check_tag,
    crc32,
    encode_reply,
    sample_packet_raw,
    slip_escape,
    slip_unescape,
    split_tag,
)
from drivers.sim.daq_source import SampleSource

log = logging.getLogger(__name__)

IDENTITY = "SINECAL,DAQ-BRIDGE-EMU,SN0001,1.0"
RATE_LIMITS_HZ = (100.0, 1_000_000.0)
FRAME_LIMITS = (16, 4096)
RANGES_V = (0.1, 10.0)
SYNTH_BLOCK_S = 0.0128  # samples are synthesised in blocks of this duration (256 samples at 20 kHz)
# While idle the emulator wakes this often (a command, the peer's end or a reply held back by
# ``delay_replies`` wakes it sooner): the synthesis follows the motor block by block from its speed
# history all the same, but 200 wake-ups a second cost an idle simulated rig 3-4 % of a core
IDLE_TICK_S = 0.1


class DaqEmulator:
    """Bridge emulator on file descriptor ``fd`` (pty master or socket), run in a daemon thread.

    The emulator owns ``fd`` and closes it (``close``/``close_port``), then calls ``on_close``.
    Samples are due at ``rate`` per second of ``clock`` (real time unless a virtual clock is given).
    With ``fd=None`` there is no thread and no wire: a caller drives it with :meth:`feed` and
    :meth:`pull` (see :class:`~drivers.sim.daq_inprocess.ClockedDaqLink`).
    """

    def __init__(self, fd: int | None, source: SampleSource, speed_hz: Callable[[float], float], *,
                 seed: int = 0, fifo_bytes: int = 1 << 20, tick_s: float = 0.005,
                 on_close: Callable[[], None] | None = None, clock: Clock = REAL_CLOCK,
                 adc_clock_hz: float | None = None, link: str = "uart",
                 link_bytes_per_s: float | None = None, adc_bits: int = 16) -> None:
        """``speed_hz(t)``: the crank frequency (Hz) at time ``t`` (s) of ``clock`` (never later than now).
        ``adc_clock_hz``: the emulated ADC's rate is ``adc_clock_hz / N`` for a whole N (the
        achievable rate nearest the asked one, reported as ``rate_exact``); None: every rate is exact.
        ``link``/``link_bytes_per_s``: what ``HW?`` reports (``usb-cdc`` needs the throughput);
        ``adc_bits``: the resolution ``HW?`` reports (that of the source's converter)."""
        self.adc_bits = adc_bits
        self.fd = -1 if fd is None else fd
        self.adc_clock_hz = adc_clock_hz
        self.link = link
        self.link_bytes_per_s = link_bytes_per_s
        self.clock = clock
        self.source = source
        self.speed_hz = speed_hz
        self.tick_s = tick_s
        self.fifo_bytes = fifo_bytes
        self._on_close = on_close
        self._rng = np.random.default_rng(seed)
        self.config: dict[str, str] = {"rate": "20000", "rate_exact": self._exact_text(20000.0), "frame": "256",
                                       "range_disp": "10", "range_force": "10", "channels": ",".join(CHANNELS)}
        self._lock = threading.Lock()
        self._out = bytearray()
        self._cmd_buf = b""
        self.streaming = False
        self.seq = 0
        self.overflows = 0
        self.lost: list[tuple[int, int]] = []
        self._drop: set[int] = set()
        self._corrupt: set[int] = set()
        self._garbage: list[bytes] = []
        self._stall_until = 0.0
        self._reply_delay: list[float] = []
        self._delayed: list[tuple[float, bytes]] = []  # (due time, reply packet)
        self._pending: tuple[np.ndarray, np.ndarray] = (np.zeros(0, np.int16), np.zeros(0, np.int16))
        self._stop = threading.Event()
        self._closed = False
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="daq-emulator", daemon=True)

    # ------------------------------------------------------------------ fault injection
    def drop_frames(self, seqs: Iterable[int]) -> None:
        """Frames with these sequence numbers are not sent."""
        with self._lock:
            self._drop.update(seqs)

    def corrupt_frames(self, seqs: Iterable[int]) -> None:
        """Frames with these sequence numbers get one byte flipped after the CRC was computed."""
        with self._lock:
            self._corrupt.update(seqs)

    def inject_garbage(self, nbytes: int) -> None:
        """Random bytes (seeded) are written between the next two frames."""
        with self._lock:
            self._garbage.append(self._rng.integers(0, 256, nbytes, dtype=np.uint8).tobytes())

    def stall(self, seconds: float) -> None:
        """Nothing is sent for ``seconds``; the samples of that period are lost."""
        with self._lock:
            self._stall_until = self.clock.monotonic() + seconds

    def delay_replies(self, seconds: float, n: int = 1) -> None:
        """The next ``n`` replies are sent ``seconds`` late (a slow or busy bridge)."""
        with self._lock:
            self._reply_delay.extend([seconds] * n)

    def _release_delayed(self, now: float) -> None:
        while self._delayed and self._delayed[0][0] <= now:
            self._out += self._delayed.pop(0)[1]

    def close_port(self) -> None:
        """Close the port as a crashed or unplugged bridge would (the driver sees a lost link)."""
        self._stop.set()
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")
        if threading.current_thread() is not self._thread and self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._close_fd()
        self.clock.notify()

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> DaqEmulator:
        self._configure_source()
        if self.fd >= 0:
            self._thread.start()
        return self

    # ------------------------------------------------------------------ without a wire
    @property
    def port_closed(self) -> bool:
        return self._closed or self._stop.is_set()

    def has_output(self) -> bool:
        """Bytes (replies, frames) are waiting to be pulled, or the port was closed."""
        return bool(self._out) or self.port_closed

    def feed(self, data: bytes) -> None:
        """Bytes from the driver (commands), as if they had arrived on the port."""
        self._read_commands(data)

    def pull(self, max_bytes: int) -> bytes:
        """Produce what is due by now (clock time) and take up to ``max_bytes`` of the output."""
        now = self.clock.monotonic()
        self._release_delayed(now)
        self._produce(now)
        with self._lock:
            out = bytes(self._out[:max_bytes])
            del self._out[:max_bytes]
        return out

    def close(self) -> None:
        self.close_port()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)

    def _close_fd(self) -> None:
        if not self._closed:
            self._closed = True
            if self.fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(self.fd)
            if self._on_close is not None:
                self._on_close()

    # ------------------------------------------------------------------ command handling
    def _handle_command(self, text: str) -> str:
        words = text.strip().split()
        if not words:
            return "ERR 1 empty command"
        cmd, args = words[0].upper(), words[1:]
        if cmd == "IDN?":
            return f"OK {IDENTITY}"
        if cmd == "HW?":
            clock = self.adc_clock_hz if self.adc_clock_hz is not None else RATE_LIMITS_HZ[1]
            text = (f"OK HW adc=EMULATED bits={self.adc_bits} channels={','.join(CHANNELS)} clock_hz={clock:g} "
                    f"rate_min={RATE_LIMITS_HZ[0]:g} rate_max={RATE_LIMITS_HZ[1]:g} link={self.link}")
            return text + ("" if self.link_bytes_per_s is None else f" link_bytes_per_s={self.link_bytes_per_s:g}")
        if cmd == "STAT?":
            state = "streaming" if self.streaming else "idle"
            return f"OK STAT state={state} frames={self.seq} overflows={self.overflows} " + self._conf_text()
        if cmd == "CONF":
            if self.streaming:
                return "ERR 3 busy: expected STOP before CONF"
            return self._configure(args)
        if cmd == "START":
            if self.streaming:
                return "ERR 3 busy: already streaming"
            self.seq = 0
            self.overflows = 0
            self.lost = []
            self._produce(self.clock.monotonic())  # idle synthesis up to now
            self._pending = (self._pending[0][:0], self._pending[1][:0])
            self.streaming = True
            return f"OK START seq=0 {self._conf_text()}"
        if cmd == "STOP":
            was = self.streaming
            self.streaming = False
            return f"OK STOP frames={self.seq} samples={self.seq * int(self.config['frame'])}" + (
                "" if was else " (was idle)")
        return f"ERR 1 unknown command {cmd!r}: expected IDN?, HW?, CONF, START, STOP or STAT?"

    def _exact_rate(self, rate: float) -> float:
        """The achievable rate nearest ``rate`` (Hz): ``adc_clock_hz / N``, or ``rate`` without a clock."""
        if self.adc_clock_hz is None:
            return rate
        return self.adc_clock_hz / max(1, round(self.adc_clock_hz / rate))

    def _exact_text(self, rate: float) -> str:
        return f"{self._exact_rate(rate):.10g}"

    def _configure_source(self) -> None:
        c = self.config
        key = (float(c["rate_exact"]), float(c["range_disp"]), float(c["range_force"]))
        if key != getattr(self, "_source_key", None):
            self.source.configure(*key)
            self._source_key = key
            self._t0 = self.clock.monotonic()
            self._produced = 0
            self._block = max(1, round(key[0] * SYNTH_BLOCK_S))

    def _conf_text(self) -> str:
        return " ".join(f"{k}={v}" for k, v in self.config.items())

    def _configure(self, args: list[str]) -> str:
        new = dict(self.config)
        for arg in args:
            key, sep, value = arg.partition("=")
            got = value
            if not sep or key not in new or key == "rate_exact":
                keys = ", ".join(k for k in new if k != "rate_exact")
                return f"ERR 2 bad argument {arg!r}: expected key=value with key in {keys}"
            try:
                if key == "rate":
                    ok = RATE_LIMITS_HZ[0] <= float(value) <= RATE_LIMITS_HZ[1]
                    value = f"{float(value):.10g}"  # the asked rate, as asked (to 10 digits)
                    lim = f"{RATE_LIMITS_HZ[0]:g}..{RATE_LIMITS_HZ[1]:g} Hz"
                elif key == "frame":
                    ok = value.isdigit() and FRAME_LIMITS[0] <= int(value) <= FRAME_LIMITS[1]
                    lim = f"integer {FRAME_LIMITS[0]}..{FRAME_LIMITS[1]}"
                elif key in ("range_disp", "range_force"):
                    ok = RANGES_V[0] <= float(value) <= RANGES_V[1]
                    value = f"{float(value):.10g}"
                    lim = f"{RANGES_V[0]}..{RANGES_V[1]} V"
                else:
                    ok, lim = value == ",".join(CHANNELS), ",".join(CHANNELS)
            except ValueError:
                ok, lim = False, "a number"
            if ok and key == "rate" and abs(self._exact_rate(float(value)) - float(value)) > 0.01 * float(value):
                ok, lim = False, f"a rate within 1 % of {self.adc_clock_hz:g} Hz / N"
            if not ok:
                return f"ERR 2 bad value for {key}: expected {lim}, got {got!r}"
            new[key] = value
            if key == "rate":
                new["rate_exact"] = self._exact_text(float(value))
        self.config = new
        self._configure_source()
        return f"OK CONF {self._conf_text()}"

    def _read_commands(self, data: bytes) -> None:
        chunks = (self._cmd_buf + data).split(END_BYTE)
        self._cmd_buf = chunks.pop()[-8192:]
        for chunk in chunks:
            if not chunk:
                continue
            try:
                pkt = slip_unescape(chunk)
            except DaqProtocolError:
                log.warning("DAQ emulator: rejected a command packet with a bad SLIP escape (%d bytes)", len(chunk))
                self._out += encode_reply("ERR 4 malformed command packet (SLIP escape)")
                continue
            if len(pkt) < 5 or crc32(pkt[:-4]) != int.from_bytes(pkt[-4:], "little") or pkt[0] != PKT_COMMAND:
                log.warning("DAQ emulator: rejected a malformed command packet (%d bytes)", len(pkt))
                self._out += encode_reply("ERR 4 malformed command packet (CRC, type or length)")
                continue
            raw = pkt[1:-4]
            if not raw.isascii() or not raw.decode("ascii").isprintable():
                log.warning("DAQ emulator: rejected a command that is not printable ASCII (%d bytes)", len(raw))
                self._out += encode_reply("ERR 4 malformed command packet (not printable ASCII)")
                continue
            text = raw.decode("ascii")
            tag, body = split_tag(text)
            if tag is not None:
                try:
                    check_tag(tag)
                except ValueError as exc:
                    tag, reply = None, f"ERR 2 bad tag: {exc}"
                else:
                    reply = self._handle_command(body)
            else:
                reply = self._handle_command(body)
            log.debug("DAQ emulator: %r -> %r", text, reply)
            packet = encode_reply(reply if tag is None else f"{tag} {reply}")
            with self._lock:
                delay = self._reply_delay.pop(0) if self._reply_delay else 0.0
            if delay > 0:
                self._delayed.append((self.clock.monotonic() + delay, packet))
            else:
                self._out += packet

    # ------------------------------------------------------------------ streaming
    def _synthesise(self, now: float) -> None:
        """Synthesise the whole blocks due by ``now``; kept (for frames) only while streaming."""
        rate = float(self.config["rate_exact"])
        due = int((now - self._t0) * rate)
        block = self._block
        kept: list[tuple[np.ndarray, np.ndarray]] = []
        while due - self._produced >= block:
            end = self._produced + block
            # the crank frequency at the block's end is the motor's speed at that sample's instant
            d, f = self.source.advance(block, self.speed_hz(self._t0 + end / rate))
            self._produced = end
            if self.streaming:
                kept.append((d, f))
        if kept:
            self._pending = (np.concatenate([self._pending[0], *(d for d, _ in kept)]),
                             np.concatenate([self._pending[1], *(f for _, f in kept)]))

    def _produce(self, now: float) -> None:
        self._synthesise(now)
        if not self.streaming:
            return
        frame = int(self.config["frame"])
        n_frames = len(self._pending[0]) // frame
        if n_frames <= 0:
            return
        disp, force = (a[: n_frames * frame] for a in self._pending)
        self._pending = (self._pending[0][n_frames * frame:], self._pending[1][n_frames * frame:])
        with self._lock:
            stalled = now < self._stall_until
            for k in range(n_frames):
                seq = self.seq
                self.seq += 1
                first = seq * frame
                if stalled or seq in self._drop:
                    self._lose(first, frame)
                    continue
                sl = slice(k * frame, (k + 1) * frame)
                raw = sample_packet_raw(seq, disp[sl], force[sl])
                if seq in self._corrupt:
                    buf = bytearray(raw)
                    buf[len(buf) // 2] ^= 0x5A
                    raw = bytes(buf)
                    self._lose(first, frame)
                wire = END_BYTE + slip_escape(raw) + END_BYTE
                if len(self._out) + len(wire) > self.fifo_bytes:
                    self.overflows += 1
                    if seq not in self._corrupt:
                        self._lose(first, frame)
                    continue
                self._out += wire
                while self._garbage:
                    self._out += self._garbage.pop(0)

    def _lose(self, first: int, count: int) -> None:
        if self.lost and sum(self.lost[-1]) == first:
            self.lost[-1] = (self.lost[-1][0], self.lost[-1][1] + count)
        else:
            self.lost.append((first, count))

    def _timeout(self) -> float:
        """How long the loop may wait for the port: a tick while streaming, longer while idle, never
        past a held-back reply's time."""
        timeout = self.tick_s if self.streaming else max(self.tick_s, IDLE_TICK_S)
        if self._delayed:
            timeout = min(timeout, max(0.0, self._delayed[0][0] - self.clock.monotonic()))
        return timeout

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                wlist = [self.fd] if self._out else []
                r, w, _ = select.select([self.fd, self._wake_r], wlist, [], self._timeout())
                if self.fd in r:
                    try:
                        data = os.read(self.fd, 65536)
                    except BlockingIOError:
                        data = None
                    if data == b"":
                        log.info("DAQ emulator: peer closed the link")
                        return
                    if data:
                        self._read_commands(data)
                now = self.clock.monotonic()
                self._release_delayed(now)
                self._produce(now)
                if self._out and (w or not wlist):
                    try:
                        n = os.write(self.fd, self._out)
                        del self._out[:n]
                    except BlockingIOError:
                        pass
        except OSError as exc:
            if not self._stop.is_set():
                log.warning("DAQ emulator: port error %s", exc)
        finally:
            self._stop.set()
