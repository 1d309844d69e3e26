"""The acquisition loop: DAQ stream -> ring buffer (for the procedure) and -> HDF5 (via a disk thread).

Three threads, none waiting on another's slow work:

* the DAQ driver's reader thread decodes frames and queues stream events (``drivers.daq``);
* the **acquisition thread** (here) drains those events into a fixed-size ring buffer and hands
  each block to the disk queue; it never touches the disk and never blocks on processing;
* the **disk thread** appends blocks to the run's recording, which flushes at least every second;
  the blocks that arrive within :data:`WRITE_BATCH_S` are appended together (one append of the
  DAQ's 256-sample frames at 20 kHz, 78 a second, cost the stream process more than the rest of its
  work: each is two resizes and two writes of HDF5 datasets).

Missing samples (a ``SampleGap`` from the driver) keep their positions: the stored raw data is
filled with zeros there and the gap (first sample, count) is recorded, so sample index k is always
the k-th sample since START.  The ring buffer and the disk queue are bounded, so memory does not
grow with run length; a disk too slow to keep up fails the run instead of blocking acquisition.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from drivers.clock import REAL_CLOCK, Clock
from drivers.daq.bridge import StreamEvent, StreamStalled
from drivers.daq.protocol import SampleBlock, SampleGap
from station.recording import RecordingWriter

log = logging.getLogger(__name__)

WRITE_BATCH_S = 0.1  # the disk thread appends the blocks that arrive within this long at once (s)
WRITE_BATCH_MAX = 256  # ... and at most this many blocks at once


@dataclass(frozen=True)
class Block:
    """Samples [first, first + n) of both channels (ADC codes); lost: True for a filled gap."""

    first: int
    displacement: np.ndarray
    force: np.ndarray
    lost: bool = False


class RingBuffer:
    """Last ``capacity`` samples of both channels, indexed by absolute sample number."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        # np.full touches every page now: no page faults (and no RSS growth) while acquiring
        self._d = np.full(capacity, 0, dtype=np.int16)
        self._f = np.full(capacity, 0, dtype=np.int16)
        self._end = 0  # absolute index one past the newest sample
        self._lock = threading.Lock()

    @property
    def end(self) -> int:
        return self._end

    def put(self, first: int, d: np.ndarray, f: np.ndarray) -> None:
        n = d.size
        if first != self._end:
            raise ValueError(f"ring buffer expected sample {self._end}, got {first}")
        if n > self.capacity:
            d, f, first = d[-self.capacity:], f[-self.capacity:], first + n - self.capacity
            n = self.capacity
        with self._lock:
            i = first % self.capacity
            k = min(n, self.capacity - i)
            self._d[i:i + k], self._f[i:i + k] = d[:k], f[:k]
            if k < n:
                self._d[: n - k], self._f[: n - k] = d[k:], f[k:]
            self._end = first + n

    def release(self) -> None:
        """Give the memory back (the run is over; the buffer is a few MB).  ``get`` raises after."""
        with self._lock:
            self._d = self._f = np.zeros(0, dtype=np.int16)
            self.capacity = 0

    def get(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        """Copies of samples [start, stop); raises if they have left the buffer or not arrived."""
        with self._lock:
            if self.capacity == 0:
                raise IndexError("the ring buffer was released at the end of the run")
            if stop > self._end or start < self._end - self.capacity or start > stop:
                raise IndexError(f"samples [{start}, {stop}) not in the buffer "
                                 f"[{max(0, self._end - self.capacity)}, {self._end})")
            idx = np.arange(start, stop) % self.capacity
            return self._d[idx], self._f[idx]


class AcquisitionError(RuntimeError):
    """Acquisition cannot go on (link lost, stream stalled, disk failed); ``reason`` says why."""


class Acquisition:
    """Runs the acquisition and disk threads for one run.

    ``get_event(timeout_s)`` returns the driver's next stream event or None (objects with
    ``first_index``, ``displacement``, ``force`` for data, ``first_index``/``count`` for gaps,
    ``next_sample_index``/``seconds`` for stalls); ``writer`` receives the raw samples.
    ``stall_limit_s``: a stream silent this long (in ``clock`` time: the rig's) fails the run.
    When no event is waiting the acquisition thread waits ``poll_s`` on ``clock`` (so that on a
    virtual clock it is one of the participants time waits for).
    """

    def __init__(self, get_event: Callable[[float], StreamEvent | None], writer: RecordingWriter, *,
                 ring_seconds: float = 60.0, sample_rate_hz: float = 20_000.0,
                 disk_queue_seconds: float = 120.0, stall_limit_s: float = 2.0,
                 storm_fraction: float = 0.5, rejected_frames: Callable[[], int] | None = None,
                 clock: Clock = REAL_CLOCK, poll_s: float = 0.01) -> None:
        self._get_event = get_event
        self._clock = clock
        self._poll_s = poll_s
        self._writer = writer
        self.ring = RingBuffer(int(ring_seconds * sample_rate_hz))
        self._fs = sample_rate_hz
        self._disk_q: queue.Queue[Block | None] = queue.Queue(
            maxsize=max(8, int(disk_queue_seconds * sample_rate_hz / 256)))
        self._stall_limit = stall_limit_s
        self._storm = storm_fraction
        self._rejected = rejected_frames or (lambda: 0)
        self.lost: list[tuple[int, int]] = []
        self.error: AcquisitionError | None = None
        self._stop = threading.Event()
        self._acq = threading.Thread(target=self._acquire, name="acquisition", daemon=True)
        self._disk = threading.Thread(target=self._write, name="disk-writer", daemon=True)
        self.disk_error: BaseException | None = None

    # -- control -------------------------------------------------------------------------------
    def start(self) -> None:
        self._disk.start()
        self._acq.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop acquiring, write out what is queued, and join both threads."""
        self._stop.set()
        self._clock.notify()
        self._acq.join(timeout_s)
        self._disk_q.put(None)
        self._disk.join(timeout_s)
        if not self._acq.is_alive():
            self.ring.release()  # not kept until the procedure object is collected

    @property
    def samples(self) -> int:
        """Samples acquired so far (including filled gaps)."""
        return self.ring.end

    def lost_between(self, start: int, stop: int) -> int:
        """Number of lost samples inside [start, stop) (gaps are kept in order: scan from the newest)."""
        total = 0
        for a, n in reversed(list(self.lost)):
            if a + n <= start:
                break
            total += max(0, min(stop, a + n) - max(start, a))
        return total

    def check(self) -> None:
        """Raise the acquisition's or the disk's error, if any (called by the procedure)."""
        if self.error is not None:
            raise self.error
        if self.disk_error is not None:
            raise AcquisitionError(f"recording cannot be written: {self.disk_error}")

    def wait_for(self, sample: int, timeout_s: float) -> None:
        """Block until ``sample`` samples have been acquired; raises on errors or time-out."""
        deadline = self._clock.monotonic() + timeout_s
        while self.ring.end < sample:
            self.check()
            if self._clock.monotonic() > deadline:
                raise AcquisitionError(f"DAQ delivered {self.ring.end} samples, {sample} awaited "
                                       f"within {timeout_s:.1f} s")
            self._clock.sleep(0.01)

    # -- threads -----------------------------------------------------------------------------------
    def _enqueue(self, block: Block) -> None:
        try:
            self._disk_q.put_nowait(block)
        except queue.Full:
            self.error = AcquisitionError("disk writer fell more than the disk queue behind; "
                                          "run stopped rather than blocking acquisition")
            self._stop.set()

    def _acquire(self) -> None:
        clock = self._clock
        quiet_since = clock.monotonic()
        rejected_at_quiet = self._rejected()
        try:
            while not self._stop.is_set():
                ev = self._get_event(0.0)
                if ev is None:
                    clock.wait_for(self._stop.is_set, self._poll_s)
                if ev is None or isinstance(ev, StreamStalled):
                    if clock.monotonic() - quiet_since >= self._stall_limit:
                        bad = self._rejected() - rejected_at_quiet
                        if bad:
                            raise AcquisitionError(
                                f"DAQ stream corrupted: {bad} frames rejected (CRC/framing) and no valid "
                                f"frame for {self._stall_limit:.1f} s (next sample {self.ring.end})")
                        raise AcquisitionError(f"DAQ stream stalled: no data for {self._stall_limit:.1f} s "
                                               f"(next sample {self.ring.end})")
                    continue
                quiet_since = clock.monotonic()  # data or gap: the stream is alive
                rejected_at_quiet = self._rejected()
                match ev:
                    case SampleBlock(first_index=first, displacement=d, force=f):
                        if first > self.ring.end:  # a gap the driver did not report separately
                            self._gap(self.ring.end, first - self.ring.end)
                        self.ring.put(first, d, f)
                        self._enqueue(Block(first, d, f))
                    case SampleGap(first_index=first, count=count):
                        self._gap(first, count)
        except AcquisitionError as exc:
            self.error = exc
        except Exception as exc:  # the driver's link error and anything else ends the run
            self.error = AcquisitionError(f"DAQ link lost: {exc}")
        if self.error is not None:
            log.error("acquisition stopped: %s", self.error)

    def _gap(self, first: int, count: int) -> None:
        if first != self.ring.end:
            if first < self.ring.end:
                count -= self.ring.end - first
                first = self.ring.end
            else:
                self._gap(self.ring.end, first - self.ring.end)
        if count <= 0:
            return
        self.lost.append((first, count))
        z = np.zeros(count, dtype=np.int16)
        self.ring.put(first, z, z)
        self._enqueue(Block(first, z, z, lost=True))
        window = int(self._fs)  # one second
        end = self.ring.end
        if end >= window and self.lost_between(end - window, end) > self._storm * window:
            raise AcquisitionError(f"DAQ stream corrupted: {self.lost_between(end - window, end)} of the "
                                   f"last {window} samples lost (CRC errors or dropped frames)")

    def _write(self) -> None:
        last_flush = time.monotonic()
        while True:
            batch, done = self._next_batch()
            try:
                if batch:
                    self._append(batch)
                if time.monotonic() - last_flush >= 0.5:
                    self._writer.flush()
                    last_flush = time.monotonic()
            except BaseException as exc:  # full disk, I/O error: stop writing, keep what is flushed
                self.disk_error = exc
                log.error("disk writer failed: %s", exc)
                self._stop.set()
                return
            if done:
                break

    def _next_batch(self) -> tuple[list[Block], bool]:
        """The blocks queued within :data:`WRITE_BATCH_S` of the first (none after 0.25 s without
        one), and whether the end (``None``) came after them."""
        try:
            block = self._disk_q.get(timeout=0.25)
        except queue.Empty:
            return [], False
        batch: list[Block] = []
        until = time.monotonic() + WRITE_BATCH_S
        while block is not None:
            batch.append(block)
            wait = until - time.monotonic()
            if len(batch) >= WRITE_BATCH_MAX or wait <= 0:
                return batch, False
            try:
                block = self._disk_q.get(timeout=wait)
            except queue.Empty:
                return batch, False
        return batch, True

    def _append(self, batch: list[Block]) -> None:
        """The blocks (consecutive samples) appended to the recording in one go, then their gaps."""
        if len(batch) == 1:
            self._writer.append(batch[0].displacement, batch[0].force)
        else:
            self._writer.append(np.concatenate([b.displacement for b in batch]),
                                np.concatenate([b.force for b in batch]))
        for b in batch:
            if b.lost:
                self._writer.add_lost(b.first, b.displacement.size)
