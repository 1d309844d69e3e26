"""A worker job for the tests: a sleep that counts as a job (busy) in the daemon's worker processes.

It lives in an importable module because a spawned worker unpickles a job by its module and name."""

from __future__ import annotations

import time

from station.service.worker import worker_job


@worker_job
def busy_sleep(seconds: float) -> None:
    """Sleep ``seconds`` (s) as a job: a worker orphaned meanwhile finishes it, then exits."""
    time.sleep(seconds)
