"""The ``beamctl`` command line over models/, gains/, rt/ and hal/."""
