"""The batch job, run in a worker process (or a Dask worker): read, identify, optionally store.

Imported by the worker processes' fork server (after ``station.blas_env``; see ``station.procpool``)
so that forked workers start with numpy, scipy, h5py and the identification already imported.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from station.batch.items import BatchItem
from station.errors import StationError
from station.ident.identify import identify_recording, store_result
from station.ident.paper.protocol import PUBLISHED_SWARM, SwarmSize
from station.recording import Recording, read_recording
from station.run.methods import identification_of, swarm_of

log = logging.getLogger(__name__)


def identify_listed(path: Path, store: bool = False) -> list[BatchItem]:
    """Identify one recording with each method its configuration lists (``identification.methods``,
    with their seeds and the swarm size): one item per method, each its own drift series; a method
    that refuses or fails gives a "failed" item of that method (the others go on)."""
    try:
        rec = read_recording(path)
    except Exception:  # the failure becomes the recording's one item
        return [identify_one(path, store=store)]
    ident = identification_of(rec)
    return [identify_one(path, c.method, None if c.model_key == "auto" else c.model_key, store, rec=rec,
                         seed=c.seed, swarm=swarm_of(ident)) for c in ident.methods]


def identify_one(path: Path, method: str | None = None, model: str | None = None,
                 store: bool = False, *, rec: Recording | None = None, seed: int = 0,
                 swarm: SwarmSize = PUBLISHED_SWARM) -> BatchItem:
    """Identify one recording; every failure becomes a "failed" item (the batch goes on)."""
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        rec = rec or read_recording(path)
        res = identify_recording(rec, method, model, seed=seed, swarm=swarm)
        stored = store_result(path, res) if store else ""
        return BatchItem(Path(path), rec.run_id, rec.transducer_id, rec.start_time, "ok", res.method, res.model,
                         {n: p.to_dict() for n, p in res.parameters.items()}, "", time.perf_counter() - t0, stored,
                         time.process_time() - c0,
                         {} if res.assumptions.structure is None else res.assumptions.structure.to_dict(),
                         [{"name": c.name, "severity": c.severity, "message": c.message}
                          for c in res.checks if c.severity != "info"])
    except Exception as exc:  # one bad recording must not stop the night's batch
        if not isinstance(exc, StationError):
            log.exception("batch: unexpected error on %s", path)
        msg = str(exc) if isinstance(exc, StationError) else f"{type(exc).__name__}: {exc}"
        return BatchItem(Path(path), rec.run_id if rec else Path(path).name.split(".")[0],
                         rec.transducer_id if rec else "", rec.start_time if rec else "", "failed",
                         method or "", model or "", error=msg, wall_s=time.perf_counter() - t0,
                         cpu_s=time.process_time() - c0)


def identify_chunk(paths: list[Path], method: str | None = None, model: str | None = None,
                   store: bool = False) -> list[BatchItem]:
    """identify_one over a chunk of recordings (fewer round trips when jobs are tiny); without a
    method, each recording's listed methods (``identify_listed``)."""
    if method is None:
        return [it for p in paths for it in identify_listed(p, store)]
    return [identify_one(p, method, model, store) for p in paths]


def warm_up() -> None:
    """Pool initializer: nothing left to import when the fork server preloaded this module; logs
    when BLAS threads are not limited (the fork server was started by someone else)."""
    import os

    if os.environ.get("OPENBLAS_NUM_THREADS") != "1":
        log.debug("batch worker %d: BLAS threads not limited (OPENBLAS_NUM_THREADS unset)", os.getpid())
