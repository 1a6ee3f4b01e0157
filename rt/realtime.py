"""Real-time privileges on Linux: SCHED_FIFO priority, CPU affinity (the process's other threads
kept off the loop's CPU), locked memory, and the garbage collector frozen and disabled for the
run. Each is asked for when permitted and
reported as granted or refused; with ``require`` a refusal is an error."""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
import threading

from beamctl.rt.config import Realtime

MCL_CURRENT, MCL_FUTURE = 1, 2
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


def _keep_off(cpu: int) -> str:
    """Move the process's other threads (telemetry, the control socket, the live view: started
    before the loop takes its CPU, and never scheduled beside it) to every CPU but ``cpu``: a
    thread of the normal class waiting on the loop's CPU is given its turn by the kernel's fair
    server (up to 50 ms a second) however high the loop's priority, a stall of the loop's own
    making."""
    others = set(os.sched_getaffinity(0)) | set(range(os.cpu_count() or 1))
    others.discard(cpu)
    if not others:
        return f"refused: no CPU but {cpu} to keep them on"
    me = threading.get_native_id()
    moved = 0
    try:
        tasks = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError as exc:
        return f"refused: /proc/self/task: {exc.strerror}"
    for tid in tasks:
        if tid == me:
            continue
        try:
            os.sched_setaffinity(tid, others)
            moved += 1
        except OSError:
            pass
    _previous["kept_off"] = tasks
    return f"granted: {moved} kept off CPU {cpu} (on {', '.join(str(c) for c in sorted(others))})"


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
        else:
            report["other threads"] = _keep_off(settings.cpu)
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
    """Undo ``acquire``: the garbage collector, memory lock, scheduler and affinity as before."""
    gc.enable()
    gc.unfreeze()
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
