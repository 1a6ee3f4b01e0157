"""The rig's I/O chain around the beam: the analogue anti-aliasing filter on the strain
channels, the transport delay from the DAQ's sampling instant to the stacks, and the analogue
reconstruction filter on the voltages (section 4 of the paper: elliptic low-pass filters on
both sides of the dSPACE system).

Configuration (``plant.io`` in a rig file, ``design.io`` in a gain table)::

    delay_samples: 0.0          # sampling instant -> voltages at the stacks, in samples (>= 0)
    anti_alias: none            # or {type: elliptic, order: 4, cutoff_hz: 1000,
    reconstruction: none        #     ripple_db: 0.5, attenuation_db: 40}

Filter types: ``butterworth``, ``bessel`` (phase-normalised) and ``elliptic`` (``ripple_db``
in the pass band, ``attenuation_db`` in the stop band), analogue, normalised to unit gain at
0 Hz (the amplifier's calibration). The same filter acts on every channel; the reconstruction
filter on the six voltages is modelled on the four lateral forces, which is the same thing
because the stack geometry is a constant linear map.

Sampled with a zero-order hold at period T, a delay of d = m + f samples (m whole, 0 <= f < 1)
makes the input switch inside the sample::

    x_k+1 = Ad x_k + B_now u_k-m + B_before u_k-m-1     (eq. of the delayed ZOH)

with B_now = Gamma((1 - f) T), B_before = Gamma(T) - Gamma((1 - f) T) and
Gamma(t) = int_0^t exp(A s) ds B. ``delayed_zoh`` computes these once, for the plant and for
every check, so the two can never disagree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg as sla
import scipy.signal as sig

from beamctl.config.schema import ConfigError

FILTER_TYPES = ("butterworth", "bessel", "elliptic")
IO_DEFAULTS: dict[str, Any] = {"delay_samples": 0.0, "anti_alias": "none", "reconstruction": "none"}
FILTER_DEFAULTS: dict[str, Any] = {"ripple_db": 0.5, "attenuation_db": 40.0}
MAX_FILTER_ORDER = 10


@dataclass(frozen=True)
class AnalogFilter:
    """An analogue low-pass filter: ``type``, ``order``, ``cutoff_hz`` (the -3 dB frequency for
    Butterworth and Bessel, the pass-band edge for elliptic)."""

    type: str
    order: int
    cutoff_hz: float
    ripple_db: float = FILTER_DEFAULTS["ripple_db"]
    attenuation_db: float = FILTER_DEFAULTS["attenuation_db"]

    def zpk(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Zeros, poles (rad/s) and gain of the analogue prototype, unit gain at 0 Hz."""
        wc = 2 * math.pi * self.cutoff_hz
        if self.type == "butterworth":
            z, p, k = sig.butter(self.order, wc, analog=True, output="zpk")
        elif self.type == "bessel":
            z, p, k = sig.bessel(self.order, wc, analog=True, output="zpk", norm="mag")
        else:
            z, p, k = sig.ellip(self.order, self.ripple_db, self.attenuation_db, wc, analog=True,
                                output="zpk")
        dc = k * np.prod(-z) / np.prod(-p) if len(z) else k / np.prod(-p)
        return np.asarray(z), np.asarray(p), float(k / dc.real)

    def state_space(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(A, B, C, D) of one channel, as a cascade of first- and second-order sections
        with states scaled by each section's natural frequency (well conditioned at kHz)."""
        z, p, k = self.zpk()
        return _cascade(z, p, k)

    def to_dict(self) -> dict[str, Any]:
        out = {"type": self.type, "order": self.order, "cutoff_hz": self.cutoff_hz}
        if self.type == "elliptic":
            out.update(ripple_db=self.ripple_db, attenuation_db=self.attenuation_db)
        return out


@dataclass(frozen=True)
class IOChain:
    """Delay and filters between the beam and the control law (see the module docstring)."""

    delay_samples: float = 0.0
    anti_alias: AnalogFilter | None = None
    reconstruction: AnalogFilter | None = None

    @property
    def is_direct(self) -> bool:
        """No delay and no filter: the chain the paper's design assumed."""
        return self.delay_samples == 0.0 and self.anti_alias is None and self.reconstruction is None

    def to_dict(self) -> dict[str, Any]:
        return {"delay_samples": self.delay_samples,
                "anti_alias": self.anti_alias.to_dict() if self.anti_alias else "none",
                "reconstruction": self.reconstruction.to_dict() if self.reconstruction else "none"}

    def describe(self) -> str:
        parts = [f"delay {self.delay_samples:g} samples"]
        for name, f in (("anti-alias", self.anti_alias), ("reconstruction", self.reconstruction)):
            if f is not None:
                text = f"{name} {f.type} order {f.order} at {f.cutoff_hz:g} Hz"
                if f.type == "elliptic":
                    text += f" ({f.ripple_db:g} dB ripple, {f.attenuation_db:g} dB attenuation)"
                parts.append(text)
        return ", ".join(parts)


def _number(value: Any, key: str, source: str, expected: str, *, low: float, low_open: bool = False,
            high: float = math.inf, whole: bool = False) -> float:
    ok = (not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)
          and (value > low if low_open else value >= low) and value <= high
          and (not whole or float(value).is_integer()))
    if not ok:
        raise ConfigError(key, value, expected, source)
    return float(value)


