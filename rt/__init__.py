"""The real-time controller: the per-sample control law (estimator, schedule, law,
allocation, safety) and the fixed-rate loop with timing and telemetry.

Imports the HAL interface (hal.base) only, never a backend.
"""
