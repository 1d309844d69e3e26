"""Byte-exact tests of the DAQ-bridge wire protocol and its decoder (no I/O)."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.daq.protocol import (
    DaqProtocolError,
    FrameError,
    Reply,
    SampleBlock,
    SampleGap,
    StreamDecoder,
    crc32,
    encode_command,
    encode_reply,
    encode_samples,
    slip_escape,
    slip_unescape,
)


def bitwise_crc32(data: bytes) -> int:
    """Independent CRC-32/ISO-HDLC (reflected 0xEDB88320, init/xorout 0xFFFFFFFF)."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0xEDB88320 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def test_crc_check_value_and_agreement() -> None:
    assert crc32(b"123456789") == 0xCBF43926
    assert bitwise_crc32(b"123456789") == 0xCBF43926
    data = bytes(range(256)) * 3
    assert crc32(data) == bitwise_crc32(data)


def test_slip_escaping_is_byte_exact() -> None:
    assert slip_escape(b"\x01\xc0\x02\xdb\x03") == b"\x01\xdb\xdc\x02\xdb\xdd\x03"
    assert slip_escape(b"\xdb\xdc") == b"\xdb\xdd\xdc"  # literal ESC ESC_END must not decode as END
    assert slip_unescape(b"\xdb\xdd\xdc") == b"\xdb\xdc"
    for raw in (b"\xc0\xc0\xdb\xdb", b"\xdb\xdd\xdb\xdc", bytes(range(256))):
        assert slip_unescape(slip_escape(raw)) == raw
    with pytest.raises(DaqProtocolError, match="followed by 0xDC or 0xDD"):
        slip_unescape(b"\x01\xdb\x02")


def test_sample_frame_bytes_exact() -> None:
    wire = encode_samples(1, np.array([1, -2], np.int16), np.array([192, 219], np.int16))
    raw = (b"\x01"                      # type: samples
           b"\x01\x00\x00\x00"          # seq 1 (u32 LE)
           b"\x02\x00"                  # count 2 (u16 LE)
           b"\x01\x00" b"\xc0\x00"      # disp 1, force 192 (0x00C0: needs escaping)
           b"\xfe\xff" b"\xdb\x00")     # disp -2, force 219 (0x00DB: needs escaping)
    crc = bitwise_crc32(raw).to_bytes(4, "little")
    escaped_crc = crc.replace(b"\xdb", b"\xdb\xdd").replace(b"\xc0", b"\xdb\xdc")
    expected = (b"\xc0" + b"\x01\x01\x00\x00\x00\x02\x00\x01\x00\xdb\xdc\x00\xfe\xff\xdb\xdd\x00"
                + escaped_crc + b"\xc0")
    assert wire == expected


def test_command_and_reply_frames_bytes_exact() -> None:
    body = b"\x10IDN?"
    assert encode_command("IDN?") == b"\xc0" + body + bitwise_crc32(body).to_bytes(4, "little") + b"\xc0"
    body = b"\x02OK STOP frames=3 samples=768"
    wire = encode_reply("OK STOP frames=3 samples=768")
    assert slip_unescape(wire[1:-1]) == body + bitwise_crc32(body).to_bytes(4, "little")


def frames(seqs: list[int], n: int = 8) -> list[bytes]:
    out = []
    for s in seqs:
        d = np.arange(s * n, (s + 1) * n, dtype=np.int16)
        out.append(encode_samples(s, d, -d))
    return out


def blocks_and_gaps(events: list) -> tuple[np.ndarray, list[tuple[int, int]]]:
    idx = [np.arange(e.first_index, e.first_index + e.count) for e in events if isinstance(e, SampleBlock)]
    for e in events:
        if isinstance(e, SampleBlock):  # every sample carries its own index as value (see frames())
            assert np.array_equal(e.displacement, np.arange(e.first_index, e.first_index + e.count))
            assert np.array_equal(e.force, -e.displacement)
    gaps = [(e.first_index, e.count) for e in events if isinstance(e, SampleGap)]
    return (np.concatenate(idx) if idx else np.array([], int)), gaps