def analog_filter(data: Any, key: str, source: str = "") -> AnalogFilter | None:
    """A filter from its configuration mapping (``none``/``null`` for no filter)."""
    if data is None or data == "none":
        return None
    if not isinstance(data, dict):
        raise ConfigError(key, data, "'none' or a mapping with type, order and cutoff_hz", source)
    unknown = sorted(set(data) - {"type", "order", "cutoff_hz", "ripple_db", "attenuation_db"})
    if unknown:
        raise ConfigError(f"{key}.{unknown[0]}", data[unknown[0]],
                          "one of the known keys ['attenuation_db', 'cutoff_hz', 'order', "
                          "'ripple_db', 'type']", source)
    for needed in ("type", "order", "cutoff_hz"):
        if needed not in data:
            raise ConfigError(f"{key}.{needed}", None, "a value (the key is missing)", source)
    kind = data["type"]
    if kind not in FILTER_TYPES:
        raise ConfigError(f"{key}.type", kind, f"one of {', '.join(FILTER_TYPES)}", source)
    order = int(_number(data["order"], f"{key}.order", source,
                        f"an integer from 1 to {MAX_FILTER_ORDER}", low=1, high=MAX_FILTER_ORDER,
                        whole=True))
    cutoff = _number(data["cutoff_hz"], f"{key}.cutoff_hz", source, "a finite number > 0 (in Hz)",
                     low=0.0, low_open=True)
    ripple = _number(data.get("ripple_db", FILTER_DEFAULTS["ripple_db"]), f"{key}.ripple_db",
                     source, "a finite number > 0 (in dB)", low=0.0, low_open=True)
    attenuation = _number(data.get("attenuation_db", FILTER_DEFAULTS["attenuation_db"]),
                          f"{key}.attenuation_db", source,
                          f"a finite number > ripple_db = {ripple:g} (in dB)", low=ripple, low_open=True)
    return AnalogFilter(type=kind, order=order, cutoff_hz=cutoff, ripple_db=ripple,
                        attenuation_db=attenuation)


def io_chain(data: Any = None, source: str = "", prefix: str = "io") -> IOChain:
    """Validate an ``io`` mapping (missing keys take IO_DEFAULTS) into an IOChain; ``prefix``
    names the section in messages (``plant.io``, ``design.io``)."""
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ConfigError(prefix, data, "a mapping with delay_samples, anti_alias, reconstruction",
                          source)
    unknown = sorted(set(data) - set(IO_DEFAULTS))
    if unknown:
        raise ConfigError(f"{prefix}.{unknown[0]}", data[unknown[0]],
                          f"one of the known keys {sorted(IO_DEFAULTS)}", source)
    merged = {**IO_DEFAULTS, **data}
    delay = _number(merged["delay_samples"], f"{prefix}.delay_samples", source,
                    "a finite number >= 0 (in samples)", low=0.0)
    return IOChain(delay_samples=delay,
                   anti_alias=analog_filter(merged["anti_alias"], f"{prefix}.anti_alias", source),
                   reconstruction=analog_filter(merged["reconstruction"], f"{prefix}.reconstruction",
                                                source))


