"""Identification on a rig, simulated or real: excitation signals (``excitation``), frequency
responses measured through the control loop (``identify``) and their files (``frf_files``)."""

import beamctl.common  # noqa: F401  (single-threaded BLAS, before numpy is imported)
