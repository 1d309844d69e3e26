"""Scheduling priority for the threads that command or watch the rig (the rig thread: the drive's
set-points, its watchdog keeper, the stop's command and read-back; the stop port's listener).

Each asks the operating system, for the calling thread only, for what ``service.rig_priority``
says and takes what it is given: ``realtime`` asks for ``SCHED_FIFO`` (needs ``CAP_SYS_NICE`` or
an ``RLIMIT_RTPRIO``, e.g. the systemd unit's ``LimitRTPRIO=``), falling back to a raised nice
value (``CAP_SYS_NICE`` or ``RLIMIT_NICE``: ``LimitNICE=``), falling back to the normal priority;
``raised`` starts at the nice value; ``normal`` asks for nothing.  What it got is logged and
returned.  A real-time thread that is mostly asleep (these are) costs the machine nothing; the
kernel's real-time throttling still leaves the rest of the machine 5 % of each second."""

from __future__ import annotations

import logging
import os
import threading
from typing import Literal

log = logging.getLogger(__name__)

Priority = Literal["realtime", "raised", "normal"]
REALTIME_PRIORITY = 20  # SCHED_FIFO 1..99; below the kernel's threaded interrupt handlers (50)
NICE = -10


def raise_priority(name: str, wanted: Priority) -> str:
    """Ask for ``wanted`` for the calling thread (``name`` for the log); what it got, in words."""
    tid = threading.get_native_id()
    refused: list[str] = []
    if wanted == "realtime":
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(REALTIME_PRIORITY))
            got = f"real-time (SCHED_FIFO {os.sched_getparam(0).sched_priority})"
            log.info("%s thread: %s", name, got)
            return got
        except (OSError, AttributeError) as exc:
            refused.append(f"SCHED_FIFO refused ({getattr(exc, 'strerror', None) or exc})")
    if wanted in ("realtime", "raised"):
        try:
            os.setpriority(os.PRIO_PROCESS, tid, NICE)
        except OSError as exc:
            refused.append(f"nice {NICE} refused ({exc.strerror})")
    nice = os.getpriority(os.PRIO_PROCESS, tid)
    got = (f"raised (nice {nice})" if nice < 0 else f"normal (nice {nice})") + (
        f": {'; '.join(refused)}; give the daemon CAP_SYS_NICE or LimitRTPRIO=/LimitNICE= (deploy/README.md)"
        if refused else "")
    (log.warning if refused else log.info)("%s thread: %s", name, got)
    return got


BELOW_REALTIME_PRIORITY = 10  # SCHED_FIFO of what runs beside the rig and must yield to it (the DAQ stream)
BELOW_NICE = -5


def lower_below_rig() -> str:
    """Lower the calling thread to just below what :func:`raise_priority` gives the rig (a thread
    made for starting a child process that inherits it: the DAQ stream, which must preempt the web
    side but never the watchdog keeper or the stop): ``SCHED_FIFO`` 10 under real-time 20, nice -5
    under a raised nice, else as it is.  Lowering needs no privilege.  What it got, in words."""
    tid = threading.get_native_id()
    try:
        if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(BELOW_REALTIME_PRIORITY))
            return f"real-time (SCHED_FIFO {os.sched_getparam(0).sched_priority})"
        if os.getpriority(os.PRIO_PROCESS, tid) < BELOW_NICE:
            os.setpriority(os.PRIO_PROCESS, tid, BELOW_NICE)
        nice = os.getpriority(os.PRIO_PROCESS, tid)
    except (OSError, AttributeError) as exc:
        return f"as inherited ({exc})"
    return f"raised (nice {nice})" if nice < 0 else f"normal (nice {nice})"
