"""Reports and figures: the paper's figures and the run plots (``plots``), the report of a
recorded run (``report``) and recordings read and exported to MDF4, HDF5, MAT and CSV
(``recordings``)."""

import beamctl.common  # noqa: F401  (single-threaded BLAS, before numpy is imported)
