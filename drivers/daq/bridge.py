"""The DAQ-bridge driver (thread-based; asyncio callers wrap its blocking calls in a thread).

A reader thread owns the link: it decodes the stream (:class:`StreamDecoder`), routes replies to
the command in flight and queues stream events for the consumer.  Usage::

    daq = DaqBridge()
    daq.connect(SerialLink("/dev/ttyACM0"))        # STOP, drain, check idle: a known state
    daq.configure(rate_hz=20_000, frame_samples=256)
    daq.start()
    for ev in daq.events(timeout_s=1.0):           # SampleBlock | SampleGap | StreamStalled
        ...
    summary = daq.stop()                           # reports a trailing gap too
    daq.close()

Events, in stream order: :class:`SampleBlock` (first_index, displacement int16[n], force int16[n]),
:class:`SampleGap` (first_index, count): samples that will never arrive, and
:class:`StreamStalled` (no data for ``stall_timeout_s``).  A lost link ends :meth:`events` with
:class:`DaqLinkError`.  Samples are indexed from 0 at START.

Every command carries a tag (``#N``) that the bridge echoes in its reply; a reply with another tag
(a late answer to a command that timed out) is dropped, never taken as the answer to a later one.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

from drivers.daq.link import ByteLink, DaqLinkError
from drivers.daq.protocol import (
    CHANNELS,
    CODE_BITS,
    DEFAULT_FRAME_SAMPLES,
    LINK_KINDS,
    DecoderStats,
    FrameError,
    Reply,
    SampleBlock,
    SampleGap,
    StreamDecoder,
    encode_command,
    link_budget,
    split_tag,
    usb_link_budget,
)

log = logging.getLogger(__name__)

# the longest the reader waits for the next byte while no stream runs (a reply wakes it at once), s
IDLE_READ_S = 0.1


class DaqCommandError(RuntimeError):
    """The bridge answered ``ERR ...`` or something unexpected to a command."""


class DaqLinkBudgetError(ValueError):
    """The serial link's baud rate cannot carry the configured stream (what it needs, what it has)."""


class DaqTimeoutError(TimeoutError):
    """No reply to a command within the reply time-out."""


@dataclass(frozen=True)
class StreamStalled:
    """No bytes arrived for ``seconds`` while streaming; ``next_sample_index`` is still awaited."""

    next_sample_index: int
    seconds: float


@dataclass(frozen=True)
class DaqConfig:
    """Effective bridge configuration: ``rate_hz`` is the sample rate the ADC actually delivers
    (``rate_exact``, Hz per channel), ``rate_requested_hz`` the one asked for; samples per frame;
    ADC ranges +-V."""

    rate_hz: float
    frame_samples: int
    range_disp_V: float
    range_force_V: float
    rate_requested_hz: float


@dataclass(frozen=True)
class DaqHardware:
    """What the bridge reports of itself at connect (``IDN?`` and ``HW?``).

    ``adc``: the converter's part name; ``adc_bits``: its resolution (the frames carry 16-bit codes);
    ``channels``: in frame order; ``adc_clock_hz``: its master clock; ``rate_min_hz``/``rate_max_hz``:
    the rates it can be configured to; ``link``: ``uart`` or ``usb-cdc``; ``link_bytes_per_s``: the
    throughput the bridge sustains to the host (required for ``usb-cdc``, None if not reported)."""

    identity: str
    adc: str
    adc_bits: int
    channels: tuple[str, ...]
    adc_clock_hz: float
    rate_min_hz: float
    rate_max_hz: float
    link: str
    link_bytes_per_s: float | None

    @property
    def code_bits(self) -> int:
        """Resolution of the codes the frames carry: the converter's, at most :data:`CODE_BITS` (a
        wider converter's codes are rounded to 16 bits)."""
        return min(self.adc_bits, CODE_BITS)

    def as_attrs(self) -> dict[str, str | float | int]:
        """Flat attributes for a recording (units in the names)."""
        attrs: dict[str, str | float | int] = {
            "daq_identity": self.identity, "daq_adc": self.adc, "daq_adc_bits": self.adc_bits,
            "daq_channels": ",".join(self.channels), "daq_adc_clock_hz": self.adc_clock_hz,
            "daq_rate_min_hz": self.rate_min_hz, "daq_rate_max_hz": self.rate_max_hz, "daq_link": self.link}
        if self.link_bytes_per_s is not None:
            attrs["daq_link_bytes_per_s"] = self.link_bytes_per_s
        return attrs


