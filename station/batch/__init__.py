"""Nightly batch: re-identify the recordings in scope through a ``concurrent.futures``-style executor
(a local process pool, or a Dask distributed cluster), then write each transducer's parameters over
time with drift flagged against its history (docs/batch.md).

Modules: ``items`` (BatchItem), ``worker`` (the job run in a worker process), ``runner``
(``run_batch``, executors), ``scope`` (which recordings), ``summary`` (history, drift, JSON/CSV),
``progress`` (the progress bar).  The worker processes are the station's (``station.procpool``).

The package's attributes are imported lazily: the worker processes' fork server imports
``station.blas_env`` before numpy and then ``batch.worker``, which would not work if importing the
package pulled numpy in.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from station.batch.items import BatchItem
    from station.batch.runner import run_batch
    from station.batch.scope import select_recordings
    from station.batch.summary import DriftCheck, drift_checks, write_summaries

__all__ = ["BatchItem", "DriftCheck", "drift_checks", "run_batch", "select_recordings", "write_summaries"]
_WHERE = {"BatchItem": "items", "run_batch": "runner", "select_recordings": "scope", "DriftCheck": "summary",
          "drift_checks": "summary", "write_summaries": "summary"}


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        return getattr(importlib.import_module(f"station.batch.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'station.batch' has no attribute {name!r}")
