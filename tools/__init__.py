"""The ``beamctl`` command line over models/, gains/, rt/ and hal/.

numpy's BLAS runs single-threaded in beamctl unless the environment says otherwise: every
matrix here is small (at most a few hundred rows), where BLAS worker threads on a shared
2-core machine cost more in contention than they gain (the gain build takes 2.5 s on one
thread and 6 to 9 s with the default pool), and in the control loop they would add jitter.
This must run before numpy is first imported.
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
