"""The DAQ stream into a run's recording, as the run's procedure sees it (:class:`RecordingStream`):
the bridge configured and streaming, the acquisition (ring buffer, gaps) and the recording's writer,
wherever they run.  The procedure asks for counts and verdicts (samples so far, samples lost in a
window, whether the newest windows are steady), never for samples.

:class:`LocalStream` runs them in the calling process (the bridge's reader thread, the acquisition
and disk threads of ``acquisition.py``): ``station calibrate``, the in-process simulated rig and its
virtual clock.  The daemon's form asks the rig process for the same (``docs/safety.md``, *The DAQ
stream under the rig process*)."""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from drivers.clock import REAL_CLOCK, Clock
from drivers.daq.bridge import DaqBridge, DaqConfig, DaqHardware
from station.recording import ChannelSpec, RecordingWriter, RunMetadata
from station.run.acquisition import Acquisition, RingBuffer
from station.run.steady import SteadyCriteria, is_steady

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StreamEnd:
    """The stream stopped: ``lost`` samples of the run never arrived (filled gaps, recorded as such);
    ``disk_error`` is why the recording could not be written on (None if it could)."""

    lost: int
    disk_error: BaseException | None


class RecordingStream(Protocol):
    """The DAQ stream into one run's recording at a time: :meth:`configure`, :meth:`open` (the
    recording's partial file), :meth:`start`, the run's questions, :meth:`stop`, then
    :meth:`finish` (or :meth:`abandon`); then the next run's :meth:`open`."""

    @property
    def hardware(self) -> DaqHardware | None:
        """What the bridge reported of itself at connect (``HW?``)."""

    @property
    def link_error(self) -> str | None:
        """Why the bridge's link is lost (None while it is not)."""

    @property
    def samples(self) -> int:
        """Samples acquired in this run so far (filled gaps included)."""

    @property
    def lost_samples(self) -> int:
        """Samples of this run that never arrived so far."""

    @property
    def partial_path(self) -> Path:
        """The recording's file while it is open (``<run>.h5.partial``)."""

    @property
    def closed_as(self) -> tuple[str, str] | None:
        """(exit status, reason) of this run's recording when it was closed without the procedure
        asking (the stream under the rig process, on a lost web process); None otherwise."""

    async def configure(self, *, rate_hz: float, range_disp_V: float, range_force_V: float) -> DaqConfig: ...

    async def open(self, out_dir: Path, meta: RunMetadata, channels: tuple[ChannelSpec, ChannelSpec], *,
                   plan: dict[str, Any], min_free_bytes: int) -> None:
        """Create the run's recording (its start document written); raises as ``RecordingWriter``."""

    async def start(self) -> None:
        """The bridge streams; its samples go into the recording (and the ring buffer)."""

    def check(self) -> None:
        """Raise the stream's error (``AcquisitionError``: a stall, a lost link, the disk), if any."""

    async def steady(self, f_set_hz: float, fs: float, crit: SteadyCriteria) -> bool | None:
        """Whether the newest samples are steady (``steady.is_steady``); None while too few arrived."""

    async def lost_between(self, start: int, stop: int) -> int:
        """Samples lost inside [start, stop)."""

    async def add_step(self, **fields: Any) -> None:
        """A recorded step (``RecordingWriter.add_step``'s arguments)."""

    async def stop(self) -> StreamEnd:
        """Stop the bridge's stream (errors logged) and write out what is queued."""

    async def finish(self, status: str, reason: str) -> Path:
        """The stop document written, the recording closed and moved into place (never written again)."""

    async def abandon(self) -> None:
        """Close the recording without a stop document (it stays partial and reads as interrupted)."""

    def close(self) -> None:
        """Let go of the bridge (blocking: its reader thread ends)."""


class LocalStream:
    """:class:`RecordingStream` in this process: ``daq`` (connected), the acquisition on ``clock``."""

    def __init__(self, daq: DaqBridge, clock: Clock = REAL_CLOCK) -> None:
        self.daq = daq
        self.clock = clock
        self._writer: RecordingWriter | None = None
        self._acq: Acquisition | None = None

    @property
    def hardware(self) -> DaqHardware | None:
        return self.daq.hardware

    @property
    def link_error(self) -> str | None:
        return str(self.daq.link_error or "") or None

    @property
    def samples(self) -> int:
        return self._acq.samples if self._acq is not None else 0

    @property
    def lost_samples(self) -> int:
        return sum(n for _, n in self._acq.lost) if self._acq is not None else 0

    @property
    def closed_as(self) -> tuple[str, str] | None:
        return None  # only the procedure closes it here

    @property
    def ring(self) -> RingBuffer | None:
        """The acquisition's ring buffer (this run's; released when the stream stopped)."""
        return self._acq.ring if self._acq is not None else None

    @property
    def partial_path(self) -> Path:
        return self._open_writer().partial_path

    def _open_writer(self) -> RecordingWriter:
        if self._writer is None:
            raise RuntimeError("no recording is open")
        return self._writer

    async def configure(self, *, rate_hz: float, range_disp_V: float, range_force_V: float) -> DaqConfig:
        return await asyncio.to_thread(self.daq.configure, rate_hz=rate_hz, range_disp_V=range_disp_V,
                                       range_force_V=range_force_V)

    async def open(self, out_dir: Path, meta: RunMetadata, channels: tuple[ChannelSpec, ChannelSpec], *,
                   plan: dict[str, Any], min_free_bytes: int) -> None:
        self._acq = None
        self._writer = RecordingWriter(out_dir, meta, channels, plan=plan, min_free_bytes=min_free_bytes)

    async def start(self) -> None:
        writer = self._open_writer()
        daq = self.daq
        assert daq.config is not None
        await asyncio.to_thread(daq.start)
        self._acq = Acquisition(daq.get_event, writer, sample_rate_hz=daq.config.rate_hz,
                                rejected_frames=lambda: daq.decoder.stats.crc_errors + daq.decoder.stats.framing_errors,
                                clock=self.clock)
        self._acq.start()

    def check(self) -> None:
        if self._acq is not None:
            self._acq.check()

    async def steady(self, f_set_hz: float, fs: float, crit: SteadyCriteria) -> bool | None:
        acq = self._acq
        end, need = (acq.samples if acq is not None else 0), crit.samples(fs)
        if acq is None or end < need:
            return None
        d, f = acq.ring.get(end - need, end)
        return await asyncio.to_thread(is_steady, d, f, f_set_hz, fs, crit)

    async def lost_between(self, start: int, stop: int) -> int:
        return self._acq.lost_between(start, stop) if self._acq is not None else 0

    async def add_step(self, **fields: Any) -> None:
        self._open_writer().add_step(**fields)

    async def stop(self) -> StreamEnd:
        try:
            async with asyncio.timeout(3.0):
                await asyncio.to_thread(self.daq.stop)
        except Exception as exc:
            log.warning("shutdown step failed: %s", exc)
        acq = self._acq
        if acq is None:
            return StreamEnd(0, None)
        await asyncio.to_thread(acq.stop)
        return StreamEnd(sum(n for _, n in acq.lost), acq.disk_error)

    async def finish(self, status: str, reason: str) -> Path:
        return self._open_writer().finish(status, reason)

    async def abandon(self) -> None:
        self._open_writer().abandon()

    def close(self) -> None:
        self.daq.close()
