"""Process-wide settings of a test run, loaded by pytest before its plugins, the conftest files and
numpy (``-p process_setup`` in pyproject.toml's ``addopts``; every pytest-xdist worker loads it too).

- One BLAS/OpenMP thread, as the station's CLI and its worker processes run (``station.cli``,
  ``station.blas_env``): the analyses are many small problems and each xdist worker already has a
  core; a BLAS thread pool per worker oversubscribes them (the model-gap tests took 133 s of CPU in
  110 s serially with OpenBLAS's threads, 98 s in 99 s with one).  A value the user set is kept.
- pytest's compiled test modules are cached even where ``PYTHONDONTWRITEBYTECODE`` is set: pytest
  compiles every test module and the modules of its plugins' packages (schemathesis, hypothesis,
  anyio: about 360) with its assertions rewritten, and without the cache every process of a run
  does it again (3.7 s of CPU per process on the 2-core station PC, against 0.1 s to read them back).
  The cache is ``__pycache__`` beside each module, as for any import.
"""

from __future__ import annotations

import os
import sys

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

sys.dont_write_bytecode = False
