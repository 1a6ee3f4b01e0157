"""Speed measured, not asserted: what ``beamctl bench`` runs (``measure``)."""

import beamctl.common  # noqa: F401  (single-threaded BLAS, before numpy is imported)
