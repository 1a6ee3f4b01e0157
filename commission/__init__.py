"""Commissioning a rig (``workflow``): identification, the fit, the calibrated box, the gain
table and its robust check, the simulated experiment and the report, as one resumable run."""

import beamctl.common  # noqa: F401  (single-threaded BLAS, before numpy is imported)
