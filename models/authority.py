"""Stack authority: how much of the stacks' voltage swing holding the beam straight takes at
each axial load, predicted from static strains measured at rest below the critical load.

At rest, integral action holds the gauges' strains at zero, so the stacks' four static forces u
(Fay,A, Faz,A, Fay,B, Faz,B) cancel the strain that the rig's imperfections (an eccentric load, a
bow, clamping moments: whatever they are) cause at that load:

    X(F) u = -s_p(F),    X(F) = C0 (Ke - F Kg)^-1 B0  (the model's static strain per force),

s_p the static strain of the beam without the stacks ("passive") at load F. A measurement at rest
at load F_m with static forces u_m (zero in open loop at bias; the law's in closed loop) gives
s_p(F_m) = s_m - X(F_m) u_m. Between and beyond the measured loads s_p follows Southwell, per gauge

    s_p(F) = F (a / (1 - F / Fcr) + b)

(a: the first buckling mode's share, amplified towards Fcr; b: the rest, nearly constant),
fitted by least squares to the measured strains at two or more loads (their amplifications
1 / (1 - F/Fcr) at least ``MIN_SPREAD`` apart, else they count as one; below ``CLOSE_SPREAD`` the
result warns that it is looser: 1000 and 2000 N on a 3200 N beam, 1.45 and 2.67, predict within
about 2 points of the swing, 500 and 1000 N within about 6 %; a point not between 0 and Fcr, or
not finite, is left out with a warning). From one load b = 0, all of the imperfection in the
first mode: one load cannot tell an eccentric load from a bow, and the result may be well off
either way (an eccentric load alone: 12 % low from 2000 N, 22 % from 1000 N; with a bow that
opposes it, twice too low or too high), which the result says. The prediction needs no model of
the imperfection,
only the model's static compliance X, which the fit to the frequency responses determines.
Near Fcr the demand tends to a finite value (both X and s_p grow as 1 / (1 - F/Fcr)): there the
beam's own stiffness is gone and the stacks carry the whole imperfection; past Fcr it goes on
growing. No design does better at Fcr itself: any static shape the stacks hold there needs the
same first-mode force. Below Fcr a design that let the beam bend would need less than the straight
beam takes (half of it 5 % below Fcr, tests/models/test_authority.py): what is predicted there is
what integral action, holding the gauges at zero, asks of the stacks.

The voltages follow the allocation (rt/allocation.py): ``scale`` needs the spread of a
support's three voltages within the span; ``clip`` each stack within its own room about the
bias. The fraction of the swing used is the largest over the supports (or stacks); 1 means a
stack at its limit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from beamctl.models.actuators import StackGeometry
from beamctl.models.analysis import buckling_mode, critical_load
from beamctl.models.fe import FEModel

# the load just below Fcr where the demand at Fcr is evaluated (the formulas' common pole)
BELOW_CRITICAL = 1e-4
# the grid of the predicted curve: from 0 to this multiple of Fcr
GRID_TOP_FRACTION = 1.2
GRID_POINTS = 121
# two loads whose amplifications 1 / (1 - F/Fcr) differ by less than MIN_SPREAD tell a from b
# apart no better than one load; below CLOSE_SPREAD the prediction is looser (module docstring;
# 1000 and 2000 N on a 3200 N beam: 1.45 and 2.67, 1.22 apart; 500 and 1000 N: 0.27)
MIN_SPREAD = 0.2
CLOSE_SPREAD = 0.8
# a static strain or stack force beyond these is no beam's at rest (1 % strain is past any metal's
# yield; piezo stacks give kilonewtons): a measurement error, left out
MAX_STRAIN = 0.01
MAX_FORCE_N = 1e5
# from this fraction at Fcr the text says the margin is little (a rig needing 94 % was held past
# its Fx,cr in the simulated experiment, its run's voltages a few % above the static need)
LITTLE_MARGIN = 0.95


@dataclass(frozen=True)
class StaticPoint:
    """The beam at rest at one load: the mean strains (4, as the gauges read them: zero with the
    beam unloaded) and the stacks' mean forces (4, N) while they were measured."""

    load_n: float
    strain: tuple[float, float, float, float]
    force_n: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    source: str = ""


