"""DAQ/signal-conditioner bridge driver (serial, SLIP-framed binary stream; docs/daq-protocol.md).

The names below load their modules at first use: the link budget (a station's configuration checks
its baud rate with it) does not import the bridge and its event loop.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from drivers.daq.bridge import (
        DaqBridge,
        DaqCommandError,
        DaqConfig,
        DaqHardware,
        DaqLinkBudgetError,
        DaqTimeoutError,
        StreamEvent,
        StreamStalled,
        StreamSummary,
    )
    from drivers.daq.link import ByteLink, DaqLinkError, SerialLink, SocketLink
    from drivers.daq.protocol import (
        DecoderStats,
        FrameError,
        LinkBudget,
        SampleBlock,
        SampleGap,
        StreamDecoder,
        link_budget,
        usb_link_budget,
    )

# each name's module, imported at the name's first use
_MODULE_OF = {
    "DaqBridge": "drivers.daq.bridge",
    "DaqCommandError": "drivers.daq.bridge",
    "DaqConfig": "drivers.daq.bridge",
    "DaqHardware": "drivers.daq.bridge",
    "DaqLinkBudgetError": "drivers.daq.bridge",
    "DaqTimeoutError": "drivers.daq.bridge",
    "StreamEvent": "drivers.daq.bridge",
    "StreamStalled": "drivers.daq.bridge",
    "StreamSummary": "drivers.daq.bridge",
    "ByteLink": "drivers.daq.link",
    "DaqLinkError": "drivers.daq.link",
    "SerialLink": "drivers.daq.link",
    "SocketLink": "drivers.daq.link",
    "DecoderStats": "drivers.daq.protocol",
    "FrameError": "drivers.daq.protocol",
    "LinkBudget": "drivers.daq.protocol",
    "SampleBlock": "drivers.daq.protocol",
    "SampleGap": "drivers.daq.protocol",
    "StreamDecoder": "drivers.daq.protocol",
    "link_budget": "drivers.daq.protocol",
    "usb_link_budget": "drivers.daq.protocol",
}

__all__ = [
    "ByteLink",
    "DaqBridge",
    "DaqCommandError",
    "DaqConfig",
    "DaqHardware",
    "DaqLinkBudgetError",
    "DaqLinkError",
    "DaqTimeoutError",
    "DecoderStats",
    "FrameError",
    "LinkBudget",
    "SampleBlock",
    "SampleGap",
    "SerialLink",
    "SocketLink",
    "StreamDecoder",
    "StreamEvent",
    "StreamStalled",
    "StreamSummary",
    "link_budget",
    "usb_link_budget",
]


def __getattr__(name: str) -> Any:
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # looked up once
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
