"""Simulated experiments: the paper's load ramps on the simulated rig (``experiment``), the
compiled offline loop that runs them (``simkernel``) and uncertainty studies over many rigs,
on Dask where it is installed (``study``)."""

import beamctl.common  # noqa: F401  (single-threaded BLAS, before numpy is imported)
