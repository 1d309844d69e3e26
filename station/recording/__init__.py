"""HDF5 recordings of calibration runs and the results stored beside them (layout in
docs/recording-format.md)."""

from station.recording.reader import Recording, Step, read_recording, recover_partial
from station.recording.stored import Stored, read_result, read_stored, write_result
from station.recording.writer import ChannelSpec, RecordingWriter, RunMetadata, new_run_id

__all__ = [
    "ChannelSpec",
    "Recording",
    "RecordingWriter",
    "RunMetadata",
    "Step",
    "Stored",
    "new_run_id",
    "read_recording",
    "read_result",
    "read_stored",
    "recover_partial",
    "write_result",
]
