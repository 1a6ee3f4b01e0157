"""Real-time privileges on Linux: SCHED_FIFO priority, CPU affinity, locked memory, and the
garbage collector frozen and disabled for the run. Each is asked for when permitted and reported
as granted or refused; with ``require`` a refusal is an error.

The process's other threads (telemetry, the control socket, the live view) share the
interpreter's lock with the loop: whichever of them holds it when a sample arrives holds the loop
up until it lets go. Two things bound that wait. The other threads run SCHED_FIFO too, at
``helper_priority`` (below the loop's, above every task of the normal class), off the loop's CPU
when it has one: a thread of the normal class holding the lock can be kept off its CPU for tens
of ms by any busier task (measured with the scheduler's trace: the loop waiting 18 ms for the lock
held by the telemetry writer, itself waiting behind a daemon at nice -10), and one waiting
on the loop's CPU is given its turn by the kernel's fair server (up to 50 ms a second) however
high the loop's priority. And the interpreter's switch interval is ``SWITCH_INTERVAL_S`` for the
run (5 ms by default: a thread computing in Python would keep the lock that long once the loop
asks for it)."""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
import sys
import threading

from beamctl.rt.config import Realtime

MCL_CURRENT, MCL_FUTURE = 1, 2
SWITCH_INTERVAL_S = 1e-4    # the interpreter's switch interval during the run
_previous: dict = {}


class RealtimeError(RuntimeError):
    """A real-time privilege was refused and ``--require-rt`` was given."""


def _mlockall() -> str | None:
    libc_name = ctypes.util.find_library("c")
    if not libc_name:
        return "libc not found"
    libc = ctypes.CDLL(libc_name, use_errno=True)
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
        return os.strerror(ctypes.get_errno())
    return None


def _helpers(cpu: int, priority: int) -> str:
    """Put the process's other threads (started before the loop takes its CPU) at SCHED_FIFO
    ``priority`` and, when the loop has a CPU, on every CPU but that one; remember how they were."""
    others = set(os.sched_getaffinity(0)) | set(range(os.cpu_count() or 1))
    if cpu >= 0:
        others.discard(cpu)
        if not others:
            return f"refused: no CPU but {cpu} to keep them on"
    me = threading.get_native_id()
    try:
        tasks = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError as exc:
        return f"refused: /proc/self/task: {exc.strerror}"
    moved, refusals = 0, set()
    for tid in tasks:
        if tid == me:
            continue
        try:
            before = (os.sched_getscheduler(tid), os.sched_getparam(tid), os.sched_getaffinity(tid))
        except OSError:         # ended meanwhile
            continue
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
            if cpu >= 0:
                os.sched_setaffinity(tid, others)
        except ProcessLookupError:      # ended meanwhile
            continue
        except OSError as exc:
            refusals.add(exc.strerror)
            _restore_thread(tid, before)
            continue
        _previous.setdefault("helpers", {})[tid] = before
        moved += 1
    if refusals:
        return f"refused: SCHED_FIFO priority {priority}: {'; '.join(sorted(refusals))}"
    where = f", kept off CPU {cpu} (on {', '.join(str(c) for c in sorted(others))})" if cpu >= 0 else ""
    return f"granted: {moved} at SCHED_FIFO priority {priority}{where}"


def _restore_thread(tid: int, before: tuple) -> None:
    policy, param, affinity = before
    try:
        os.sched_setscheduler(tid, policy, param)
        os.sched_setaffinity(tid, affinity)
    except OSError:             # ended meanwhile
        pass


def rt_budget_share() -> float | None:
    """The share of a CPU Linux lets real-time threads take (kernel.sched_rt_runtime_us over
    sched_rt_period_us; a thread past it is held for the rest of the period): 1.0 when unlimited,
    None where unknown."""
    try:
        with open("/proc/sys/kernel/sched_rt_runtime_us") as f:
            runtime = int(f.read())
        with open("/proc/sys/kernel/sched_rt_period_us") as f:
            period = int(f.read())
    except (OSError, ValueError):
        return None
    return 1.0 if runtime < 0 or period <= 0 else runtime / period


def acquire(settings: Realtime, require: bool = False) -> dict[str, str]:
    """Ask for everything in ``settings``; return {item: 'granted ...' | 'refused: why'}."""
    report: dict[str, str] = {}
    _previous.clear()
    if hasattr(os, "sched_getscheduler"):
        _previous["scheduler"] = (os.sched_getscheduler(0), os.sched_getparam(0))
        _previous["affinity"] = os.sched_getaffinity(0)
    if hasattr(os, "sched_setscheduler"):
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(settings.priority))
            report["scheduler"] = f"granted SCHED_FIFO priority {settings.priority}"
        except OSError as exc:
            report["scheduler"] = f"refused: SCHED_FIFO priority {settings.priority}: {exc.strerror}"
    else:
        report["scheduler"] = "refused: SCHED_FIFO not available on this system"
    if settings.cpu >= 0:
        try:
            os.sched_setaffinity(0, {settings.cpu})
            report["affinity"] = f"granted CPU {settings.cpu}"
        except (OSError, AttributeError) as exc:
            report["affinity"] = f"refused: CPU {settings.cpu}: {getattr(exc, 'strerror', exc)}"
    if hasattr(os, "sched_setscheduler"):
        report["other threads"] = _helpers(settings.cpu, settings.helper_priority)
    _previous["switch_interval"] = sys.getswitchinterval()
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    report["switch interval"] = f"granted {SWITCH_INTERVAL_S * 1e6:g} us"
    budget = rt_budget_share()
    if budget is not None:
        report["kernel budget"] = ("unlimited (kernel.sched_rt_runtime_us -1)" if budget >= 1.0 else
                                   f"{100 * budget:g} % of a CPU (kernel.sched_rt_runtime_us): a loop taking "
                                   f"more is held for the rest of each second")
    if settings.lock_memory:
        error = _mlockall()
        report["memory"] = "granted mlockall" if error is None else f"refused: mlockall: {error}"
        _previous["locked"] = error is None
    gc.collect()
    gc.freeze()
    gc.disable()
    report["gc"] = "granted: collected, frozen and disabled for the run"
    refused = {k: v for k, v in report.items() if v.startswith("refused")}
    if require and refused:
        release()
        raise RealtimeError("real-time privileges refused (--require-rt): "
                            + "; ".join(f"{k} {v}" for k, v in refused.items()))
    return report


def release() -> None:
    """Undo ``acquire``: the garbage collector, switch interval, memory lock, scheduler and
    affinity (the loop's and the other threads') as before."""
    gc.enable()
    gc.unfreeze()
    if "switch_interval" in _previous:
        sys.setswitchinterval(_previous.pop("switch_interval"))
    for tid, before in _previous.pop("helpers", {}).items():
        _restore_thread(tid, before)
    if _previous.pop("locked", False):
        libc_name = ctypes.util.find_library("c")
        if libc_name:
            ctypes.CDLL(libc_name).munlockall()
    if "scheduler" in _previous:
        policy, param = _previous.pop("scheduler")
        try:
            os.sched_setscheduler(0, policy, param)
        except OSError:
            pass
    if "affinity" in _previous:
        try:
            os.sched_setaffinity(0, _previous.pop("affinity"))
        except OSError:
            pass
