"""Hardware abstraction: the interface (hal.base) and its backends, chosen by name."""
