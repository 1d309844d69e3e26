"""A run's files and what is made from them: the recording (kept inside the recordings folder,
one access at a time from the daemon), plots, the report and the discrepancy analysis (rendered in
the render worker, cached)."""

from __future__ import annotations

import asyncio
import contextlib
from collections import OrderedDict
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from station.lab.integrity import check_recording
from station.recording.stored import results_version
from station.report.names import PLOT_NAMES
from station.service import worker
from station.service.errors import ResultNotStoredError, RunStateError
from station.service.store import RunRow

CACHE_ENTRIES = 64  # rendered plots and reports kept in memory (a few 100 kB each)


@dataclass
class _Lock:
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    users: int = 0


class Artifacts:
    """Recordings and their renderings; ``get_row`` looks a run up (live or stored)."""

    def __init__(self, recordings_dir: Path, render_pool: worker.WorkerPool,
                 get_row: Callable[[str], Awaitable[RunRow]]) -> None:
        self.recordings_dir = recordings_dir
        self.render_pool = render_pool
        self._get_row = get_row
        self._file_locks: dict[str, _Lock] = {}
        self._cache: OrderedDict[tuple[str, str], bytes | str] = OrderedDict()

    def recording_path(self, row: RunRow) -> Path:
        """The run's recording, always inside the recordings folder."""
        if not row.recording:
            raise RunStateError(f"run {row.id} has no recording")
        base = self.recordings_dir
        p = (base / Path(row.recording).name).resolve()
        if p.parent != base:
            raise RunStateError(f"run {row.id}: recording outside the recordings folder refused")
        if not p.is_file():
            raise RunStateError(f"run {row.id}: recording {p.name} is missing from the recordings folder")
        return p

    @contextlib.asynccontextmanager
    async def file_lock(self, run_id: str) -> AsyncIterator[None]:
        """Serialises the daemon's own accesses to one recording (HDF5 locks files).  The lock is
        forgotten when nobody holds or waits for it (memory stays flat over many runs)."""
        entry = self._file_locks.setdefault(run_id, _Lock())
        entry.users += 1
        try:
            async with entry.lock:
                yield
        finally:
            entry.users -= 1
            if entry.users == 0:
                del self._file_locks[run_id]

    async def read_file(self, run_id: str, fn: Callable[[Path], Any]) -> Any:
        path = self.recording_path(await self._get_row(run_id))
        async with self.file_lock(run_id):
            return await asyncio.to_thread(fn, path)

    async def stream_file(self, run_id: str, chunk: int = 1 << 20) -> AsyncIterator[bytes]:
        path = self.recording_path(await self._get_row(run_id))
        async with self.file_lock(run_id):
            f = await asyncio.to_thread(open, path, "rb")
            try:
                while True:
                    data = await asyncio.to_thread(f.read, chunk)
                    if not data:
                        return
                    yield data
            finally:
                f.close()

    async def _cached(self, key: tuple[str, str], make: Callable[[], Awaitable[Any]]) -> Any:
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        value = await make()
        if value is None:
            return None
        self._cache[key] = value
        self._trim()
        return value

    def _trim(self) -> None:
        while len(self._cache) > CACHE_ENTRIES:
            self._cache.popitem(last=False)

    async def _completed_path(self, run_id: str) -> Path:
        row = await self._get_row(run_id)
        if row.state != "completed":
            raise RunStateError(f"run {run_id} is {row.state}: plots, report and analyses exist for "
                                "completed runs only")
        return self.recording_path(row)

    async def _locked_job(self, run_id: str, fn: Callable[..., Any], *args: Any) -> Any:
        async with self.file_lock(run_id):
            return await self.render_pool.run(fn, *args)

    async def plot(self, run_id: str, name: str) -> bytes | None:
        path = await self._completed_path(run_id)
        if name not in PLOT_NAMES:
            return None
        version = await asyncio.to_thread(results_version, path)  # a result stored later shows at once
        return await self._cached((run_id, f"plot:{name}:{hash(version)}"),
                                  lambda: self._locked_job(run_id, worker.plot_job, str(path), name))

    async def verified(self, row: RunRow, *, required: bool = False) -> str:
        """The recording's SHA-256, checked against the one stored when it was closed
        (RecordingTamperedError naming the file on a mismatch; ``required``: a run recorded before
        hashes were stored is refused too).  What a report or a certificate reads first."""
        return await asyncio.to_thread(check_recording, self.recording_path(row), row.recording_sha256,
                                       required=required)

    async def report(self, run_id: str) -> str:
        path = await self._completed_path(run_id)
        await self.verified(await self._get_row(run_id))
        version = await asyncio.to_thread(results_version, path)
        return await self._cached((run_id, f"report:{hash(version)}"),
                                  lambda: self._locked_job(run_id, worker.report_job, str(path)))

    async def report_pdf(self, run_id: str) -> bytes:
        """The report's HTML page as PDF (rendered in the render worker, cached like the page)."""
        path = await self._completed_path(run_id)
        version = await asyncio.to_thread(results_version, path)
        out: bytes = await self._cached((run_id, f"report.pdf:{hash(version)}"),
                                        lambda: self._locked_job(run_id, worker.report_pdf_job, str(path)))
        return out

    async def _register(self, run_id: str) -> dict[str, Any]:
        """The lab register's records as the run used them (transducer, standards)."""
        import json

        row = await self._get_row(run_id)
        return {"transducer": json.loads(row.transducer_json or "{}"),
                "standards": json.loads(row.standards_json or "[]")}

    async def certificate(self, run_id: str, ext: str) -> bytes:
        """The run's certificate (the issued one, else the draft) as html, pdf or xml."""
        path = await self._completed_path(run_id)
        out: bytes = await self._locked_job(run_id, worker.certificate_job, str(path), ext,
                                            await self._register(run_id))
        return out

    async def issue_certificate(self, run_id: str, prepared_by: str, approver: str, roles: dict[str, str],
                                replaces: str | None, reason: str) -> dict[str, Any]:
        """Issue the run's certificate (the approval's checks made by the caller: RunManager.approve)."""
        path = await self._completed_path(run_id)
        out: dict[str, Any] = await self._locked_job(run_id, worker.issue_job, str(path), prepared_by, approver, roles,
                                                     replaces, reason, await self._register(run_id))
        return out

    async def certificates(self, transducer_id: str | None) -> list[dict[str, Any]]:
        from station.certificate.register import FOLDER, list_issued

        return await asyncio.to_thread(list_issued, self.recordings_dir / FOLDER, transducer_id)

    async def issued_certificate(self, number: str, ext: str) -> bytes:
        from station.certificate.register import FOLDER, issued_file

        return await asyncio.to_thread(issued_file, self.recordings_dir / FOLDER, number, ext)

    async def campaign(self, run_ids: list[str]) -> dict[str, Any]:
        """The joint identification of completed runs in the render worker (``worker.campaign_job``),
        every recording held against the daemon's other accesses meanwhile (locked in id order)."""
        paths = []
        for run_id in run_ids:
            row = await self._get_row(run_id)
            if row.state != "completed":
                raise RunStateError(f"run {run_id} is {row.state}: only completed runs take part in a campaign")
            paths.append(str(self.recording_path(row)))
        async with contextlib.AsyncExitStack() as stack:
            for run_id in sorted(set(run_ids)):
                await stack.enter_async_context(self.file_lock(run_id))
            out: dict[str, Any] = await self.render_pool.run(worker.campaign_job, paths)
        return out

    async def discrepancy(self, run_id: str, max_effects: int) -> dict[str, Any]:
        """Compute the model-gap analysis in the render worker and store it beside the recording
        (behind an authenticated POST only)."""
        path = await self._completed_path(run_id)
        out = await self._locked_job(run_id, worker.discrepancy_job, str(path), max_effects)
        return out

    async def stored_discrepancy(self, run_id: str, max_effects: int) -> dict[str, Any]:
        """The stored model-gap analysis (read only); ResultNotStoredError names how to make it."""
        path = await self._completed_path(run_id)
        out = await asyncio.to_thread(worker.stored_discrepancy, path, max_effects)
        if out is None:
            raise ResultNotStoredError(f"run {run_id}: no model-gap analysis with max_effects={max_effects} is "
                                       f"stored; POST /runs/{run_id}/discrepancy?max_effects={max_effects} "
                                       "(bearer token) computes and stores it")
        return dict(out)

