"""Excitation signals for identifying the rig: periodic, so that a record of whole periods has
no leakage and every period after the first (the transient) is one average.

- ``multisine``: equal-amplitude cosines on every frequency line of the band (the lines of the
  period, k / (P T)), random phases (seeded);
- ``chirp``: a linear sweep across the band within one period, repeated;
- ``prbs``: a maximum-length binary sequence, each bit held for ``hold`` samples so that its
  spectrum covers the band (the first null at 1 / (hold T) lies at 2.5 x the band's top).

Each signal is scaled to a peak of 1; ``voltage_directions`` turns it into the six stack voltages
that push along one lateral force axis of one support (the stacks' minimum-norm combination, the
largest stack swing equal to the amplitude), so the voltages never leave bias +- amplitude.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.signal as sig

from beamctl.config.schema import ConfigError
from beamctl.models.actuators import StackGeometry
from beamctl.models.measured import INPUTS

SIGNALS = ("multisine", "chirp", "prbs")
SUPPORT_INPUTS = {"A": (0, 1), "B": (2, 3), "AB": (0, 1, 2, 3)}
PRBS_BANDWIDTH = 2.5        # the bit rate over the band's top frequency
MAX_PRBS_BITS = 24
MIN_RESOLUTION_HZ = 0.01            # a period of at most 100 s


@dataclass(frozen=True)
class Excitation:
    """One periodic signal: ``period`` samples of ``values`` (peak 1), repeated."""

    kind: str
    values: np.ndarray
    sample_rate_hz: float

    @property
    def period_samples(self) -> int:
        return len(self.values)

    @property
    def resolution_hz(self) -> float:
        return self.sample_rate_hz / self.period_samples


def periodic_signal(kind: str, sample_rate_hz: float, band_hz: tuple[float, float],
                    resolution_hz: float, seed: int = 0) -> Excitation:
    """A periodic excitation of one input, peak 1 (see the module docstring). The period is
    ``sample_rate_hz / resolution_hz`` samples (the PRBS: the next whole sequence that long or
    longer)."""
    low, high = band_hz
    nyquist = sample_rate_hz / 2
    if not 0 <= low < high <= nyquist:
        raise ConfigError("--band", f"{low:g}:{high:g}",
                          f"0 <= LOW < HIGH <= the Nyquist frequency {nyquist:g} Hz (the rig samples at "
                          f"{sample_rate_hz:g} Hz)")
    if not (math.isfinite(resolution_hz) and resolution_hz >= MIN_RESOLUTION_HZ
            and resolution_hz <= (high - low) / 4):
        raise ConfigError("--resolution", resolution_hz,
                          f"a frequency step from {MIN_RESOLUTION_HZ:g} Hz (a period of "
                          f"{1 / MIN_RESOLUTION_HZ:g} s) that puts at least 4 lines into the band "
                          f"{low:g}..{high:g} Hz")
    period = int(round(sample_rate_hz / resolution_hz))
    rng = np.random.default_rng(seed)
    if kind == "multisine":
        spectrum = np.zeros(period // 2 + 1, dtype=complex)
        lines = excited_lines(period, sample_rate_hz, band_hz)
        spectrum[lines] = np.exp(1j * rng.uniform(0.0, 2 * np.pi, len(lines)))
        values = np.fft.irfft(spectrum, n=period)
    elif kind == "chirp":
        t = np.arange(period) / sample_rate_hz
        values = sig.chirp(t, f0=low, t1=period / sample_rate_hz, f1=high, method="linear")
    elif kind == "prbs":
        hold = max(1, int(sample_rate_hz / (PRBS_BANDWIDTH * high)))
        bits = max(4, math.ceil(math.log2(period / hold + 1)))
        if bits > MAX_PRBS_BITS:
            raise ConfigError("--resolution", resolution_hz, "a coarser frequency step for prbs "
                              f"(at most 2^{MAX_PRBS_BITS} - 1 bits a period)")
        sequence = sig.max_len_seq(bits, state=rng.integers(0, 2, bits) | np.eye(1, bits, 0, dtype=int)[0])[0]
        values = np.repeat(2.0 * sequence - 1.0, hold)
    else:
        raise ConfigError("--signal", kind, f"one of {', '.join(SIGNALS)}")
    values = values - values.mean()
    return Excitation(kind=kind, values=values / np.max(np.abs(values)), sample_rate_hz=sample_rate_hz)


def excited_lines(period: int, sample_rate_hz: float, band_hz: tuple[float, float]) -> np.ndarray:
    """The DFT lines k (k / (period T) Hz) of a period inside the band, 0 Hz and the Nyquist
    line left out."""
    k = np.arange(1, (period + 1) // 2)
    f = k * sample_rate_hz / period
    return k[(f >= band_hz[0]) & (f <= band_hz[1])]


def voltage_directions(geometry: StackGeometry) -> np.ndarray:
    """[4 x 6]: row j, the stack voltages (about bias) that push along lateral force j
    (Fay,A, Faz,A, Fay,B, Faz,B) alone, the largest stack swing 1 V; the force per volt of
    swing along that axis is ``force_per_volt[j]`` of ``force_gains``."""
    directions = np.linalg.pinv(geometry.force_matrix()).T          # [4 x 6]
    return directions / np.max(np.abs(directions), axis=1, keepdims=True)


def force_gains(geometry: StackGeometry) -> np.ndarray:
    """[4]: the lateral force (N) one volt of swing along ``voltage_directions`` gives."""
    return np.einsum("jj->j", geometry.force_matrix() @ voltage_directions(geometry).T)


def input_names(inputs: tuple[int, ...]) -> list[str]:
    return [INPUTS[j] for j in inputs]
