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
from station.ident.api import identify_recording, store_result
from station.recording import Recording, read_recording

log = logging.getLogger(__name__)


def identify_one(path: Path, method: str | None = None, model: str | None = None,
                 store: bool = False) -> BatchItem:
    """Identify one recording; every failure becomes a "failed" item (the batch goes on)."""
    t0, c0 = time.perf_counter(), time.process_time()
    rec: Recording | None = None
    try:
        rec = read_recording(path)
        res = identify_recording(rec, method, model)
        stored = store_result(path, res) if store else ""
        return BatchItem(Path(path), rec.run_id, rec.transducer_id, rec.start_time, "ok", res.method, res.model,
                         {n: p.to_dict() for n, p in res.parameters.items()}, "", time.perf_counter() - t0, stored,
                         time.process_time() - c0)
    except Exception as exc:  # one bad recording must not stop the night's batch
        if not isinstance(exc, StationError):
            log.exception("batch: unexpected error on %s", path)
        msg = str(exc) if isinstance(exc, StationError) else f"{type(exc).__name__}: {exc}"
        return BatchItem(Path(path), rec.run_id if rec else Path(path).name.split(".")[0],
                         rec.transducer_id if rec else "", rec.start_time if rec else "", "failed",
                         error=msg, wall_s=time.perf_counter() - t0, cpu_s=time.process_time() - c0)


def identify_chunk(paths: list[Path], method: str | None = None, model: str | None = None,
                   store: bool = False) -> list[BatchItem]:
    """identify_one over a chunk of recordings (fewer round trips when jobs are tiny)."""
    return [identify_one(p, method, model, store) for p in paths]


def warm_up() -> None:
    """Pool initializer: nothing left to import when the fork server preloaded this module; logs
    when BLAS threads are not limited (the fork server was started by someone else)."""
    import os

    if os.environ.get("OPENBLAS_NUM_THREADS") != "1":
        log.debug("batch worker %d: BLAS threads not limited (OPENBLAS_NUM_THREADS unset)", os.getpid())
