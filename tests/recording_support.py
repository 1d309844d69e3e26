"""Small HDF5 recordings for the tests of the recording layer and of what reads it: metadata, float
channels, a one-step recording, and the damage an in-place write killed mid-way used to leave."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from station.recording import ChannelSpec, RecordingWriter, RunMetadata

FS = 20_000.0  # sample rate of these recordings (Hz)
FLOAT_CHANNELS = (ChannelSpec("displacement", "f8", "m", "m", scale=1.0),
                  ChannelSpec("force", "f8", "V", "V", scale=1.0))


def run_metadata(run_id: str = "20250101T000000-TX-1-abcdef", **kw: Any) -> RunMetadata:
    """Metadata of a test run of transducer TX-1 at :data:`FS` (``kw`` replaces any field)."""
    fields: dict[str, Any] = dict(run_id=run_id, transducer_id="TX-1", source="calibrate", sample_rate_hz=FS,
                                  load_mass_kg=26.167, end_mass_kg=0.12, sensitivity_V_per_N=0.002,
                                  capacity_N=5000.0, config_yaml="transducer:\n  id: TX-1  # µ-test\n")
    fields.update(kw)
    return RunMetadata(**fields)


def small_recording(folder: Path, n: int = 4000) -> Path:
    """A closed recording in ``folder`` of one 10 Hz step of ``n`` samples (1 mm sine, 0.1 V cosine)."""
    w = RecordingWriter(folder, run_metadata(), FLOAT_CHANNELS, chunk_samples=1000, min_free_bytes=0)
    t = np.arange(n) / FS
    w.append(1e-3 * np.sin(2 * np.pi * 10 * t), 0.1 * np.cos(2 * np.pi * 10 * t))
    w.add_step(crank_frequency_hz=10.0, crank_radius_m=0.001, start_sample=0, end_sample=n)
    return w.finish("completed")


def killed_in_place_write(rec: Path) -> None:
    """What the old scheme left: a process killed while it held the recording open for writing."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child is killed
        try:
            f = h5py.File(rec, "r+")
            g = f.require_group("results").create_group("identify_fd_sdof")
            g.attrs["json"] = json.dumps({"k_f": 1.0})
            f.flush()
            os.kill(os.getpid(), signal.SIGKILL)
        finally:
            os._exit(1)
    os.waitpid(pid, 0)


def flip_bit(path: Path, at: float = 0.5) -> bytes:
    """Flip the lowest bit of the byte at fraction ``at`` of the file (an edit outside the station);
    returns the file's bytes before."""
    data = path.read_bytes()
    b = bytearray(data)
    b[int(len(b) * at)] ^= 0x01
    path.write_bytes(bytes(b))
    return data
