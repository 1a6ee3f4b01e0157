"""Benchmarks of the model (run with ``pytest tests/benchmarks --benchmark-enable -n 0``)."""

from beamctl.models import build_model, critical_load, load_parameters


def test_build_default_model_and_its_critical_load(benchmark):
    """Read the parameters, assemble the FE model (with its Rayleigh fit) and solve eq. (12)."""

    def build():
        return critical_load(build_model(load_parameters()))

    fcr = benchmark(build)
    assert abs(fcr - 3194.0) <= 3.0
