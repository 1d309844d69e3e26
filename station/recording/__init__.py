"""HDF5 recordings of calibration runs and the results stored beside them (layout in
docs/recording-format.md)."""

from station.recording.reader import Recording, Step, read_documents, read_recording, recover_partial, start_metadata
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
    "read_documents",
    "read_recording",
    "read_result",
    "read_stored",
    "recover_partial",
    "start_metadata",
    "write_result",
]
