"""The loopwatch service: connectors in, analyses on a process pool, the REST API out.

The analyses parallelise over loops with worker processes, one per core: a BLAS
thread pool in each would only compete with the other workers.  OpenBLAS's threads
also spin for a while after every call they share, which doubled the CPU time of a
loop's diagnosis once one such call (the model trace's matrix exponential) was in it.
So BLAS runs on one thread in the service unless the environment says otherwise;
this runs before anything of the service imports numpy.
"""

import os

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")