def parse_hardware(identity: str, reply: str) -> DaqHardware:
    """The ``HW?`` reply text (``OK HW adc=... bits=... ...``) -> :class:`DaqHardware`; DaqCommandError
    naming the key that is missing or malformed."""
    kv = _parse_kv(reply)
    try:
        link = kv["link"]
        if link not in LINK_KINDS:
            raise ValueError(f"link={link!r} (expected {' or '.join(LINK_KINDS)})")
        lbps = float(kv["link_bytes_per_s"]) if "link_bytes_per_s" in kv else None
        if link == "usb-cdc" and (lbps is None or not lbps > 0):
            raise ValueError("link=usb-cdc without a positive link_bytes_per_s")
        hw = DaqHardware(identity, kv["adc"], int(kv["bits"]), tuple(kv["channels"].split(",")),
                         float(kv["clock_hz"]), float(kv["rate_min"]), float(kv["rate_max"]), link, lbps)
    except (KeyError, ValueError) as exc:
        raise DaqCommandError(f"HW? reply: expected adc=, bits=, channels=, clock_hz=, rate_min=, rate_max=, "
                              f"link=uart|usb-cdc (and link_bytes_per_s= for usb-cdc), got {reply!r}: "
                              f"{exc}") from exc
    return hw


@dataclass(frozen=True)
class StreamSummary:
    """At STOP: frames/samples the bridge sent, what arrived intact and what was lost."""

    frames_sent: int
    samples_sent: int
    stats: DecoderStats


StreamEvent = SampleBlock | SampleGap | StreamStalled
class _LinkLost:
    """Queued after the last event when the link is lost (a sentinel)."""


_LINK_LOST = _LinkLost()


def _parse_kv(text: str) -> dict[str, str]:
    return dict(w.split("=", 1) for w in text.split() if "=" in w)


