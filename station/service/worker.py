"""Worker processes: identification of finished runs, plots, reports and the discrepancy analysis.

Everything CPU-bound runs here, in spawned processes, never in the daemon's event loop.  The job
functions are module-level (picklable) and take plain arguments (paths as strings, settings as
dicts).  A worker whose daemon dies finishes the job it is on (a write into a recording is never
cut short by us) and then exits: the kernel tells it at once (Linux: ``PR_SET_PDEATHSIG``), a
thread watching the parent's PID is the fallback, and a daemon that died while the worker was
still starting is noticed as the worker starts (the PID it was given is no longer its parent).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import ctypes
import functools
import logging
import os
import signal
import threading
import time
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any, TypeVar

from station.procpool import process_pool

log = logging.getLogger(__name__)

T = TypeVar("T")

_busy = threading.Event()
_orphaned = threading.Event()  # the daemon is gone: exit once the job on hand is done
PDEATH_SIGNAL = signal.SIGUSR1  # sent by the kernel when the daemon dies (Linux)


class WorkerCrashed(RuntimeError):
    """The worker process died during a job (killed, out of memory, a crash in a C library)."""


# --------------------------------------------------------------------------- inside the worker
def _exit_if_orphaned(daemon_pid: int) -> None:
    """Exit now if the daemon is gone and no job is running; with a job, once it is done."""
    if os.getppid() == daemon_pid:
        return
    _orphaned.set()
    if not _busy.is_set():
        os._exit(0)


def _watch_parent(daemon_pid: int) -> None:
    while True:
        time.sleep(0.5)
        _exit_if_orphaned(daemon_pid)


def _ask_for_parent_death_signal() -> bool:
    """Linux: have the kernel send PDEATH_SIGNAL when the parent exits; False elsewhere."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return int(libc.prctl(PR_SET_PDEATHSIG, int(PDEATH_SIGNAL), 0, 0, 0)) == 0
    except (OSError, AttributeError):
        return False


PR_SET_PDEATHSIG = 1


def _init_worker(level: int, daemon_pid: int) -> None:
    """Logging, and an exit once the daemon (PID ``daemon_pid``, the parent) is gone (module
    docstring).  One BLAS thread per worker is set by ``station.procpool`` before this runs."""
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s worker[%(process)d] %(name)s: %(message)s")
    signal.signal(PDEATH_SIGNAL, lambda signum, frame: _exit_if_orphaned(daemon_pid))
    _ask_for_parent_death_signal()
    _exit_if_orphaned(daemon_pid)  # the daemon died before the signal was asked for
    threading.Thread(target=_watch_parent, args=(daemon_pid,), daemon=True, name="parent-watch").start()


def worker_job(fn: Callable[..., T]) -> Callable[..., T]:
    """Decorate a module-level function as a job of the daemon's worker processes: while it runs the
    worker counts as busy (the parent-watch leaves it alone); a worker whose daemon died meanwhile
    finishes the job, then exits (nobody is left to take the result).  A job must be importable by
    module and name (a spawned worker unpickles it so)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kw: Any) -> T:
        _busy.set()
        try:
            return fn(*args, **kw)
        finally:
            _busy.clear()
            if _orphaned.is_set():
                os._exit(0)  # nobody is left to take the result
    return wrapper


@worker_job
def identify_job(path: str) -> dict[str, Any]:
    """H(f) per step, then the primary identification, stored beside the recording with every listed
    method's outcome (the others ``pending``: ``secondary_job`` computes each; station.run.methods)."""
    from station.ident.response.checked import checked_response
    from station.recording import read_recording
    from station.run.methods import identify_primary
    from station.run.processing import process_recording

    t0 = time.perf_counter()
    rec = read_recording(Path(path))
    response = checked_response(rec)
    process_recording(Path(path), rec, response)
    outcomes, res = identify_primary(Path(path), rec, response)
    return {"result_name": res.result_name, "method": res.method, "model": res.model,
            "wall_s": time.perf_counter() - t0, "outcomes": [o.to_dict() for o in outcomes]}


@worker_job
def secondary_job(path: str, index: int) -> dict[str, Any]:
    """Listed identification ``index`` (>= 1) of the recording, its result stored beside it; its
    outcome (``MethodOutcome.to_dict``): a refusal or failure is an outcome, never an exception."""
    from station.recording import read_recording
    from station.run.methods import identify_secondary

    return identify_secondary(Path(path), read_recording(Path(path)), index).to_dict()


@worker_job
def warm_up_job() -> None:
    """Load the plotting and report modules (the first results page would otherwise wait for them)."""
    import station.report.html
    import station.report.plots  # noqa: F401


@worker_job
def plot_job(path: str, name: str) -> bytes | None:
    """PNG bytes of plot ``name``; None for an unknown name."""
    from station.report.plots import render_plot

    try:
        return bytes(render_plot(Path(path), name))
    except KeyError:
        return None


@worker_job
def report_job(path: str) -> str:
    from station.report.html import render_report

    return str(render_report(Path(path)))


@worker_job
def pdf_job(html: str) -> bytes:
    """PDF bytes of an HTML page (``station.report.render.html_to_pdf``: the report's and the
    certificates' engine); the daemon sends the page it has rendered and kept."""
    from station.report.render import html_to_pdf

    return html_to_pdf(html)


@worker_job
def certificate_job(path: str, ext: str, register: dict[str, Any]) -> bytes:
    """The run's draft certificate as html or DCC bytes (its PDF is that html page through ``pdf_job``;
    the daemon serves an issued one from its files, checked against the audit trail)."""
    from station.certificate.issue import run_document

    return run_document(Path(path), ext, register, draft_only=True)


