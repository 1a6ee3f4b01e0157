"""The controller's per-sample CAN path, timed in one process over the local bus.

Two ``beamctl_local`` buses on a private channel: a DAQ bus sends a ``DAQ_Load`` frame every
``SampleDivisor`` samples and a ``DAQ_Strains`` frame every sample (untimed); the controller's
``CanBackend`` reads the sample (timed: ``read``) and answers it (timed: ``write``); the DAQ bus
then drains the answers (untimed), so that no queue fills. The frames arrive faster than the
2500 Hz the backend expects, so the rate check is off (``rate_tolerance=0``). The garbage
collector is off while timing (as the loop's real-time set-up has it).

    python -m tests.hal.can_path_bench [samples] [repeats]

prints the median and 99th percentile of each, in microseconds, and the time of the first
``CanBackend`` (the codecs' compile or cache load included) as the first line.
"""

from __future__ import annotations

import gc
import os
import sys
import tempfile
import time

import numpy as np


def run(samples: int = 20_000) -> dict:
    import can

    from beamctl.hal.can_backend import CanBackend
    from beamctl.hal.dbc import Contract

    contract = Contract()
    channel = f"bench-{os.getpid()}"
    daq = can.Bus(interface="beamctl_local", channel=channel)
    backend = CanBackend(2500.0, "beamctl_local", channel, rate_tolerance=0.0).open()
    strains, load = contract.strains, contract.load
    load_frames = [can.Message(arbitration_id=load.frame_id, is_extended_id=False,
                               data=load.encode([1500.0, k, 0])) for k in range(256)]
    strain_frames = [can.Message(arbitration_id=strains.frame_id, is_extended_id=False,
                                 data=strains.encode([1e-5 * (k % 7), -2e-5, 3e-6, 0.0, k, 0]))
                     for k in range(256)]
    volts = np.array([75.0, 80.4, 60.0, 90.0, 120.0, 30.0])
    reads = np.empty(samples)
    writes = np.empty(samples)
    clock = time.perf_counter_ns
    gc.collect()
    gc.disable()
    try:
        for k in range(samples):
            if k % load.divisor == 0:
                daq.send(load_frames[(k // load.divisor) & 0xFF])
            daq.send(strain_frames[k & 0xFF])
            t0 = clock()
            backend.read(0.5)
            t1 = clock()
            backend.write(volts)
            t2 = clock()
            reads[k], writes[k] = t1 - t0, t2 - t1
            while daq.recv(0.0) is not None:
                pass
    finally:
        gc.enable()
        status = backend.status()
        backend.close()
        daq.shutdown()
    assert status["reads"] == samples and status["frames_out"] >= samples, status
    warm = samples // 10                    # the first tenth warms the caches up
    r, w = reads[warm:] / 1e3, writes[warm:] / 1e3
    return {"read_median_us": float(np.median(r)), "read_p99_us": float(np.percentile(r, 99)),
            "write_median_us": float(np.median(w)), "write_p99_us": float(np.percentile(w, 99))}


def main(argv: list[str]) -> None:
    samples = int(argv[0]) if argv else 20_000
    repeats = int(argv[1]) if len(argv) > 1 else 3
    with tempfile.TemporaryDirectory(prefix="bc-bench-") as tmp:
        base = os.path.join(tmp, "bus")
        os.mkdir(base, 0o700)
        os.environ["BEAMCTL_LOCALBUS_DIR"] = base
        start = time.perf_counter()
        from beamctl.hal.can_backend import CanBackend
        CanBackend(2500.0, "beamctl_local", "first")
        print(f"first CanBackend (imports, DBC, codecs' compile or cache load): "
              f"{time.perf_counter() - start:.3f} s")
        for _ in range(repeats):
            result = run(samples)
            print("  ".join(f"{k} {v:6.2f}" for k, v in result.items()))


if __name__ == "__main__":
    main(sys.argv[1:])
