"""DAQ/signal-conditioner bridge driver (serial, SLIP-framed binary stream; docs/daq-protocol.md)."""

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
