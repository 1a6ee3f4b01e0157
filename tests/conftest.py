"""Shared fixtures: the paper's model is built once per test session; every test has a control
socket path of its own."""

import gc
import shutil
import sys
import tempfile
from pathlib import Path

import pytest
from hypothesis import settings
from threadpoolctl import threadpool_limits

# Compiled modules are cached (__pycache__, ignored by git) even where the environment asks
# Python not to write them (PYTHONDONTWRITEBYTECODE): the suite starts some fifty Python processes
# (services, commands, Dask and pool workers) that read the cache this process writes instead
# of compiling beamctl's sources again each, and pytest keeps the test modules it rewrote.
sys.dont_write_bytecode = False

# The cyclic garbage collector of this process runs less often: its full collections walk every
# object the session holds (the modules of numpy, scipy, numba, matplotlib and dask, the tables,
# the test items), a tenth of a second and more each, and the tests that read a gain table
# allocate hundreds of thousands of objects. What the tests run is unchanged (a service's
# real-time set-up disables the collector for its run anyway).
gc.set_threshold(10000, 20, 20)

import beamctl.tools  # noqa: E402, F401  (single-threaded BLAS as beamctl runs it; before numpy loads)
from beamctl.models import build_model, load_parameters, reduce  # noqa: E402

# One BLAS thread, as beamctl runs (beamctl.common): pytest-randomly imports numpy before this file
# runs, and numpy's OpenBLAS then starts with a thread a core, which beamctl's environment setting
# comes too late to prevent. Two BLAS threads on this 2-core machine make every eigenvalue and
# matrix exponential of the gain and robustness tests two to three times slower in wall time
# when another process keeps a core busy.
_ONE_BLAS_THREAD = threadpool_limits(1)

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


@pytest.fixture(autouse=True)
def short_dir(monkeypatch):
    """A directory of the test's own with a short path (a UNIX socket's path holds 107 bytes; a
    test's tmp_path under pytest-xdist is longer than that leaves room for): the control socket
    and the local bus's sockets live there, so that a service or bus a test starts, in process or
    not, never meets another test's, in this process or in another worker."""
    directory = Path(tempfile.mkdtemp(prefix="bc-", dir="/tmp" if Path("/tmp").is_dir() else None))
    monkeypatch.setenv("BEAMCTL_CONTROL_SOCKET", str(directory / "control.sock"))
    monkeypatch.setenv("BEAMCTL_LOCALBUS_DIR", str(directory / "bus"))
    yield directory
    shutil.rmtree(directory, ignore_errors=True)


@pytest.fixture
def control_socket(short_dir):
    """The control socket path of this test ($BEAMCTL_CONTROL_SOCKET)."""
    return short_dir / "control.sock"


@pytest.fixture(scope="session")
def other_table(tmp_path_factory):
    """A second table of the paper's design (its rate, I/O chain and model) on a 250 N grid: one a
    running service may swap to."""
    from beamctl.tools.cli import main

    out = tmp_path_factory.mktemp("tables") / "coarse.yaml"
    assert main(["gains", "build", "--design", "integral-lqr", "--no-robust", "--grid", "0:4000:250",
                 "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="session")
def compiled_engine():
    """The control engine compiled into numba's cache (rt/engine.py, ``cache=True``) before a test
    starts a service in a process of its own. In a fresh clone the first step of the first
    controller compiles it, for seconds: in a service that happens inside its control loop,
    which already reports RUNNING, so that an operator's command waits past the control
    socket's time-out. Here it is compiled once in this process, and every service loads it."""
    from beamctl.gains.defaults import paper_table_path
    from beamctl.gains.table import load_table
    from beamctl.hal.base import Sample
    from beamctl.rt.config import controller_config
    from beamctl.rt.controller import Controller

    controller = Controller(load_table(paper_table_path()), controller_config({"pacing": "sample"}))
    sample = Sample()
    sample.axial_load = 1000.0
    controller.arm(sample)
    controller.start()
    controller.step(sample)


@pytest.fixture(scope="session")
def _dask_cluster(tmp_path_factory):
    pytest.importorskip("distributed")
    from tests.processes import DaskCluster

    cluster = DaskCluster(tmp_path_factory.mktemp("dask"))
    yield cluster
    cluster.close()


@pytest.fixture
def dask_cluster(_dask_cluster):
    """A Dask scheduler and two workers, each a process of its own on 127.0.0.1
    (tests/processes.py), shared by the tests: starting the processes and importing
    beamctl, scipy and numba in each worker costs seconds every time. A worker that a test
    killed is replaced by a new one before the next test gets the cluster."""
    _dask_cluster.revive()
    return _dask_cluster
