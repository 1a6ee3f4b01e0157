"""Configuration validation, shared by every room: the one place where configuration files
(model parameters, plant scenario, controller, HAL and service settings) are read and
checked, so that a wrong value is always refused the same way, naming the key."""