@dataclass
class StackAuthority:
    """The prediction: the fraction of the stacks' swing used at each load."""

    critical_load_n: float
    loads_n: list[float]
    fraction: list[float]
    measured: list[tuple[float, float]]          # (load, fraction) at the measured loads
    at_critical: float                           # the fraction at Fcr
    limit_n: float | None                        # the first load at which a stack reaches its limit
    method: str
    one_load: bool = False                       # rough: it may be well off either way
    warnings: list[str] = field(default_factory=list)
    forces: Callable[[float], np.ndarray] | None = field(default=None, repr=False, compare=False)

    @property
    def not_enough(self) -> bool:
        """A stack reaches its limit at or below Fcr."""
        return self.limit_n is not None and self.limit_n <= self.critical_load_n

    def to_json(self) -> dict:
        return {"critical_load_n": self.critical_load_n, "at_critical": self.at_critical,
                "limit_n": self.limit_n, "not_enough": self.not_enough, "method": self.method,
                "one_load": self.one_load,
                "measured": self.measured,
                "loads_n": self.loads_n, "fraction": self.fraction, "warnings": self.warnings}

    def text(self) -> str:
        """One line: the fraction at Fcr and where the stacks run out."""
        amount = (f"roughly {100 * self.at_critical:.0f} % (from one load, which cannot tell an eccentric "
                  "load from a bow: it may be well off either way)" if self.one_load
                  else f"{100 * self.at_critical:.0f} %")
        head = (f"holding the beam straight takes {amount} of the stacks' swing at the fitted Fx,cr "
                f"{self.critical_load_n:.0f} N")
        if self.not_enough:
            check = ("; measure at a second load to be sure" if self.one_load else "")
            return (f"{head}: NOT ENOUGH, a stack reaches its limit at about {self.limit_n:.0f} N. At Fx,cr "
                    "the rig's imperfection (eccentric load, bow) needs more force than these stacks give, "
                    "whatever the gains: align the load line, straighten the beam, or use stiffer stacks"
                    f"{check}")
        tail = (f"; a stack reaches its limit at about {self.limit_n:.0f} N" if self.limit_n is not None
                else f"; within the swing to {self.loads_n[-1]:.0f} N")
        if self.at_critical >= LITTLE_MARGIN:
            tail += "; little margin: the control's own motion and the noise take a few % more"
        return f"{head} ({self.method}){tail}"


def static_compliance(model: FEModel, load_n: float) -> np.ndarray:
    """[4 x 4] X(F): the static strains per newton of each stack force at axial load F."""
    k = model.load_stiffness(load_n)
    return model.output_matrix @ np.linalg.solve(k, model.input_matrix)


def passive_strain(model: FEModel, point: StaticPoint) -> np.ndarray:
    """s_p at the point's load: the measured strain less what the stacks' forces caused."""
    forces = np.asarray(point.force_n, float)
    return np.asarray(point.strain, float) - static_compliance(model, point.load_n) @ forces


def swing_fraction(forces: np.ndarray, geometry: StackGeometry, min_v: float, max_v: float,
                   allocation: str = "scale") -> float:
    """The fraction of the swing that the four forces take (see the module docstring): the
    voltages V_i = bias + 2/3 e_i . F / k, unclipped, measured as ``voltage_fraction`` does."""
    bias = geometry.bias_voltage_v
    volts = [bias + 2.0 / 3.0 * axes @ forces[2 * s:2 * s + 2] / geometry.force_constant_n_per_v
             for s, axes in enumerate(geometry.axes())]
    return voltage_fraction(np.concatenate(volts), min_v, max_v, bias, allocation)


def voltage_fraction(voltages, min_v: float, max_v: float, bias_v: float, allocation: str = "scale") -> float:
    """The fraction of the swing six applied voltages (a1, a2, a3, b1, b2, b3) take: the spread
    of a support's three over the span (``scale``), or a stack's distance from the bias over its
    room on that side (``clip``); the larger of the supports'."""
    v = np.asarray(voltages, dtype=float).reshape(2, 3)
    if allocation == "clip":
        d = v - bias_v
        return float(np.max(np.where(d > 0, d / (max_v - bias_v), -d / (bias_v - min_v))))
    return float(np.max(np.ptp(v, axis=1)) / (max_v - min_v))


