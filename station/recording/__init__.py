"""HDF5 recordings of calibration runs (layout in docs/recording-format.md)."""

from station.recording.reader import (
    Recording,
    Step,
    read_recording,
    read_results,
    recover_partial,
    write_results,
)
from station.recording.writer import ChannelSpec, RecordingWriter, RunMetadata, new_run_id

__all__ = [
    "ChannelSpec",
    "Recording",
    "RecordingWriter",
    "RunMetadata",
    "Step",
    "new_run_id",
    "read_recording",
    "read_results",
    "recover_partial",
    "write_results",
]
