"""How a run is put together: a configuration into a model, gain table, controller, plant and
HAL (``beamctl.assembly.run``), for the lab service, the simulated experiment, identification,
commissioning and the benchmarks alike."""
