"""The ``beamctl`` command line: parsing, printing and exit codes over the library rooms
(models/, gains/, rt/, hal/, simulation/, identification/, service/, reports/, common/)."""

import beamctl.common  # noqa: F401  (single-threaded BLAS, before numpy is imported)
