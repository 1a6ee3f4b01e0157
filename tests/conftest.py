"""Shared fixtures: the paper's model is built once per test session."""

import pytest

import beamctl.tools  # noqa: F401  (single-threaded BLAS as beamctl runs it; before numpy loads)
from beamctl.models import build_model, load_parameters, reduce


@pytest.fixture(scope="session")
def paper_params():
    return load_parameters()


@pytest.fixture(scope="session")
def paper_model(paper_params):
    return build_model(paper_params)


@pytest.fixture(scope="session")
def paper_reduced(paper_model):
    return reduce(paper_model)