def test_clean_stream_in_arbitrary_chunks_is_one_contiguous_run() -> None:
    stream = b"".join(frames(list(range(20))))
    rng = np.random.default_rng(5)
    dec = StreamDecoder(8)
    events: list = []
    pos = 0
    while pos < len(stream):
        step = int(rng.integers(1, 60))
        events += dec.feed(stream[pos:pos + step])
        pos += step
    idx, gaps = blocks_and_gaps(events)
    assert np.array_equal(idx, np.arange(160)) and gaps == []
    assert dec.stats.frames_ok == 20 and dec.stats.crc_errors == 0 and dec.stats.samples_lost == 0


def test_garbage_between_frames_is_skipped_without_losing_samples() -> None:
    f = frames([0, 1, 2, 3])
    garbage = bytes([0x55, 0xC0, 0xDB, 0x01, 0xFF, 0xC0, 0x13, 0x37])
    dec = StreamDecoder(8)
    events = dec.feed(f[0] + garbage + f[1] + b"\x00\x01\x02" + f[2] + garbage * 3 + f[3])
    idx, gaps = blocks_and_gaps(events)
    assert np.array_equal(idx, np.arange(32)) and gaps == []
    assert dec.stats.framing_errors + dec.stats.crc_errors > 0  # the garbage was seen and counted
    assert all(isinstance(e, FrameError) for e in events if not isinstance(e, SampleBlock))


def test_crc_error_is_counted_and_reported_as_an_exact_gap() -> None:
    f = frames([0, 1, 2, 3])
    bad = bytearray(f[2])
    bad[10] ^= 0x01  # one bit flipped inside the payload
    dec = StreamDecoder(8)
    events = dec.feed(f[0] + f[1] + bytes(bad) + f[3])
    idx, gaps = blocks_and_gaps(events)
    assert gaps == [(16, 8)]
    assert np.array_equal(idx, np.r_[0:16, 24:32])
    errs = [e for e in events if isinstance(e, FrameError)]
    assert [e.kind for e in errs] == ["crc"]
    assert errs[0].next_sample_index == 16
    assert errs[0].stream_offset == len(f[0]) + len(f[1]) + len(bad)  # just past its closing END
    assert dec.stats.crc_errors == 1 and dec.stats.samples_lost == 8


def test_sequence_gaps_report_first_missing_index_and_count() -> None:
    f = frames([0, 1, 4, 5, 9])
    dec = StreamDecoder(8)
    events = dec.feed(b"".join(f))
    _, gaps = blocks_and_gaps(events)
    assert gaps == [(16, 16), (48, 24)]
    assert dec.stats.gaps == 2 and dec.stats.frames_lost == 5 and dec.stats.samples_lost == 40
    # the stream order of events is preserved: block, gap, block, gap, block
    kinds = [type(e).__name__ for e in events]
    assert kinds == ["SampleBlock", "SampleGap", "SampleBlock", "SampleGap", "SampleBlock"]
    # a trailing gap (frames lost before STOP) is accounted for by gap_to(frames_sent)
    tail = dec.gap_to(12)
    assert tail is not None and (tail.first_index, tail.count) == (80, 16)


def test_wrong_length_count_type_and_old_sequence_are_rejected() -> None:
    dec = StreamDecoder(8)
    short = encode_samples(0, np.zeros(4, np.int16), np.zeros(4, np.int16))  # valid CRC, 4 samples
    events = dec.feed(short)
    assert [e.kind for e in events if isinstance(e, FrameError)] == ["length"]
    assert "expected a 43-byte sample packet (8 samples), got 27 bytes" in events[0].detail
    f = frames([0, 1])
    events = dec.feed(f[0] + f[1] + f[0])  # a replayed old frame
    assert [e.kind for e in events if isinstance(e, FrameError)] == ["sequence"]
    from drivers.daq.protocol import encode_packet
    events = dec.feed(encode_packet(0x7F, b"hello"))
    assert events[0].kind == "type" and "got 0x7F" in events[0].detail
    assert dec.stats.samples_ok == 16


