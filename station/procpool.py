"""The station's one way to start worker processes: the daemon's job pools (``service.worker``) and
the nightly batch's local executor (``batch.runner``) are both ``process_pool`` executors.

Every worker runs single-threaded BLAS (``blas_env``: the pool is the parallelism) and then the
pool's own initializer.  Two start methods, one choice each:

* ``fork_server=True`` (the batch): processes come from the multiprocessing *fork server*, started
  once per parent process with ``PRELOAD`` imported (``blas_env`` first, then numpy, scipy, h5py,
  the identification and its least-squares fitter), so every worker is a fork of a process that has
  them imported: no per-worker import time.  A fork server, unlike a plain fork, is safe from a multi-threaded parent.
* ``fork_server=False`` (the daemon): spawned processes, children of the daemon itself, so that they
  see it die (``kill -9``) and exit; a fork server and its resource tracker outlive a killed parent.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from multiprocessing.context import BaseContext
from typing import Any

# scipy.optimize by name: the identification imports it where it fits (a report reads without it),
# and every batch worker fits
PRELOAD = ["station.blas_env", "station.batch.worker", "scipy.optimize"]


def _context(fork_server: bool) -> BaseContext:
    if fork_server and "forkserver" in mp.get_all_start_methods():
        fs = mp.get_context("forkserver")
        fs.set_forkserver_preload(PRELOAD)  # effective when this starts the fork server
        return fs
    return mp.get_context("spawn")


def start(initializer: Callable[..., None] | None, *initargs: Any) -> None:
    """In each worker: the BLAS thread limit (already set in a fork of the fork server; in a spawned
    worker before anything imports numpy), then ``initializer``."""
    import station.blas_env  # noqa: F401

    if initializer is not None:
        initializer(*initargs)


def process_pool(workers: int, initializer: Callable[..., None] | None = None,
                 initargs: tuple[Any, ...] = (), *, fork_server: bool = True) -> ProcessPoolExecutor:
    """A ProcessPoolExecutor of ``workers`` processes (see the module docstring)."""
    return ProcessPoolExecutor(max_workers=max(1, workers), mp_context=_context(fork_server), initializer=start,
                               initargs=(initializer, *initargs))
