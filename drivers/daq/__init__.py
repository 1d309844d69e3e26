"""DAQ/signal-conditioner bridge driver (serial, SLIP-framed binary stream; docs/daq-protocol.md)."""

from drivers.daq.bridge import (
    DaqBridge,
    DaqCommandError,
    DaqConfig,
    DaqTimeoutError,
    StreamEvent,
    StreamStalled,
    StreamSummary,
)
from drivers.daq.link import ByteLink, DaqLinkError, SerialLink, SocketLink
from drivers.daq.protocol import DecoderStats, FrameError, SampleBlock, SampleGap, StreamDecoder

__all__ = [
    "ByteLink",
    "DaqBridge",
    "DaqCommandError",
    "DaqConfig",
    "DaqLinkError",
    "DaqTimeoutError",
    "DecoderStats",
    "FrameError",
    "SampleBlock",
    "SampleGap",
    "SerialLink",
    "SocketLink",
    "StreamDecoder",
    "StreamEvent",
    "StreamStalled",
    "StreamSummary",
]