def _section(zeros: list[complex], poles: list[complex]):
    """One first- or second-order section with unit DC gain, states scaled by its natural
    frequency w0: x' = w0 (F x + G u), y = H x + J u."""
    if len(poles) == 1:
        p = poles[0].real
        w0 = -p
        if zeros:                       # (s - z) / (s - p) scaled to unit DC gain
            z = zeros[0].real
            g = p / z
            return np.array([[p]]), np.array([[1.0]]), np.array([[g * (p - z)]]), np.array([[g]])
        return np.array([[p]]), np.array([[w0]]), np.array([[1.0]]), np.array([[0.0]])
    a1 = float(-(poles[0] + poles[1]).real)
    a0 = float((poles[0] * poles[1]).real)
    w0 = math.sqrt(a0)
    # states: x1 = y_all-pole / 1, x2 = x1' / w0  (controllable form scaled by w0)
    a = np.array([[0.0, w0], [-a0 / w0, -a1]])
    b = np.array([[0.0], [w0]])
    # all-pole part: H0(s) = a0 / (s^2 + a1 s + a0) -> y0 = x1
    if not zeros:
        return a, b, np.array([[1.0, 0.0]]), np.array([[0.0]])
    # numerator (s^2 + c1 s + c0) / c0 times H0: y = (x1'' + c1 x1' + c0 x1) / c0
    c1 = float(-(sum(zeros)).real) if len(zeros) == 2 else 0.0
    c0 = float(np.prod(zeros).real) if len(zeros) == 2 else 0.0
    if len(zeros) == 1:                 # one real zero: (s - z)/(-z) H0
        z = zeros[0].real
        return a, b, np.array([[1.0, -w0 / z]]), np.array([[0.0]])
    # x1'' = -a0 x1 - a1 x1' + a0 u with x1' = w0 x2
    c = np.array([[(c0 - a0) / c0, w0 * (c1 - a1) / c0]])
    d = np.array([[a0 / c0]])
    return a, b, c, d


def _pairs(values: np.ndarray) -> list[list[complex]]:
    """Group roots into conjugate pairs and single real roots."""
    remaining = sorted((complex(v) for v in values), key=lambda v: (abs(v.imag) < 1e-9 * (abs(v) + 1),
                                                                     abs(v)))
    groups, used = [], [False] * len(remaining)
    for i, v in enumerate(remaining):
        if used[i]:
            continue
        used[i] = True
        if abs(v.imag) > 1e-9 * (abs(v) + 1):
            j = min((j for j in range(len(remaining)) if not used[j]),
                    key=lambda j: abs(remaining[j] - v.conjugate()))
            used[j] = True
            groups.append([v, remaining[j]])
        else:
            groups.append([v])
    return groups


def series(first, second):
    """State space of ``first`` followed by ``second`` (each (A, B, C, D))."""
    a1, b1, c1, d1 = first
    a2, b2, c2, d2 = second
    n1, n2 = a1.shape[0], a2.shape[0]
    a = np.zeros((n1 + n2, n1 + n2))
    a[:n1, :n1] = a1
    a[n1:, :n1] = b2 @ c1
    a[n1:, n1:] = a2
    b = np.vstack([b1, b2 @ d1])
    c = np.hstack([d2 @ c1, c2])
    return a, b, c, d2 @ d1


def _cascade(zeros: np.ndarray, poles: np.ndarray, gain: float):
    pole_groups = _pairs(poles)
    zero_groups = _pairs(zeros)
    # each pole pair takes the zero pair nearest to it (elliptic: the stop-band notches)
    sections = []
    for pg in sorted(pole_groups, key=lambda g: abs(g[0])):
        zs: list[complex] = []
        if zero_groups and len(pg) == 2:
            best = min(range(len(zero_groups)), key=lambda i: abs(abs(zero_groups[i][0]) - abs(pg[0])))
            zs = zero_groups.pop(best)
        sections.append(_section(zs, pg))
    total = sections[0]
    for s in sections[1:]:
        total = series(total, s)
    a, b, c, d = total
    # unit DC gain overall (each section has it; guard rounding)
    dc = float((d - c @ np.linalg.solve(a, b))[0, 0])
    return a, b, c / dc, d / dc


