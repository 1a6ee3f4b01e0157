"""Real-time privileges: reported when granted or refused; --require-rt makes refusal fatal."""

import gc
import os

import pytest

from beamctl.rt import realtime
from beamctl.rt.config import controller_config


def test_refused_privileges_are_reported_and_the_run_goes_on(monkeypatch):
    def refuse(*_):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    report = realtime.acquire(controller_config({"realtime": {"lock_memory": False}}).realtime)
    try:
        assert report["scheduler"].startswith("refused") and "not permitted" in report["scheduler"]
        assert not gc.isenabled(), "the collector is off for the run"
    finally:
        realtime.release()
    assert gc.isenabled()


def test_require_rt_turns_a_refusal_into_an_error(monkeypatch):
    def refuse(*_):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    with pytest.raises(realtime.RealtimeError, match="SCHED_FIFO"):
        realtime.acquire(controller_config().realtime, require=True)
    assert gc.isenabled(), "a refused start gives the collector back"


def test_release_restores_the_previous_scheduling():
    before = (os.sched_getscheduler(0), os.sched_getaffinity(0))
    realtime.acquire(controller_config({"realtime": {"cpu": 0, "lock_memory": False}}).realtime)
    realtime.release()
    assert (os.sched_getscheduler(0), os.sched_getaffinity(0)) == before
