"""Shared fixtures: the paper's model is built once per test session."""

import pytest
from hypothesis import settings

import beamctl.tools  # noqa: F401  (single-threaded BLAS as beamctl runs it; before numpy loads)
from beamctl.models import build_model, load_parameters, reduce

# Property tests run the same examples on every machine and run (a failure is reproducible,
# not a red CI one time in ten) and have no per-example deadline (a shared 2-core machine
# is not a benchmark). `pytest --hypothesis-profile=explore` searches with fresh randomness.
settings.register_profile("ci", derandomize=True, database=None, deadline=None, print_blob=True)
settings.register_profile("explore", max_examples=2000, deadline=None)
settings.load_profile("ci")


@pytest.fixture(scope="session")
def paper_params():
    return load_parameters()


@pytest.fixture(scope="session")
def paper_model(paper_params):
    return build_model(paper_params)


@pytest.fixture(scope="session")
def paper_reduced(paper_model):
    return reduce(paper_model)