@worker_job
def issue_job(path: str, prepared_by: str, approver: str, roles: dict[str, str], replaces: str | None, reason: str,
              register: dict[str, Any], number: str, signature: dict[str, str]) -> dict[str, Any]:
    """Issue the run's certificate under ``number`` (taken from the lab's sequence; roles: of the
    authenticated approver and the preparer); its record and the SHA-256 of each of its files."""
    from station.certificate.issue import MappingRoles, issue
    from station.lab.integrity import sha256_file

    it = issue(Path(path), prepared_by=prepared_by, approver=approver, replaces=replaces, reason=reason,
               roles=MappingRoles(roles), register=register, number=number, signature=signature)
    return {"record": {k: v for k, v in it.record.items() if k != "content"},
            "hashes": {ext: sha256_file(it.path(ext)) for ext in ("html", "pdf", "xml", "json")}}


@worker_job
def discrepancy_job(path: str, max_effects: int, recording_sha256: str | None = None) -> dict[str, Any]:
    """Compute the model-gap analysis of a recording and store it beside it as result ``discrepancy``
    (everything, ``to_dict``, with the ``max_effects`` used: where ``station discrepancy --save``
    writes and the report reads); returns the JSON contract (``to_json``).  The analysis is a function
    of the recording, ``max_effects`` and the software: one stored for the same three (the recording's
    SHA-256, the version) is given again, not computed again.  ``recording_sha256``: the recording's,
    when the caller has checked it already (computed here otherwise)."""
    from station import __version__
    from station.discrepancy import analyse_recording
    from station.lab.integrity import sha256_file
    from station.recording import read_result, write_result

    source = recording_sha256 or sha256_file(Path(path))
    doc = read_result(path, "discrepancy")
    if (doc is not None and doc.get("max_effects") == max_effects and doc.get("software_version") == __version__
            and doc.get("recording_sha256") == source):
        return {k: doc.get(k) for k in CONTRACT_KEYS}
    rep = analyse_recording(path, max_effects=max_effects)
    # a result identical to the one stored is kept, not rewritten
    write_result(path, "discrepancy", {**rep.to_dict(), "max_effects": max_effects, "software_version": __version__,
                                       "recording_sha256": source}, keep_identical=True)
    return dict(rep.to_json())  # the contract (DiscrepancyJson) as the API's plain JSON


@worker_job
def campaign_job(paths: list[str]) -> dict[str, Any]:
    """The joint identification of several recordings (``station.ident.campaign.identify``):
    ``{"result": CampaignResult.to_dict()}``, or ``{"refused": message}`` for recordings that cannot
    be one campaign (a plain message: an exception's own fields need not survive the pickling)."""
    from station.errors import BadInputError
    from station.ident.campaign.identify import identify_campaign
    from station.recording import read_recording

    try:
        res = identify_campaign([read_recording(Path(p)) for p in paths])
    except BadInputError as exc:
        return {"refused": str(exc)}
    return {"result": res.to_dict()}


CONTRACT_KEYS = ("base_gap", "effects", "final_gap", "parameters_before", "parameters_after", "unexplained",
                 "ties", "notes", "proposal", "proposal_note", "structure", "drive")


def stored_discrepancy(path: Path, max_effects: int) -> dict[str, Any] | None:
    """The stored model-gap analysis' JSON contract if it was computed with ``max_effects``, else None
    (reads only: nothing is computed or written)."""
    from station.recording import read_result

    doc = read_result(path, "discrepancy")
    if doc is None or doc.get("max_effects") != max_effects:
        return None
    return {k: doc.get(k) for k in CONTRACT_KEYS}  # results stored before a key existed: null


# --------------------------------------------------------------------------- in the daemon
class WorkerPool:
    """A pool of spawned worker processes; rebuilt when a worker dies."""

    def __init__(self, name: str, processes: int) -> None:
        self.name = name
        self.processes = processes
        self._executor: concurrent.futures.ProcessPoolExecutor | None = None
        self._lock = threading.Lock()
        self.crashes = 0

    def _get(self) -> concurrent.futures.ProcessPoolExecutor:
        with self._lock:
            if self._executor is None:
                self._executor = process_pool(self.processes, _init_worker,
                                              (logging.getLogger().getEffectiveLevel(), os.getpid()),
                                              fork_server=False)
            return self._executor

    @property
    def started(self) -> bool:
        return self._executor is not None

    def pids(self) -> list[int]:
        ex = self._executor
        procs = getattr(ex, "_processes", None) or {}
        return [p.pid for p in procs.values() if p.pid is not None]

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        import asyncio  # here: the daemon's side; a worker process has no event loop

        ex = self._get()
        try:
            return await asyncio.get_running_loop().run_in_executor(ex, fn, *args)
        except BrokenProcessPool as exc:
            self.crashes += 1
            with self._lock:
                if self._executor is ex:
                    self._executor = None
            with contextlib.suppress(Exception):
                ex.shutdown(wait=False, cancel_futures=True)
            raise WorkerCrashed(f"{self.name} worker process died during the job") from exc

    def shutdown(self, timeout_s: float = 30.0) -> None:
        """Let running jobs finish (up to ``timeout_s``), then stop the processes."""
        with self._lock:
            ex, self._executor = self._executor, None
        if ex is None:
            return
        procs = list((getattr(ex, "_processes", None) or {}).values())
        ex.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + timeout_s
        for p in procs:
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                log.warning("%s worker %s still busy after %.0f s; terminating it", self.name, p.pid, timeout_s)
                p.terminate()
                p.join(2.0)