def predict(model: FEModel, points: list[StaticPoint], geometry: StackGeometry, min_v: float,
            max_v: float, allocation: str = "scale") -> StackAuthority:
    """The stacks' use over the load range from static measurements (module docstring).

    A point that cannot be used (a load not between 0 and Fcr, a strain or force not finite or
    beyond any beam's) is left out, named in ``warnings``. Raises ValueError (one line) when none
    is left, naming the first left out, or when the result is not finite."""
    fcr = critical_load(model)
    warnings: list[str] = []
    usable = []
    for p in points:
        where = f"the static strains of {p.source or 'a measurement'} at {p.load_n:.0f} N"
        if not (0.0 < p.load_n < fcr):
            warnings.append(f"{where} are left out: the load is not between 0 and the critical load "
                            f"{fcr:.0f} N")
        elif len(p.strain) != 4 or len(p.force_n) != 4 or not np.all(np.isfinite([*p.strain, *p.force_n])):
            warnings.append(f"{where} are left out: not 4 finite strains and 4 finite forces")
        elif np.max(np.abs(p.strain)) > MAX_STRAIN or np.max(np.abs(p.force_n)) > MAX_FORCE_N:
            warnings.append(f"{where} are left out: beyond any elastic strain ({MAX_STRAIN:g}) or stack "
                            f"force ({MAX_FORCE_N:g} N)")
        else:
            usable.append(p)
    if not usable:
        raise ValueError("no usable static measurement" + (f" ({warnings[0]})" if warnings else ""))
    loads = np.array([p.load_n for p in usable])
    sp = np.array([passive_strain(model, p) for p in usable])                   # [m x 4]
    amp = 1.0 / (1.0 - loads / fcr)
    # only the first buckling mode grows as 1 / (1 - F/Fcr): a lies in the strain pattern of its
    # two planes (anything else fitted into a would be amplified without bound near Fcr)
    pattern = np.column_stack([model.output_matrix @ buckling_mode(model, plane)[1] for plane in ("y", "z")])
    m = len(usable)
    one_load = bool(np.ptp(amp) < MIN_SPREAD)
    if not one_load:
        # s_p = F amp pattern alpha + F b: unknowns alpha (2), b (4); 4 equations per load
        design = np.zeros((4 * m, 6))
        for i in range(m):
            design[4 * i:4 * i + 4, :2] = loads[i] * amp[i] * pattern
            design[4 * i:4 * i + 4, 2:] = loads[i] * np.eye(4)
        coef, *_ = np.linalg.lstsq(design, sp.reshape(-1), rcond=None)
        a, b = pattern @ coef[:2], coef[2:]
        method = f"Southwell through the static strains at {', '.join(f'{x:.0f}' for x in loads)} N"
        if np.ptp(amp) < CLOSE_SPREAD:
            warnings.append(f"the loads measured are close together (amplifications {np.min(amp):.2f} to "
                            f"{np.max(amp):.2f}): the prediction may be off by about 6 %; a top load near "
                            f"{0.6 * fcr:.0f} N (0.6 x Fx,cr) with one near half of it predicts within about "
                            "2 points of the swing")
    else:
        design = np.vstack([f * k * pattern for f, k in zip(loads, amp, strict=True)])
        coef, *_ = np.linalg.lstsq(design, sp.reshape(-1), rcond=None)
        a, b = pattern @ coef, np.zeros(4)
        method = f"from one load ({np.mean(loads):.0f} N), rough"
        warnings.append("the stacks' use near Fx,cr is estimated from one load, which cannot tell an "
                        "eccentric load from a bow: it may be well off either way; measure at two loads "
                        "apart (for example 1000 and 2000 N) to predict it within about 2 points of the "
                        "swing")

    def forces(f: float) -> np.ndarray:
        """The four static forces that hold the gauges at zero strain at load f."""
        return -np.linalg.solve(static_compliance(model, f), f * (a / (1.0 - f / fcr) + b))

    def fraction_at(f: float) -> float:
        return swing_fraction(forces(f), geometry, min_v, max_v, allocation)

    grid = np.linspace(0.0, GRID_TOP_FRACTION * fcr, GRID_POINTS)
    grid = grid[np.abs(grid / fcr - 1.0) > BELOW_CRITICAL]
    fraction = [fraction_at(float(f)) for f in grid]
    at_critical = fraction_at(fcr * (1.0 - BELOW_CRITICAL))
    limit = None
    for f0, f1, r0, r1 in zip(grid[:-1], grid[1:], fraction[:-1], fraction[1:], strict=True):
        if r0 < 1.0 <= r1:
            limit = float(f0 + (1.0 - r0) / (r1 - r0) * (f1 - f0))
            break
    if limit is None and at_critical >= 1.0:
        limit = fcr
    if not (math.isfinite(at_critical) and all(math.isfinite(x) for x in fraction)):
        raise ValueError("the static strains give no finite prediction (values far outside a beam's)")
    measured = []
    for p in usable:
        u = np.asarray(p.force_n, float) - np.linalg.solve(static_compliance(model, p.load_n),
                                                           np.asarray(p.strain, float))
        measured.append((p.load_n, swing_fraction(u, geometry, min_v, max_v, allocation)))
    return StackAuthority(critical_load_n=fcr, loads_n=[float(x) for x in grid], fraction=fraction,
                          measured=measured, at_critical=at_critical, limit_n=limit, method=method,
                          one_load=one_load, warnings=warnings, forces=forces)


def finite_point(load_n: float, static: dict, source: str) -> StaticPoint:
    """A StaticPoint from a measurement's ``settings["static"]`` (identification/identify.py); a
    value that is not finite is left for ``predict`` to leave out, with a warning."""
    try:
        if not all(isinstance(static.get(key, []), list | tuple) for key in ("strain", "force_n")):
            raise TypeError
        strain = tuple(float(x) for x in static["strain"])
        force = tuple(float(x) for x in static.get("force_n", (0.0,) * 4))
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{source}: its static strains are not 4 numbers") from None
    if len(strain) != 4 or len(force) != 4:
        raise ValueError(f"{source}: its static strains are not 4 numbers")
    return StaticPoint(load_n=load_n, strain=strain, force_n=force, source=source)
