"""Imported first by the station's worker-process fork server (``station.procpool``), before numpy:
one BLAS/OpenMP thread per worker process.  The pool's processes are the parallelism; a
multi-threaded BLAS in each of them oversubscribes the cores (measured: identify_fd of a 5-step run
takes 0.14 s with OpenBLAS's default threads on 2 cores against 0.04 s single-threaded).  Never
imported by the parent process."""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"
