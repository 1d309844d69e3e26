"""Wire protocol of the DAQ/signal-conditioner bridge (see ``docs/daq-protocol.md``).

Packets in both directions are SLIP-framed (RFC 1055: END=0xC0, ESC=0xDB, ESC_END=0xDC,
ESC_ESC=0xDD), with an END before *and* after each packet so that line garbage is isolated.
A packet is ``type:u8 | body | crc:u32le`` where the CRC is CRC-32/ISO-HDLC (``zlib.crc32``) of
``type | body``.  Sample packets (type 0x01) carry ``seq:u32le | count:u16le | count x (disp:i16le,
force:i16le)``.  Replies (0x02) and commands (0x10) carry ASCII text.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field

import numpy as np

END = 0xC0
ESC = 0xDB
ESC_END = 0xDC
ESC_ESC = 0xDD
END_BYTE = bytes([END])
_ESC_B = bytes([ESC])
_ESC_END_PAIR = bytes([ESC, ESC_END])
_ESC_ESC_PAIR = bytes([ESC, ESC_ESC])

PKT_SAMPLES = 0x01
PKT_REPLY = 0x02
PKT_COMMAND = 0x10

SAMPLE_HEADER = struct.Struct("<BIH")  # type, seq, count
CRC_SIZE = 4
MAX_FRAME_SAMPLES = 4096
SAMPLE_DTYPE = np.dtype("<i2")
CODE_BITS = 8 * SAMPLE_DTYPE.itemsize  # frames carry 16-bit codes (a wider converter's rounded to them)
SEQ_MODULUS = 1 << 32  # the u32 sequence number wraps 0xFFFFFFFF -> 0 (docs/daq-protocol.md, section 3)
# a forward jump of up to this many frames is a gap at once; a longer one must be confirmed by the
# next frame (seq + 1) before it is believed: one valid frame far ahead cannot derail the stream
IMMEDIATE_GAP_FRAMES = 16
TAG_PREFIX = "#"
MAX_TAG_CHARS = 16


DEFAULT_FRAME_SAMPLES = 256  # samples per channel per frame the station configures
BITS_PER_CHAR = 10  # the DAQ serial link is 8N1: start bit, 8 data bits, stop bit
# a UART (the budget is the host port's baud rate) or a native USB-CDC port (the baud rate is
# ignored; the budget is the throughput the bridge reports in its HW? reply)
LINK_KINDS = ("uart", "usb-cdc")
CHANNELS = ("disp", "force")  # the channels the station streams, in frame order (CONF channels=)


def frame_bytes_of(frame_samples: int) -> int:
    """Bytes of an un-escaped sample packet of ``frame_samples`` samples per channel: header (11 B),
    4 B per sample pair (two i16), CRC (4 B); without the SLIP END bytes."""
    return SAMPLE_HEADER.size + 4 * frame_samples + CRC_SIZE


@dataclass(frozen=True)
class LinkBudget:
    """Can a DAQ link that sustains ``capacity_bytes_per_s`` carry ``rate_hz`` x 2 channels in frames
    of ``frame_samples``?  One budget in bytes per second for both link kinds (``LINK_KINDS``):

    - ``uart``: ``baudrate`` Bd at :data:`BITS_PER_CHAR` bits per byte (8N1 framing), so the capacity
      is ``baudrate / 10`` B/s (:func:`link_budget`);
    - ``usb-cdc``: no baud rate and no start/stop bits; the capacity is the throughput the bridge
      reports in its ``HW?`` reply (:func:`usb_link_budget`); ``baudrate`` is None.

    ``frame_bytes``: un-escaped sample packet (11 + 4 x frame); ``worst_wire_bytes``: on the wire if
    SLIP escaped every byte, plus the two END bytes (2 x frame_bytes + 2); ``required_bytes_per_s``:
    what the worst case needs (the link is lossless for *any* sample values at or below it);
    ``nominal_bytes_per_s``: the same without escapes (no 0xC0/0xDB bytes); ``margin`` = capacity /
    required (>= 1 is carried).  ``rate_hz`` is the rate the bridge's ADC delivers (``rate_exact``).
    """

    rate_hz: float
    frame_samples: int
    kind: str
    capacity_bytes_per_s: float
    baudrate: int | None = None

    @property
    def frame_bytes(self) -> int:
        return frame_bytes_of(self.frame_samples)

    @property
    def worst_wire_bytes(self) -> int:
        return 2 * self.frame_bytes + 2

    @property
    def frames_per_s(self) -> float:
        return self.rate_hz / self.frame_samples

    @property
    def required_bytes_per_s(self) -> float:
        return self.frames_per_s * self.worst_wire_bytes

    @property
    def nominal_bytes_per_s(self) -> float:
        return self.frames_per_s * (self.frame_bytes + 2)

    @property
    def required_baud(self) -> float:
        """The worst case in Bd at :data:`BITS_PER_CHAR` bits per byte (a UART's figure)."""
        return self.required_bytes_per_s * BITS_PER_CHAR

    @property
    def nominal_baud(self) -> float:
        """The case without escapes in Bd at :data:`BITS_PER_CHAR` bits per byte (a UART's figure)."""
        return self.nominal_bytes_per_s * BITS_PER_CHAR

    @property
    def margin(self) -> float:
        return self.capacity_bytes_per_s / self.required_bytes_per_s

    @property
    def ok(self) -> bool:
        return self.margin >= 1.0

    def message(self) -> str:
        """What the link needs and what it has, e.g. for a refused configuration."""
        frames = (f"frames of {self.frame_samples} samples = {self.frame_bytes} bytes, "
                  f"{self.worst_wire_bytes} on the wire if SLIP escapes every byte")
        largest = f"{self.rate_hz * self.margin:,.0f} Hz"
        if self.baudrate is None:
            have = f"{self.capacity_bytes_per_s:,.0f} B/s"
            return (f"a USB-CDC DAQ link sustaining {have} (as the bridge reports) cannot carry "
                    f"{self.rate_hz:g} Hz x 2 channels: expected at least {self.required_bytes_per_s:,.0f} B/s "
                    f"({frames}), received {have}; largest rate: {largest}")
        return (f"a DAQ link of {self.baudrate} Bd cannot carry {self.rate_hz:g} Hz x 2 channels: "
                f"expected at least {self.required_baud:,.0f} Bd ({frames}, {BITS_PER_CHAR} bits per byte; "
                f"{self.nominal_baud:,.0f} Bd without escapes), received {self.baudrate} Bd; "
                f"largest rate at {self.baudrate} Bd: {largest}")


def link_budget(rate_hz: float, baudrate: int, frame_samples: int = DEFAULT_FRAME_SAMPLES) -> LinkBudget:
    """The :class:`LinkBudget` of a UART (rate in Hz per channel, link in Bd, 8N1: 10 bits per byte)."""
    return LinkBudget(rate_hz, frame_samples, "uart", baudrate / BITS_PER_CHAR, baudrate)


def usb_link_budget(rate_hz: float, capacity_bytes_per_s: float,
                    frame_samples: int = DEFAULT_FRAME_SAMPLES) -> LinkBudget:
    """The :class:`LinkBudget` of a USB-CDC link (rate in Hz per channel, the bridge's throughput in B/s)."""
    return LinkBudget(rate_hz, frame_samples, "usb-cdc", capacity_bytes_per_s)


class DaqProtocolError(ValueError):
    """A packet does not follow the protocol; the message says what was expected and what came."""


def crc32(data: bytes | bytearray | memoryview) -> int:
    """CRC-32/ISO-HDLC (poly 0x04C11DB7 reflected, init/xorout 0xFFFFFFFF); check('123456789')=0xCBF43926."""
    return zlib.crc32(data) & 0xFFFFFFFF


def slip_escape(data: bytes) -> bytes:
    """Escape ESC first, then END (order matters)."""
    return data.replace(_ESC_B, _ESC_ESC_PAIR).replace(END_BYTE, _ESC_END_PAIR)


def slip_unescape(data: bytes) -> bytes:
    """Inverse of :func:`slip_escape`; raises DaqProtocolError on an ESC not followed by 0xDC/0xDD."""
    if ESC not in data:
        return data
    n_esc = data.count(_ESC_B)
    if n_esc != data.count(_ESC_END_PAIR) + data.count(_ESC_ESC_PAIR):
        raise DaqProtocolError("SLIP: expected ESC (0xDB) to be followed by 0xDC or 0xDD, found a bare ESC")
    return data.replace(_ESC_END_PAIR, END_BYTE).replace(_ESC_ESC_PAIR, _ESC_B)


def encode_packet(ptype: int, body: bytes) -> bytes:
    """``END | slip(type | body | crc32) | END``."""
    raw = bytes([ptype]) + body
    return END_BYTE + slip_escape(raw + crc32(raw).to_bytes(4, "little")) + END_BYTE


def encode_command(text: str, tag: str | None = None) -> bytes:
    """A command packet; with ``tag`` (e.g. ``"#12"``) the bridge starts its reply with the same tag."""
    if tag is not None:
        check_tag(tag)
        text = f"{tag} {text}"
    return encode_packet(PKT_COMMAND, text.encode("ascii"))


def check_tag(tag: str) -> None:
    """A tag is ``#`` plus 1..15 printable ASCII characters (no space); ValueError otherwise."""
    if not (tag.startswith(TAG_PREFIX) and 2 <= len(tag) <= MAX_TAG_CHARS and tag.isascii()
            and tag.isprintable() and " " not in tag):
        raise ValueError(f"command tag: expected '#' and 1..{MAX_TAG_CHARS - 1} printable ASCII "
                         f"characters without spaces, got {tag!r}")


def split_tag(text: str) -> tuple[str | None, str]:
    """``"#12 OK STAT ..."`` -> ``("#12", "OK STAT ...")``; untagged text -> ``(None, text)``."""
    if text.startswith(TAG_PREFIX):
        tag, _, rest = text.partition(" ")
        return tag, rest
    return None, text


def encode_reply(text: str) -> bytes:
    return encode_packet(PKT_REPLY, text.encode("ascii"))


def sample_packet_raw(seq: int, displacement: np.ndarray, force: np.ndarray) -> bytes:
    """Unescaped sample packet (with CRC) for frame ``seq``; both arrays int16 of shape (n,)."""
    n = len(displacement)
    if len(force) != n or not 0 < n <= MAX_FRAME_SAMPLES:
        raise ValueError(f"expected two channels of equal length 1..{MAX_FRAME_SAMPLES}, "
                         f"got {n}/{len(force)}")
    inter = np.empty((n, 2), SAMPLE_DTYPE)
    inter[:, 0] = displacement
    inter[:, 1] = force
    raw = SAMPLE_HEADER.pack(PKT_SAMPLES, seq & 0xFFFFFFFF, n) + inter.tobytes()
    return raw + crc32(raw).to_bytes(4, "little")


def encode_samples(seq: int, displacement: np.ndarray, force: np.ndarray) -> bytes:
    """A complete on-wire sample frame (SLIP-framed)."""
    return END_BYTE + slip_escape(sample_packet_raw(seq, displacement, force)) + END_BYTE


# ------------------------------------------------------------------------------ decoder events
@dataclass(frozen=True)
class SampleBlock:
    """Contiguous good samples: ``first_index`` of the stream (0 = first sample after START);
    ``displacement`` and ``force`` are int16 ADC codes of shape (n,)."""

    first_index: int
    displacement: np.ndarray
    force: np.ndarray

    @property
    def count(self) -> int:
        return len(self.displacement)


@dataclass(frozen=True)
class SampleGap:
    """Samples ``first_index .. first_index+count-1`` are missing (lost or corrupted frames)."""

    first_index: int
    count: int
    frames: int


@dataclass(frozen=True)
class FrameError:
    """A packet was rejected: kind is 'crc', 'slip', 'length', 'type', 'count' or 'sequence';
    ``stream_offset`` is the byte offset just past its closing END in the received stream;
    ``next_sample_index`` the first sample index not yet delivered when it happened."""

    kind: str
    stream_offset: int
    length: int
    next_sample_index: int
    detail: str


@dataclass(frozen=True)
class Reply:
    """A text reply of the bridge ('OK ...' or 'ERR ...')."""

    text: str


DecoderEvent = SampleBlock | SampleGap | FrameError | Reply


@dataclass
class DecoderStats:
    """Counters of one stream (reset at START)."""

    bytes: int = 0
    frames_ok: int = 0
    samples_ok: int = 0
    crc_errors: int = 0
    framing_errors: int = 0
    gaps: int = 0
    frames_lost: int = 0
    samples_lost: int = 0
    errors: list[FrameError] = field(default_factory=list)


class StreamDecoder:
    """Bytes in, events out.  Never delivers a sample from a packet that failed any check.

    ``frame_samples`` is the configured samples per frame: frame ``seq`` holds samples
    ``seq*frame_samples ..``, so a sequence gap maps exactly onto the missing sample indices.
    Frame numbers are counted without bound here (``next_seq``); the wire carries them modulo 2**32,
    so a wrap 0xFFFFFFFF -> 0 is continuity, and a frame "2**32 - 1 ahead" is one frame *behind*.
    A forward jump of more than ``immediate_gap_frames`` is held until the next frame confirms it
    (its seq follows the held one): otherwise the held frame is rejected as ``sequence``.
    """

    def __init__(self, frame_samples: int = 256, *, max_errors_kept: int = 1000,
                 immediate_gap_frames: int = IMMEDIATE_GAP_FRAMES) -> None:
        self._pending = b""
        self._offset = 0
        self._max_errors = max_errors_kept
        self.immediate_gap_frames = immediate_gap_frames
        self.reset(frame_samples)

    def reset(self, frame_samples: int) -> None:
        """Start a new stream (sequence 0) with ``frame_samples`` samples per frame."""
        if not 0 < frame_samples <= MAX_FRAME_SAMPLES:
            raise ValueError(f"frame_samples: expected 1..{MAX_FRAME_SAMPLES}, got {frame_samples}")
        self.frame_samples = frame_samples
        self._packet_len = frame_bytes_of(frame_samples)
        self.next_seq = 0
        self.stats = DecoderStats()
        self._held: tuple[int, bytes] | None = None  # (frame index, payload) of an unconfirmed jump

    @property
    def next_sample_index(self) -> int:
        return self.next_seq * self.frame_samples

    def _error(self, out: list[DecoderEvent], kind: str, length: int, detail: str) -> None:
        err = FrameError(kind, self._offset, length, self.next_sample_index, detail)
        if kind == "crc":
            self.stats.crc_errors += 1
        else:
            self.stats.framing_errors += 1
        if len(self.stats.errors) < self._max_errors:
            self.stats.errors.append(err)
        out.append(err)

    def finish(self, frames_sent: int) -> list[DecoderEvent]:
        """At STOP (the bridge produced ``frames_sent`` frames): settle a held jump, then the trailing gap.

        A held frame is delivered if its index is below ``frames_sent`` (the bridge did produce it),
        and rejected as ``sequence`` otherwise.
        """
        out: list[DecoderEvent] = []
        if self._held is not None:
            index, payload = self._held
            self._held = None
            if index < frames_sent:
                gap = self.gap_to(index)
                if gap is not None:
                    out.append(gap)
                out.append(self._block(payload))
            else:
                self._error(out, "sequence", len(payload), f"frame {index % SEQ_MODULUS} is beyond the "
                            f"{frames_sent} frames the bridge reports at STOP: rejected")
        gap = self.gap_to(frames_sent)
        if gap is not None:
            out.append(gap)
        return out

    def _block(self, payload: bytes) -> SampleBlock:
        inter = np.frombuffer(payload, SAMPLE_DTYPE).reshape(-1, 2)
        block = SampleBlock(self.next_sample_index, inter[:, 0].copy(), inter[:, 1].copy())
        self.next_seq += 1
        self.stats.frames_ok += 1
        self.stats.samples_ok += block.count
        return block

    def gap_to(self, seq: int) -> SampleGap | None:
        """Account for frames ``next_seq .. seq-1`` as lost (also used for a trailing gap at STOP).

        ``seq`` is an unbounded frame index (not reduced modulo 2**32)."""
        if seq <= self.next_seq:
            return None
        frames = seq - self.next_seq
        gap = SampleGap(self.next_sample_index, frames * self.frame_samples, frames)
        self.stats.gaps += 1
        self.stats.frames_lost += frames
        self.stats.samples_lost += gap.count
        self.next_seq = seq
        return gap

    def feed(self, data: bytes) -> list[DecoderEvent]:
        """Decode ``data`` (any chunking); returns events in stream order, good samples merged."""
        out: list[DecoderEvent] = []
        self.stats.bytes += len(data)
        chunks = (self._pending + data).split(END_BYTE)
        self._pending = chunks.pop()
        if len(self._pending) > 2 * frame_bytes_of(MAX_FRAME_SAMPLES):
            self._offset += len(self._pending)
            self._error(out, "length", len(self._pending), "no END byte in an over-long run: discarded")
            self._pending = b""
        run: list[bytes] = []
        run_start = -1

        def flush() -> None:
            nonlocal run, run_start
            if run:
                inter = np.frombuffer(b"".join(run), SAMPLE_DTYPE).reshape(-1, 2)
                out.append(SampleBlock(run_start, inter[:, 0].copy(), inter[:, 1].copy()))
                run = []

        for chunk in chunks:
            self._offset += len(chunk) + 1
            if not chunk:
                continue
            try:
                pkt = slip_unescape(chunk)
            except DaqProtocolError as exc:
                flush()
                self._error(out, "slip", len(chunk), str(exc))
                continue
            if len(pkt) < 1 + CRC_SIZE or crc32(pkt[:-CRC_SIZE]) != int.from_bytes(pkt[-CRC_SIZE:], "little"):
                flush()
                self._error(out, "crc", len(pkt), f"CRC mismatch in a {len(pkt)}-byte packet")
                continue
            ptype = pkt[0]
            if ptype == PKT_REPLY:
                flush()
                out.append(Reply(pkt[1:-CRC_SIZE].decode("ascii", errors="replace")))
                continue
            if ptype != PKT_SAMPLES:
                flush()
                self._error(out, "type", len(pkt), f"expected packet type 0x01 or 0x02, got 0x{ptype:02X}")
                continue
            if len(pkt) != self._packet_len:
                flush()
                self._error(out, "length", len(pkt), f"expected a {self._packet_len}-byte sample packet "
                                                      f"({self.frame_samples} samples), got {len(pkt)} bytes")
                continue
            _, seq, count = SAMPLE_HEADER.unpack_from(pkt)
            if count != self.frame_samples:
                flush()
                self._error(out, "count", len(pkt), f"expected {self.frame_samples} samples, got {count}")
                continue
            payload = pkt[SAMPLE_HEADER.size:-CRC_SIZE]
            if self._held is not None:
                held_index, held_payload = self._held
                self._held = None
                if seq == (held_index + 1) % SEQ_MODULUS:  # the jump is confirmed
                    gap = self.gap_to(held_index)
                    if gap is not None:
                        out.append(gap)
                    run_start = self.next_sample_index
                    run.append(held_payload)
                    self.next_seq += 1
                    self.stats.frames_ok += 1
                    self.stats.samples_ok += self.frame_samples
                else:
                    self._error(out, "sequence", len(pkt), f"a jump to frame {held_index % SEQ_MODULUS} "
                                f"(expected {self.next_seq % SEQ_MODULUS}) was not confirmed by the next "
                                f"frame (got {seq}): rejected")
            ahead = (seq - self.next_seq) % SEQ_MODULUS
            if ahead >= SEQ_MODULUS // 2:
                flush()
                self._error(out, "sequence", len(pkt), f"expected sequence {self.next_seq % SEQ_MODULUS}, "
                            f"got {seq} ({SEQ_MODULUS - ahead} frame(s) behind: duplicate or replay)")
                continue
            if ahead > self.immediate_gap_frames:
                flush()
                self._held = (self.next_seq + ahead, payload)
                continue
            if ahead > 0:
                flush()
                gap = self.gap_to(self.next_seq + ahead)
                if gap is not None:
                    out.append(gap)
            if not run:
                run_start = self.next_sample_index
            run.append(payload)
            self.next_seq += 1
            self.stats.frames_ok += 1
            self.stats.samples_ok += count
        flush()
        return out
