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


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler") or os.geteuid() != 0,
                    reason="setting another thread's SCHED_FIFO needs root (CAP_SYS_NICE)")
def test_the_other_threads_run_at_the_helper_priority_off_the_loop_s_cpu_and_are_restored():
    """A thread of the process holding the interpreter's lock holds the loop up: for the run the
    other threads are SCHED_FIFO at helper_priority (nothing below the loop keeps them off their
    CPU), off the loop's CPU, the switch interval short; afterwards as they were."""
    import sys
    import threading

    done = threading.Event()
    other = threading.Thread(target=done.wait, daemon=True)
    other.start()
    tid = other.native_id
    before = (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority, os.sched_getaffinity(tid),
              sys.getswitchinterval())
    cpus = os.cpu_count() or 1
    settings = controller_config({"realtime": {"lock_memory": False, "helper_priority": 30,
                                               "cpu": 0 if cpus > 1 else -1}}).realtime
    report = realtime.acquire(settings)
    try:
        assert report["other threads"].startswith("granted"), report
        assert os.sched_getscheduler(tid) == os.SCHED_FIFO and os.sched_getparam(tid).sched_priority == 30
        if cpus > 1:
            assert 0 not in os.sched_getaffinity(tid), "the other threads are kept off the loop's CPU"
        assert sys.getswitchinterval() == pytest.approx(realtime.SWITCH_INTERVAL_S)
    finally:
        realtime.release()
        done.set()
    assert (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority, os.sched_getaffinity(tid),
            sys.getswitchinterval()) == before


def test_the_helpers_priority_must_be_below_the_loop_s():
    """Given, it must be below the loop's; not given, 60, or one below a loop set lower."""
    from beamctl.config.schema import ConfigError

    with pytest.raises(ConfigError, match="realtime.helper_priority"):
        controller_config({"realtime": {"priority": 50, "helper_priority": 50}})
    assert controller_config().realtime.helper_priority == 60
    assert controller_config({"realtime": {"priority": 50}}).realtime.helper_priority == 49