def test_replies_are_routed_in_stream_order() -> None:
    f = frames([0, 1])
    dec = StreamDecoder(8)
    events = dec.feed(f[0] + encode_reply("OK STAT state=streaming") + f[1])
    assert [type(e).__name__ for e in events] == ["SampleBlock", "Reply", "SampleBlock"]
    assert isinstance(events[1], Reply) and events[1].text == "OK STAT state=streaming"


def test_random_corruption_never_delivers_a_wrong_sample() -> None:
    rng = np.random.default_rng(11)
    clean = frames(list(range(200)))
    stream = bytearray(b"".join(clean))
    for pos in rng.integers(0, len(stream), 60):
        stream[pos] = int(rng.integers(0, 256))
    dec = StreamDecoder(8)
    events = dec.feed(bytes(stream))
    idx, gaps = blocks_and_gaps(events)  # asserts each delivered sample equals its index
    missing = set(range(1600)) - set(idx.tolist())
    reported = {i for first, n in gaps for i in range(first, first + n)}
    last_delivered = int(idx.max())
    assert {i for i in missing if i < last_delivered} == reported
    assert dec.stats.crc_errors + dec.stats.framing_errors > 0


def test_tagged_command_and_reply_bytes_exact() -> None:
    body = b"\x10#7 STAT?"
    assert encode_command("STAT?", "#7") == b"\xc0" + body + bitwise_crc32(body).to_bytes(4, "little") + b"\xc0"
    from drivers.daq.protocol import split_tag
    assert split_tag("#7 OK STAT state=idle") == ("#7", "OK STAT state=idle")
    assert split_tag("OK STAT state=idle") == (None, "OK STAT state=idle")
    for bad in ("7", "#", "#a b", "#" + "9" * 16):
        with pytest.raises(ValueError, match="command tag: expected"):
            encode_command("IDN?", bad)


def test_a_confirmed_long_jump_is_one_gap_and_an_unconfirmed_one_is_rejected() -> None:
    dec = StreamDecoder(8, immediate_gap_frames=4)
    events = dec.feed(b"".join(frames([0, 1, 100])))
    assert blocks_and_gaps(events)[1] == []  # frame 100 held: not yet believed
    events = dec.feed(b"".join(frames([101, 102])))
    idx, gaps = blocks_and_gaps(events)
    assert gaps == [(16, 98 * 8)] and idx.tolist() == list(range(800, 824))
    # an unconfirmed jump: the held frame is rejected when the next frame continues the old sequence
    dec = StreamDecoder(8, immediate_gap_frames=4)
    events = dec.feed(b"".join(frames([0, 1, 50, 2, 3])))
    idx, gaps = blocks_and_gaps(events)
    assert gaps == [] and idx.tolist() == list(range(32))
    assert [e.kind for e in events if isinstance(e, FrameError)] == ["sequence"]
    # a held frame at STOP: delivered if the bridge produced it, rejected otherwise
    dec = StreamDecoder(8, immediate_gap_frames=4)
    dec.feed(b"".join(frames([0, 10])))
    idx, gaps = blocks_and_gaps(dec.finish(12))
    assert gaps == [(8, 72), (88, 8)] and idx.tolist() == list(range(80, 88))
    dec = StreamDecoder(8, immediate_gap_frames=4)
    dec.feed(b"".join(frames([0, 10])))
    events = dec.finish(5)
    assert [e.kind for e in events if isinstance(e, FrameError)] == ["sequence"]
    assert blocks_and_gaps(events)[1] == [(8, 32)]
