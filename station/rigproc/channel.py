"""The channel between the daemon's web process and the rig process: a Unix stream socket carrying
messages of at most :data:`MAX_MESSAGE` bytes, each a 4-byte big-endian length and a JSON object
with the protocol version ``v`` (:data:`VERSION`).

The web process asks (``op``), the rig process answers (``id`` of the question, ``ok`` or
``error``) and tells (``event``) on its own:

=================  ==============================================  ==========================================
question (``op``)  fields                                          answer
=================  ==============================================  ==========================================
``hello``          --                                              ``profile``, ``latched`` (a stop it holds)
``read``           ``address``, ``count``, ``what``, ``function``  ``words``
``write``          ``address``, ``words``, ``what``, ``retry``     --; refused while it holds a stop and the
                                                                   words would set a set-point other than 0
``release``        --                                              -- (the operator acknowledged the stop)
``page_port``      ``port``                                        -- (the main port: the station's own page)
``run``            ``run_id`` (or null)                            -- (the run the crank turns for)
``keeper``         ``run_id`` (or null, as ``run``)                ``keeper_error``: null while the drive's
                                                                   watchdog refreshes go through (the web
                                                                   process's keeper asks it instead of
                                                                   refreshing the drive a second time)
``run_start``      ``run_id``, ``config``, ``steps``,              -- (the run goes on in the rig process,
                   ``provenance``, ``out_dir``, ``hardware``,      ``runhost.py``); refused while it holds a
                   ``radius_m``, ``reserve_file``, (``steady``,    stop or carries out another run
                   ``reset_faults``)
``run_abort``      ``run_id``, ``reason``, ``interrupt``           ``aborted``: the run aborted (null: none)
``run_outcome``    ``run_id``                                      ``running``, ``outcome`` (as ``run_end``;
                                                                   null while it goes on or if unknown)
``daq_*``,         as ``docs/safety.md`` (*The DAQ stream under     answered by the stream process (the rig
``record_*``       the rig process*) tabulates them                process forwards them unchanged); a
                                                                   failure as ``error`` (``kind`` ``daq``,
                                                                   ``disk``, ``recording``, ``acquisition``,
                                                                   ``stream``, ``bad``, ``exception``;
                                                                   ``type``, ``detail``); refused (``busy``)
                                                                   while a run is carried out there
=================  ==============================================  ==========================================

Events: ``stream`` (the DAQ stream's ``samples``, ``lost``, ``error``: every 0.1 s while it streams;
``samples`` null when the stream process ended), ``run_progress`` (a run carried out in the rig
process: ``run_id``, ``state``, ``step``, ``n_steps``, ``step_state``, ``samples``, ``lost_samples``,
``message``; at most every 0.25 s, at once when the step or its state changes), ``run_end`` (its
outcome: ``run_id``, ``status``, ``reason``, ``path``, ``lost_samples``, ``motor_fault``, ``drive``,
``radius_m``), ``stopping`` (a stop the rig process is about to
give, told before it commands the drive: ``source``; the runs are aborted before any answer can
show them the drive's emergency-stop fault) and ``stopped`` (the stop given: ``source``,
``detail``, ``commanded``, ``drive``, ``credentials`` of the request for the record).  The periodic
events (``stream`` without an error, ``run_progress`` within a step's state) are not queued while
the web process has not read 256 KiB told before (it is stopped or hangs).  A failure
travels as ``error``: ``kind`` (``link``,
``timeout``, ``exception``, ``protocol``, ``refused``, ``bad``) and ``detail``."""

from __future__ import annotations

import asyncio
import json
import logging
import struct
from collections.abc import AsyncIterator
from typing import Any

VERSION = 4  # 2: ``keeper`` (the drive's watchdog refreshed by the rig process alone); 3: the DAQ stream;
# 4: the run's procedure carried out in the rig process (``run_*``)
MAX_MESSAGE = 64 * 1024  # bytes of JSON; a register exchange is some 100
_LEN = struct.Struct(">I")


class ChannelError(Exception):
    """A message that is not of this protocol (too long, not JSON, another version)."""


def encode(msg: dict[str, Any]) -> bytes:
    data = json.dumps({**msg, "v": VERSION}, separators=(",", ":")).encode()
    if len(data) > MAX_MESSAGE:
        raise ChannelError(f"a message of {len(data)} bytes (at most {MAX_MESSAGE})")
    return _LEN.pack(len(data)) + data


async def receive(reader: asyncio.StreamReader) -> dict[str, Any] | None:
    """The next message; None at the end of the stream; :class:`ChannelError` for a bad one."""
    try:
        head = await reader.readexactly(_LEN.size)
    except (asyncio.IncompleteReadError, ConnectionError):
        return None
    (n,) = _LEN.unpack(head)
    if n > MAX_MESSAGE:
        raise ChannelError(f"a message of {n} bytes announced (at most {MAX_MESSAGE})")
    try:
        data = await reader.readexactly(n)
    except (asyncio.IncompleteReadError, ConnectionError):
        return None
    try:
        msg = json.loads(data)
    except ValueError as exc:
        raise ChannelError(f"not JSON: {exc}") from None
    if not isinstance(msg, dict) or msg.get("v") != VERSION:
        raise ChannelError(f"expected a message of protocol version {VERSION}, got "
                           f"{msg.get('v') if isinstance(msg, dict) else type(msg).__name__!r}")
    return msg


async def messages(reader: asyncio.StreamReader, sender: str, log: logging.Logger) -> AsyncIterator[dict[str, Any]]:
    """The messages from ``sender`` until the end of the stream or one not of this protocol (logged
    as an error: the caller then closes the channel)."""
    while True:
        try:
            msg = await receive(reader)
        except ChannelError as exc:
            log.error("%s sent %s: the channel is closed", sender, exc)
            return
        if msg is None:
            return
        yield msg
