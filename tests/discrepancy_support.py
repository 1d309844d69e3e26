"""Model-gap tests: a sinecal-csv step file written as ``np.savetxt`` writes it, in one formatting
operation per file instead of one per row (the tests that edit an exported run rewrite about 20 000
rows per step)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

HEADER = "t_s,displacement_m,force_V"


def write_step_csv(path: Path, columns: np.ndarray) -> None:
    """``columns`` (n, 3): t_s, displacement_m, force_V, written with the bytes of
    ``np.savetxt(path, columns, delimiter=",", fmt="%.17g", header=HEADER, comments="")`` (each value
    as ``%.17g``: an exact round trip)."""
    n, k = columns.shape
    line = ",".join(["%.17g"] * k) + "\n"
    path.write_text(HEADER + "\n" + (line * n) % tuple(np.asarray(columns, dtype=float).ravel().tolist()),
                    encoding="utf-8")
