"""The rig's threads ask for a raised scheduling priority and say what they got (the system
decides: root or CAP_SYS_NICE gets SCHED_FIFO, others a nice value or nothing)."""

from __future__ import annotations

import logging
import os
import threading

import pytest

from station.service.priority import NICE, REALTIME_PRIORITY, Priority, raise_priority


def in_a_thread(wanted: Priority) -> tuple[str, int, int, int]:
    """(what it said, the policy, the real-time priority, the nice value) of a fresh thread after asking."""
    out: list[tuple[str, int, int, int]] = []

    def main() -> None:
        said = raise_priority("test", wanted)
        out.append((said, os.sched_getscheduler(0), os.sched_getparam(0).sched_priority,
                    os.getpriority(os.PRIO_PROCESS, threading.get_native_id())))
    t = threading.Thread(target=main)
    t.start()
    t.join()
    return out[0]


def test_what_a_thread_says_it_got_is_what_the_system_gave(caplog: pytest.LogCaptureFixture) -> None:
    base = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    with caplog.at_level(logging.INFO, logger="station.service.priority"):
        said, policy, prio, nice = in_a_thread("realtime")
    assert said in caplog.text
    if policy == os.SCHED_FIFO:
        assert said == f"real-time (SCHED_FIFO {REALTIME_PRIORITY})" and prio == REALTIME_PRIORITY
    else:  # refused: the fallback, and why
        assert "SCHED_FIFO refused" in said and f"nice {nice}" in said
    said, policy, _, nice = in_a_thread("raised")
    assert policy == os.SCHED_OTHER
    assert said.startswith(f"raised (nice {NICE})" if nice == NICE else f"normal (nice {nice}): nice {NICE} refused")
    said, policy, _, nice = in_a_thread("normal")
    assert (said, policy, nice) == (f"normal (nice {base})", os.SCHED_OTHER, base)
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # only the asking thread changed
