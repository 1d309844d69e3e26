"""A run's files and what is made from them: the recording (kept inside the recordings folder,
one access at a time from the daemon), plots, the report and the discrepancy analysis (rendered in
the render worker, cached).

Nothing here reads a run's files before :meth:`Artifacts.guard` has compared them with the audit
chain (``station.lab.chain``): the recording with the hash its closing entry holds, every results
file with the hash of the latest entry that wrote it, nothing added beside them.  A mismatch is a
RecordingTamperedError naming each file (409).  What the daemon writes beside a recording it vouches
for at once, under the recording's lock (:meth:`Artifacts.seal`)."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
from collections import OrderedDict
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from station.lab import audit, certificates, chain
from station.lab.integrity import RecordingTamperedError, check_recording, sha256_file
from station.lab.issued import CertificateNotFoundError
from station.lab.store import RunRow, Store
from station.recording.stored import results_version
from station.report.names import PLOT_NAMES, plotted
from station.service import worker
from station.service.db import DbAccess
from station.service.errors import ResultNotStoredError, RunStateError

CACHE_ENTRIES = 64  # rendered plots and reports kept in memory (a few 100 kB each)


@dataclass
class _Lock:
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    users: int = 0


class Artifacts:
    """Recordings and their renderings; ``get_row`` looks a run up (live or stored)."""

    def __init__(self, recordings_dir: Path, render_pool: worker.WorkerPool,
                 get_row: Callable[[str], Awaitable[RunRow]], db: DbAccess | None = None) -> None:
        self.recordings_dir = recordings_dir
        self.render_pool = render_pool
        self._get_row = get_row
        self.db = db  # None: no audit chain to check against (one class's tests)
        self.busy: Callable[[str], bool] = lambda run_id: False  # a run whose results are being written
        self._file_locks: dict[str, _Lock] = {}
        self._cache: OrderedDict[tuple[str, str], bytes | str] = OrderedDict()
        self._hashes: dict[Path, tuple[tuple[int, int, int, int], str]] = {}

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

    # ------------------------------------------------------------------ the chain's word on the files
    def _sha256(self, path: Path) -> str:
        """A file's SHA-256, taken again whenever its inode, size, mtime or ctime changed (ctime
        cannot be set back by a user: a file written since is always hashed again)."""
        st = path.stat()
        key = (st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
        got = self._hashes.get(path)
        if got is not None and got[0] == key:
            return got[1]
        sha = sha256_file(path)
        self._hashes[path] = (key, sha)
        while len(self._hashes) > 4 * CACHE_ENTRIES:
            self._hashes.pop(next(iter(self._hashes)))
        return sha

    def _compare(self, row: RunRow, path: Path, expected: dict[str, str], required: bool,
                 writing: bool = False) -> str:
        """``writing``: a further method of the run is being computed by the daemon now; the result
        file it is writing is not vouched for yet, so an added file is not judged (every file the
        chain vouches for still is)."""
        rec_key, prefix = chain.run_files(row.id, path.name)
        want = expected.get(rec_key)
        if want is None:  # a run from before the chain: the SHA-256 its row holds
            sha = check_recording(path, row.recording_sha256, required=required)
        else:
            if row.recording_sha256 is not None and row.recording_sha256 != want:
                raise RecordingTamperedError(f"{path.name}: the SHA-256 in the runs table ({row.recording_sha256[:16]}"
                                             f"...) is not the one the audit trail holds ({want[:16]}...); refused")
            chain.check_files(self.recordings_dir, {rec_key: want}, [rec_key], f"run {row.id}", self._sha256)
            sha = want
        results = {k: v for k, v in expected.items() if k.startswith(prefix)}
        if results:  # results vouched for: exactly those, as written
            present = chain.results_hashes_names(path)
            if writing:
                present = [k for k in present if k in results]
            chain.check_files(self.recordings_dir, results, present, f"run {row.id}", self._sha256)
        return sha

    async def guard(self, row: RunRow, *, required: bool = False) -> str:
        """The run's recording and results compared with the audit chain before anything reads them
        (module docstring); returns the recording's SHA-256.  ``required``: a run from before the
        chain without a stored SHA-256 is refused too (a certificate needs it)."""
        path = self.recording_path(row)
        if self.db is None:
            return await asyncio.to_thread(check_recording, path, row.recording_sha256, required=required)

        def expected(store: Store) -> dict[str, str]:
            with store.reading() as db:
                return chain.expected_files(db, row.id)
        for attempt in (0, 1):
            try:
                # what the chain vouches for, read under the recording's lock: a writer holds it from
                # writing a results file until its entry is in the chain
                async with self.file_lock(row.id):
                    want = await self.db.read(expected)
                    return await asyncio.to_thread(self._compare, row, path, want, required, self.busy(row.id))
            except RecordingTamperedError:
                if attempt or not self.busy(row.id):
                    raise
            await asyncio.sleep(1.0)  # a method's result was being stored as we looked: once more
        raise AssertionError("unreachable")

    async def seal(self, row: RunRow, who: str, action: str, details: dict[str, Any]) -> int:
        """Vouch for the run's results as they are now (audit entry with their hashes); the caller
        holds the recording's lock since it wrote them."""
        path = self.recording_path(row)
        if self.db is None:
            return 0
        return await self.db.call(lambda s: audit.seal_results(s, who, action, row.id, path, details))

    async def checked_path(self, run_id: str) -> Path:
        """The run's recording, its files checked against the chain first (:meth:`guard`)."""
        row = await self._get_row(run_id)
        await self.guard(row)
        return self.recording_path(row)

    async def read_file(self, run_id: str, fn: Callable[[Path], Any]) -> Any:
        path = await self.checked_path(run_id)
        async with self.file_lock(run_id):
            return await asyncio.to_thread(fn, path)

    async def stream_file(self, run_id: str, chunk: int = 1 << 20) -> AsyncIterator[bytes]:
        path = await self.checked_path(run_id)
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

    async def _completed(self, run_id: str) -> tuple[Path, str]:
        """The completed run's recording and its SHA-256, both checked against the chain (:meth:`guard`)."""
        row = await self._get_row(run_id)
        if row.state != "completed":
            raise RunStateError(f"run {run_id} is {row.state}: plots, report and analyses exist for "
                                "completed runs only")
        sha = await self.guard(row)
        return self.recording_path(row), sha

    async def _completed_path(self, run_id: str) -> Path:
        return (await self._completed(run_id))[0]

    async def _locked_job(self, run_id: str, fn: Callable[..., Any], *args: Any) -> Any:
        async with self.file_lock(run_id):
            return await self.render_pool.run(fn, *args)

    async def plot(self, run_id: str, name: str) -> bytes | None:
        path = await self._completed_path(run_id)
        if name not in PLOT_NAMES:
            return None
        version = await asyncio.to_thread(results_version, path)  # a result stored later shows at once
        return await self._cached((run_id, f"plot:{name}:{hash(plotted(version))}"),
                                  lambda: self._locked_job(run_id, worker.plot_job, str(path), name))

    async def verified(self, row: RunRow, *, required: bool = False) -> str:
        """The recording's SHA-256, checked against the one stored when it was closed
        (RecordingTamperedError naming the file on a mismatch; ``required``: a run recorded before
        hashes were stored is refused too).  What a report or a certificate reads first."""
        return await self.guard(row, required=required)

    async def _report_html(self, run_id: str, path: Path, version: Any) -> str:
        out: str = await self._cached((run_id, f"report:{hash(version)}"),
                                      lambda: self._locked_job(run_id, worker.report_job, str(path)))
        return out

    async def report(self, run_id: str) -> str:
        path = await self._completed_path(run_id)
        version = await asyncio.to_thread(results_version, path)
        return await self._report_html(run_id, path, version)

    async def _as_pdf(self, page: Callable[[], Awaitable[str]]) -> bytes:
        """The PDF of an HTML page (``page``: the page, kept like any rendering) in the render worker:
        a page asked for as HTML before is not drawn again for its PDF, nor the other way round."""
        return await self.render_pool.run(worker.pdf_job, await page())

    async def report_pdf(self, run_id: str) -> bytes:
        """The report's HTML page as PDF (``station.report.pdf``: the page through the HTML-to-PDF
        engine; the page and the PDF each rendered in the render worker, cached)."""
        path = await self._completed_path(run_id)
        version = await asyncio.to_thread(results_version, path)
        out: bytes = await self._cached((run_id, f"report.pdf:{hash(version)}"),
                                        lambda: self._as_pdf(lambda: self._report_html(run_id, path, version)))
        return out

    async def _register(self, run_id: str) -> dict[str, Any]:
        """The lab register's records as the run used them (transducer, standards)."""
        row = await self._get_row(run_id)
        return {"transducer": json.loads(row.transducer_json or "{}"),
                "standards": json.loads(row.standards_json or "[]")}

    async def certificate(self, run_id: str, ext: str) -> bytes:
        """The run's certificate (the one in force by the audit trail, else the draft) as html, pdf
        or xml (a draft's DCC is marked as a draft)."""
        path = await self._completed_path(run_id)
        if self.db is not None:
            live = await self.db.read(lambda s: certificates.live_of_run(s, run_id))
            if live is not None:
                return await self.issued_certificate(live["number"], ext)
        register = await self._register(run_id)
        version = await asyncio.to_thread(results_version, path)
        # a draft is a function of the recording, its results and the register's records the run used
        # (no date in it): kept like the report, drawn again when a result is stored
        drawn = hash((version, json.dumps(register, sort_keys=True)))

        def form(ext: str) -> Awaitable[bytes]:
            return self._cached((run_id, f"certificate.{ext}:{drawn}"), lambda: self._locked_job(
                run_id, worker.certificate_job, str(path), ext, register))

        async def page() -> str:
            return (await form("html")).decode()
        # the draft's PDF is its HTML page through the HTML-to-PDF engine (``certificate.issue.run_document``)
        out: bytes = await (self._cached((run_id, f"certificate.pdf:{drawn}"), lambda: self._as_pdf(page))
                            if ext == "pdf" else form(ext))
        return out

    async def issue_certificate(self, run_id: str, prepared_by: str, approver: str, roles: dict[str, str],
                                replaces: str | None, reason: str, number: str,
                                signature: dict[str, str]) -> dict[str, Any]:
        """Write the run's certificate under ``number`` (the rules checked by the caller:
        RunManager.issue_certificate); its record and the SHA-256 of each file."""
        path = await self._completed_path(run_id)
        out: dict[str, Any] = await self._locked_job(run_id, worker.issue_job, str(path), prepared_by, approver, roles,
                                                     replaces, reason, await self._register(run_id), number,
                                                     signature)
        return out

    async def certificates(self, transducer_id: str | None) -> list[dict[str, Any]]:
        """The issued certificates as the audit trail records them (never from the folder's files)."""
        if self.db is None:
            return []
        return await self.db.read(lambda s: certificates.issued(s, transducer_id))

    async def issued_certificate(self, number: str, ext: str) -> bytes:
        """An issued certificate's file as issued: compared with the SHA-256 its issue entry holds."""
        if self.db is None:
            raise CertificateNotFoundError(f"no issued certificate {number}")
        c = await self.db.read(lambda s: certificates.one(s, number))
        key = certificates.file_key(number, ext)
        if key not in c["files"]:
            raise CertificateNotFoundError(f"certificate {number} has no .{ext} form")
        try:  # the bytes served are the bytes compared
            data = await asyncio.to_thread((self.recordings_dir / key).read_bytes)
        except FileNotFoundError:
            raise RecordingTamperedError(f"certificate {number}: {key} is missing; refused") from None
        if hashlib.sha256(data).hexdigest() != c["files"][key]:
            raise RecordingTamperedError(f"certificate {number}: {key} was changed after it was issued (its SHA-256 "
                                         "is not the one the issue entry holds); refused")
        return data

    async def campaign(self, run_ids: list[str]) -> dict[str, Any]:
        """The joint identification of completed runs in the render worker (``worker.campaign_job``),
        every recording held against the daemon's other accesses meanwhile (locked in id order)."""
        paths = []
        for run_id in run_ids:
            row = await self._get_row(run_id)
            if row.state != "completed":
                raise RunStateError(f"run {run_id} is {row.state}: only completed runs take part in a campaign")
            await self.guard(row)
            paths.append(str(self.recording_path(row)))
        async with contextlib.AsyncExitStack() as stack:
            for run_id in sorted(set(run_ids)):
                await stack.enter_async_context(self.file_lock(run_id))
            out: dict[str, Any] = await self.render_pool.run(worker.campaign_job, paths)
        return out

    async def discrepancy(self, run_id: str, max_effects: int, who: str) -> dict[str, Any]:
        """Compute the model-gap analysis in the render worker and store it beside the recording
        (behind an authenticated POST only); the audit trail vouches for it at once."""
        path, sha = await self._completed(run_id)  # the SHA-256 the guard has just checked: not hashed again
        row = await self._get_row(run_id)
        async with self.file_lock(run_id):
            out: dict[str, Any] = await self.render_pool.run(worker.discrepancy_job, str(path), max_effects, sha)
            await self.seal(row, who, audit.RESULT_STORED, {"kind": "discrepancy", "max_effects": max_effects})
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

