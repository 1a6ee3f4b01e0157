"""What every room beside models/, gains/, rt/ and hal/ shares: files written whole
(``outputs``), stop requests from signals (``signals``), optional extras (``extras``).

numpy's BLAS runs single-threaded in beamctl unless the environment says otherwise: every
matrix here is small (at most a few hundred rows), where BLAS worker threads on a shared
2-core machine cost more in contention than they gain (the gain build takes 2.5 s on one
thread and 6 to 9 s with the default pool), and in the control loop they would add jitter.
This runs before numpy is first imported by the command line or any room that imports this
package first (simulation, identification, service, reports: a Dask worker importing a study
gets it too).
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