def channels(system, count: int):
    """The single-channel (A, B, C, D) repeated on ``count`` independent channels."""
    a, b, c, d = system
    eye = np.eye(count)
    return np.kron(eye, a), np.kron(eye, b), np.kron(eye, c), np.kron(eye, d)


def with_filters(a: np.ndarray, b: np.ndarray, c: np.ndarray, chain: IOChain, n_control: int):
    """The continuous plant (A, B, C) with the chain's filters: the reconstruction filter before
    the first ``n_control`` inputs (the other inputs, e.g. the axial load, pass unfiltered) and
    the anti-aliasing filter after every output. Returns (A, B, C, D); the state is
    [reconstruction filter, plant, anti-aliasing filter]."""
    n_out = c.shape[0]
    system = (a, b, c, np.zeros((n_out, b.shape[1])))
    if chain.reconstruction is not None:
        ra, rb, rc, rd = channels(chain.reconstruction.state_space(), n_control)
        m, nr = b.shape[1], ra.shape[0]
        pre_b = np.zeros((nr, m))
        pre_b[:, :n_control] = rb
        pre_c = np.zeros((m, nr))
        pre_c[:n_control] = rc
        pre_d = np.eye(m)
        pre_d[:n_control, :n_control] = rd
        pre = (ra, pre_b, pre_c, pre_d)
        system = series(pre, system)
    if chain.anti_alias is not None:
        system = series(system, channels(chain.anti_alias.state_space(), n_out))
    return system


@dataclass(frozen=True)
class DelayedZOH:
    """x_k+1 = ad x_k + b_now u_k-whole + b_before u_k-whole-1 + b_direct w_k (see module)."""

    ad: np.ndarray
    b_now: np.ndarray
    b_before: np.ndarray
    b_direct: np.ndarray
    whole: int
    fraction: float


def _gamma(a: np.ndarray, b: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
    """(exp(A t), int_0^t exp(A s) ds B) by one matrix exponential."""
    n, m = a.shape[0], b.shape[1]
    aug = np.zeros((n + m, n + m))
    aug[:n, :n], aug[:n, n:] = a, b
    phi = sla.expm(aug * t)
    return phi[:n, :n], phi[:n, n:]


def delayed_zoh(a: np.ndarray, b: np.ndarray, period: float, delay_samples: float,
                b_direct: np.ndarray | None = None) -> DelayedZOH:
    """Exact zero-order-hold discretisation of x' = A x + B u(t - d T) + B_direct w(t) with
    the delay d = ``delay_samples`` (see the module docstring); w is not delayed."""
    whole = int(math.floor(delay_samples))
    fraction = float(delay_samples - whole)
    n = a.shape[0]
    direct = np.zeros((n, 0)) if b_direct is None else b_direct
    both = np.hstack([b, direct])
    if fraction == 0.5:
        # half a sample: one exponential over half the period gives
        # both halves, exp(A T) = E E and int_0^T = G + E G
        e_half, g_half = _gamma(a, both, 0.5 * period)
        ad, gamma = e_half @ e_half, g_half + e_half @ g_half
        g_full, g_direct = gamma[:, :b.shape[1]], gamma[:, b.shape[1]:]
        b_now = g_half[:, :b.shape[1]]
        return DelayedZOH(ad=ad, b_now=b_now, b_before=g_full - b_now, b_direct=g_direct, whole=whole,
                          fraction=fraction)
    ad, gamma = _gamma(a, both, period)
    g_full, g_direct = gamma[:, :b.shape[1]], gamma[:, b.shape[1]:]
    if fraction == 0.0:
        b_now, b_before = g_full, np.zeros_like(g_full)
    else:
        _, b_now = _gamma(a, b, (1.0 - fraction) * period)
        b_before = g_full - b_now
    return DelayedZOH(ad=ad, b_now=b_now, b_before=b_before, b_direct=g_direct, whole=whole,
                      fraction=fraction)
