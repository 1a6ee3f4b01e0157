"""Gain tables swapped into the running service at bias (``TableSwaps``): read and checked in a
process of their own, so that the control loop never waits for the YAML parser."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from beamctl.assembly.run import ServiceConfig, check_voltage_range, load_gain_table
from beamctl.config.schema import ConfigError
from beamctl.gains.table import GainTable, GainTableError
from beamctl.hal.base import HalBase
from beamctl.rt.controller import Controller, PreparedTable


def read_gain_table(cfg: ServiceConfig, path: str) -> tuple[GainTable | None, str]:
    """``load_gain_table(cfg, path)`` with the table's content hash computed, as the reader
    process of ``TableSwaps`` runs it: (the table, "") or (None, why it was refused; as text,
    which passes between processes where an exception carrying its key would not)."""
    try:
        table = load_gain_table(cfg, path)
    except ConfigError as exc:
        return None, str(exc)
    if table.sha256:            # computed here, carried back with the table
        return table, ""
    return None, f"{path}: the table's content hash is empty"


def table_reader() -> None:
    """The reader process of ``TableSwaps``: each request on stdin, a pickled (config, path),
    is answered on stdout by the pickled ``read_gain_table(config, path)``, until stdin closes.
    Whatever else would print goes to stderr; Ctrl-C at the terminal is the service's to handle."""
    import pickle
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    answers = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    requests = sys.stdin.buffer
    while True:
        try:
            cfg, path = pickle.load(requests)
        except EOFError:
            return
        pickle.dump(read_gain_table(cfg, path), answers)
        answers.flush()


READER_SOURCE = ("import os\n"
                 "if hasattr(os, 'sched_setscheduler'):\n"
                 "    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))\n"
                 "from beamctl.service.swaps import table_reader\n"
                 "table_reader()\n")


class TableSwaps:
    """Gain tables for the running service to swap in at bias (``prepare(path)``), through the
    checks of its start (``load_gain_table``, ``check_voltage_range``) and the rig's: the table
    runs at the rate of the HAL and assumes the I/O chain (delay, filters) of the table running
    now. A ValueError (a ConfigError) says why a table is refused.

    The file is read and hashed in a process of its own (``table_reader``), started at the first
    swap and kept until ``close()``: the YAML parser and the hash hold the interpreter's lock for
    up to 0.2 s at a stretch, which the control loop would otherwise wait for (its cycles stalled
    by up to 55 ms per swap of the paper's table, measured). The process is started as
    ``subprocess`` starts one (vfork and exec): a fork of the service, its memory locked,
    stalled the loop for up to 0.7 s.
    """

    def __init__(self, cfg: ServiceConfig, hal: HalBase, controller: Controller) -> None:
        self.cfg, self.hal, self.controller = cfg, hal, controller
        self._reader: subprocess.Popen | None = None

    def _read(self, path: str) -> GainTable:
        import pickle

        if self._reader is None or self._reader.poll() is not None:
            # started from a thread at SCHED_FIFO (rt/realtime.py): the reader drops to the normal
            # class before anything else, so that its seconds of parsing never compete with the loop
            self._reader = subprocess.Popen(
                [sys.executable, "-c", READER_SOURCE],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        try:
            pickle.dump((self.cfg, path), self._reader.stdin)
            self._reader.stdin.flush()
            table, refusal = pickle.load(self._reader.stdout)
        except (OSError, EOFError, pickle.UnpicklingError):
            self.close()
            raise ValueError(f"{path}: the process reading the table ended before it was read") from None
        if table is None:
            raise ValueError(refusal)
        return table

    def prepare(self, path: str | Path) -> PreparedTable:
        table = self._read(str(path))
        check_voltage_range(self.cfg, self.hal)
        source = str(path)
        rate = table.design.sample_rate_hz
        if rate != self.hal.sample_rate_hz:
            raise GainTableError("design.sample_rate_hz", rate,
                                 f"the rate the service runs at, {self.hal.sample_rate_hz:g} Hz", source)
        running = self.controller.table.design.io
        if table.design.io != running:
            raise GainTableError("design.io", table.design.io.to_dict(),
                                 f"the I/O chain of the running table, {running.to_dict()} (the rig's)",
                                 source)
        return self.controller.prepare_table(table)

    def close(self) -> None:
        """End the reader process (after the read under way, if any)."""
        reader, self._reader = self._reader, None
        if reader is None:
            return
        reader.stdin.close()
        try:
            reader.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            reader.kill()
            reader.wait()
        reader.stdout.close()