class DaqBridge:
    """Driver of the DAQ/signal-conditioner bridge over any :class:`ByteLink`."""

    def __init__(self, *, reply_timeout_s: float = 1.0, stall_timeout_s: float = 0.5,
                 read_interval_s: float = 0.02) -> None:
        self.reply_timeout_s = reply_timeout_s
        self.stall_timeout_s = stall_timeout_s
        self.read_interval_s = read_interval_s
        self.decoder = StreamDecoder()
        self.config: DaqConfig | None = None
        self.hardware: DaqHardware | None = None
        self.link_error: DaqLinkError | None = None
        self._link: ByteLink | None = None
        self._events: queue.Queue[StreamEvent | _LinkLost] = queue.Queue()
        self._replies: queue.Queue[str] = queue.Queue()
        self._cmd_lock = threading.Lock()
        self._streaming = False
        self._running = False
        self._thread: threading.Thread | None = None
        self._tag = 0
        self._last_rx = 0.0
        self.stale_replies = 0
        self.discarded_frames = 0

    # ------------------------------------------------------------------ link / reader
    def connect(self, link: ByteLink, *, reset: bool = True, reset_timeout_s: float = 5.0) -> None:
        """Attach the backend link, start the reader thread and bring the bridge to a known state.

        With ``reset`` (default) the bridge is sent ``STOP`` (a stream left running by a station that
        died is stopped), the link is drained until quiet and ``STAT?`` must report ``state=idle``;
        :class:`DaqCommandError` otherwise.  ``reset_timeout_s`` bounds the STOP reply, which comes
        after whatever the bridge still had queued.
        """
        self._link = link
        self._running = True
        self._last_rx = time.monotonic()
        self._thread = threading.Thread(target=self._reader, name="daq-reader", daemon=True)
        self._thread.start()
        log.info("DAQ bridge connected via %s", link.description)
        if reset:
            try:
                self.reset(timeout_s=reset_timeout_s)
                self.hardware = self.read_hardware()
            except BaseException:
                self.close()  # no reader thread or open port left behind
                raise

    def reset(self, *, timeout_s: float = 5.0, quiet_s: float = 0.1) -> dict[str, str]:
        """STOP, drain and check: returns the idle ``STAT?`` of the bridge (DaqCommandError if not idle)."""
        reply = self.command("STOP", timeout_s=timeout_s)
        self._streaming = False
        if "was idle" not in reply:
            log.warning("DAQ bridge was still streaming (left running by an earlier session): stopped (%s)",
                        reply)
        self._wait_quiet(quiet_s, timeout_s)
        st = self.status()
        if st.get("state") != "idle":
            raise DaqCommandError(f"DAQ bridge after STOP: expected state=idle, got state={st.get('state')!r}")
        self.config = None
        return st

    def _wait_quiet(self, quiet_s: float, timeout_s: float) -> None:
        """Wait until nothing arrived for ``quiet_s`` (bytes still in flight are read and discarded)."""
        deadline = time.monotonic() + timeout_s
        while (now := time.monotonic()) - self._last_rx < quiet_s:
            if now > deadline:
                raise DaqCommandError(f"DAQ link not quiet {timeout_s} s after STOP: the bridge keeps sending")
            time.sleep(quiet_s / 4)

    def _reader(self) -> None:
        assert self._link is not None
        last_data = time.monotonic()
        stalled = False
        while self._running:
            try:
                data = self._read()
            except DaqLinkError as exc:
                if self._running:
                    log.error("DAQ link lost: %s", exc)
                    self.link_error = exc
                    self._events.put(_LINK_LOST)
                return
            now = time.monotonic()
            if data:
                self._last_rx = now
            if not data:
                if self._streaming and not stalled and now - last_data > self.stall_timeout_s:
                    stalled = True
                    log.warning("DAQ stream stalled: no data for %.2f s", now - last_data)
                    self._events.put(StreamStalled(self.decoder.next_sample_index, now - last_data))
                continue
            last_data, stalled = now, False
            for ev in self.decoder.feed(data):
                if isinstance(ev, Reply):
                    self._replies.put(ev.text)
                elif not self._streaming:  # frames of a stream we did not start (or already stopped)
                    self.discarded_frames += isinstance(ev, SampleBlock)
                elif isinstance(ev, FrameError):
                    log.warning("DAQ frame rejected (%s) at byte %d, next sample %d: %s",
                                ev.kind, ev.stream_offset, ev.next_sample_index, ev.detail)
                else:
                    self._events.put(ev)

    def _read(self) -> bytes:
        """The next bytes: while streaming, what arrives within ``read_interval_s`` (batched); else,
        on a link that can return at the first byte (``SerialLink.read_first``), as soon as anything
        arrives, waiting at most ``IDLE_READ_S`` (an idle stream process woke 50 times a second)."""
        assert self._link is not None
        read_first = None if self._streaming else getattr(self._link, "read_first", None)
        if read_first is not None:
            return bytes(read_first(1 << 20, max(self.read_interval_s, IDLE_READ_S)))
        return self._link.read(1 << 20, self.read_interval_s)

    # ------------------------------------------------------------------ commands
    def command(self, text: str, *, timeout_s: float | None = None) -> str:
        """Send one command, return the ``OK ...`` reply text (tag removed); DaqCommandError on ``ERR``.

        The command is tagged; replies carrying another tag (or none) are stale and dropped.
        ``timeout_s`` defaults to ``reply_timeout_s``.
        """
        if self._link is None:
            raise DaqLinkError("DAQ bridge not connected: call connect(link) first")
        if self.link_error is not None:
            raise DaqLinkError(f"DAQ link lost earlier: {self.link_error}")
        wait = self.reply_timeout_s if timeout_s is None else timeout_s
        with self._cmd_lock:
            self._tag = self._tag % 65535 + 1
            tag = f"#{self._tag}"
            self._link.write(encode_command(text, tag))
            deadline = time.monotonic() + wait
            while True:
                try:
                    got_tag, reply = split_tag(self._replies.get(timeout=max(0.0, deadline - time.monotonic())))
                except queue.Empty:
                    if self.link_error is not None:
                        raise DaqLinkError(f"DAQ link lost during {text!r}: {self.link_error}") from None
                    raise DaqTimeoutError(f"no reply to {text!r} ({tag}) within {wait} s") from None
                if got_tag == tag:
                    break
                self.stale_replies += 1
                log.warning("DAQ: dropped a stale reply (tag %s, waiting for %s): %r", got_tag, tag, reply)
        if not reply.startswith("OK"):
            raise DaqCommandError(f"command {text!r} refused: {reply}")
        return reply

    def identify(self) -> str:
        """Identity string of the bridge (vendor, model, serial, firmware)."""
        return self.command("IDN?")[3:]

    def read_hardware(self) -> DaqHardware:
        """``IDN?`` and ``HW?``: the bridge's ADC, resolution, channels, clock, rates and link."""
        return parse_hardware(self.identify(), self.command("HW?"))

    def _check_budget(self, rate_hz: float, frame_samples: int) -> None:
        """Refuse (DaqLinkBudgetError) a rate the link cannot carry in the worst case: a UART by its baud
        rate, a USB-CDC port by the throughput the bridge reports."""
        kind = getattr(self._link, "kind", None)
        hw = self.hardware
        if kind is not None and hw is not None and hw.link != kind:
            raise DaqLinkBudgetError(f"DAQ link kind: the station is configured for {kind}, the bridge "
                                     f"reports link={hw.link} (HW?): expected the same kind")
        if kind == "usb-cdc":
            if hw is None or hw.link_bytes_per_s is None:
                raise DaqLinkBudgetError("a usb-cdc DAQ link is checked against the throughput the bridge "
                                         "reports (HW? link_bytes_per_s=): expected it, got none")
            budget = usb_link_budget(rate_hz, hw.link_bytes_per_s, frame_samples)
        else:
            baud = getattr(self._link, "baudrate", None)
            if not isinstance(baud, int):
                return  # a link without a baud rate (a socket): nothing to budget
            budget = link_budget(rate_hz, baud, frame_samples)
        if not budget.ok:
            raise DaqLinkBudgetError(budget.message())

    def configure(self, *, rate_hz: float = 20_000.0, frame_samples: int = DEFAULT_FRAME_SAMPLES,
                  range_disp_V: float = 10.0, range_force_V: float = 10.0,
                  check_link_budget: bool = True) -> DaqConfig:
        """Set sample rate (Hz), samples per frame and the +-V ranges; returns the effective config.

        On a link with a known baud rate (``SerialLink``) a rate the link cannot carry in the worst
        case (:func:`~drivers.daq.protocol.link_budget`) is refused before anything is sent
        (:class:`DaqLinkBudgetError`); ``check_link_budget=False`` is for benches that measure beyond.
        """
        if check_link_budget:
            self._check_budget(rate_hz, frame_samples)
        kv = _parse_kv(self.command(f"CONF rate={rate_hz:g} frame={frame_samples} "
                                    f"range_disp={range_disp_V:g} "
                                    f"range_force={range_force_V:g} channels={','.join(CHANNELS)}"))
        try:
            asked = float(kv["rate"])
            exact = float(kv.get("rate_exact", kv["rate"]))  # a bridge without rate_exact: its rate is exact
            config = DaqConfig(exact, int(kv["frame"]), float(kv["range_disp"]), float(kv["range_force"]), asked)
        except (KeyError, ValueError) as exc:
            raise DaqCommandError(
                f"CONF reply: expected rate=, rate_exact=, frame=, range_disp=, range_force=, got {kv}") from exc
        if not abs(exact - asked) <= 0.01 * asked:
            raise DaqCommandError(f"CONF reply: the ADC delivers rate_exact={exact:g} Hz for rate={asked:g} Hz: "
                                  "expected within 1 %")
        if check_link_budget and exact > rate_hz:
            self._check_budget(exact, frame_samples)
        self.config = config
        return self.config

    def status(self) -> dict[str, str]:
        """Bridge status as key=value pairs (state, frames, overflows, configuration)."""
        return _parse_kv(self.command("STAT?"))

    def start(self) -> None:
        """Start streaming; sample index 0 is the first sample of the first frame."""
        if self.config is None:
            self.configure()
        assert self.config is not None
        self.decoder.reset(self.config.frame_samples)
        while not self._events.empty():
            self._events.get_nowait()
        self.discarded_frames = 0
        self._streaming = True
        try:
            self.command("START")
        except Exception:
            self._streaming = False
            raise

    def stop(self) -> StreamSummary:
        """Stop streaming; frames lost at the very end are reported as a final :class:`SampleGap`."""
        reply = self.command("STOP")
        self._streaming = False
        kv = _parse_kv(reply)
        try:
            frames = int(kv["frames"])
        except (KeyError, ValueError) as exc:
            raise DaqCommandError(f"STOP reply: expected frames=N, got {reply!r}") from exc
        for ev in self.decoder.finish(frames):
            if isinstance(ev, FrameError):
                log.warning("DAQ frame rejected at STOP (%s): %s", ev.kind, ev.detail)
            elif isinstance(ev, SampleBlock | SampleGap):
                self._events.put(ev)
            else:  # a reply after the STOP reply is no stream event
                log.debug("DAQ reply after STOP ignored: %r", ev)
        return StreamSummary(frames, frames * self.decoder.frame_samples, self.decoder.stats)

    # ------------------------------------------------------------------ events
    def get_event(self, timeout_s: float | None = None) -> StreamEvent | None:
        """Next stream event, or None after ``timeout_s``; raises DaqLinkError after a lost link."""
        try:
            ev = self._events.get(timeout=timeout_s)
        except queue.Empty:
            return None
        if isinstance(ev, _LinkLost):
            self._events.put(_LINK_LOST)
            raise DaqLinkError(f"DAQ link lost: {self.link_error}")
        return ev

    def events(self, timeout_s: float = 1.0) -> Iterator[StreamEvent]:
        """Yield events until none arrives within ``timeout_s``."""
        while (ev := self.get_event(timeout_s)) is not None:
            yield ev

    def close(self) -> None:
        """Stop the reader thread and close the link (does not send STOP)."""
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._link is not None:
            self._link.close()
            self._link = None
