"""The one controller form every design is written in: per grid load a discrete state-space
compensator with integral action (python-control's estimator + state feedback, as data).

Per sample k, with y the four strains and u the four lateral forces (Fay,A, Faz,A, Fay,B,
Faz,B)::

    xi_k    = xi_k-1 + T H y_k                         integral action (H: gauges -> modal q)
    u_k     = -(C x_k + D y_k) - Ki xi_k               the law
    x_k+1   = A x_k + B y_k + E u_applied,k            the compensator state

where u_applied is the force the stacks actually produce after allocation, saturation and the
fade-in (so an estimator in x never drifts under saturation). A, B, E, C, D, Ki depend on the
axial load and are interpolated linearly between grid points by the schedule; H, the start
map and the period do not. ``x`` starts at ``start @ y`` (bumpless).

A sample that does not arrive is bridged by a prediction step: with the strains predicted from
the compensator state, y_hat = P x (``predict``, [4 x n] per grid load, interpolated like the
rest), the integral xi held and u_held the force of the voltages the stacks hold::

    x_k+1   = A x_k + B y_hat + E u_held

For a model-based estimator P x is the strain its prediction expects, so the step is the
estimator's time update without a measurement. ``predict`` None (a design without a
prediction, such as the paper's) means y_hat = the last measured strains.

The paper's design is one instance (``from_integral_lqr``): x is the first-order Butterworth
high-pass state of the modal velocity estimate, so A = -a1 I, E = 0 and the voltages equal
those of the paper's step written out (q, dq/dt, xi, K) to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# (strain / force) channel indices of each bending plane
PLANE_CHANNELS = {"y": (0, 2), "z": (1, 3)}
MATRICES = ("a", "b", "e", "c", "d", "ki")


@dataclass(frozen=True)
class CompensatorPoint:
    """The compensator matrices at one axial load (A [n x n], B [n x 4], E [n x 4],
    C [4 x n], D [4 x 4], Ki [4 x 4]) and the strain prediction P [4 x n] (None: none)."""

    a: np.ndarray
    b: np.ndarray
    e: np.ndarray
    c: np.ndarray
    d: np.ndarray
    ki: np.ndarray
    predict: np.ndarray | None = None

    def plane(self, states: list[int], plane: str) -> CompensatorPoint:
        """The sub-compensator of one bending plane: its states, inputs and outputs."""
        io = list(PLANE_CHANNELS[plane])
        s = np.asarray(states, dtype=int)
        return CompensatorPoint(a=self.a[np.ix_(s, s)], b=self.b[np.ix_(s, io)], e=self.e[np.ix_(s, io)],
                                c=self.c[np.ix_(io, s)], d=self.d[np.ix_(io, io)], ki=self.ki[np.ix_(io, io)],
                                predict=None if self.predict is None else self.predict[np.ix_(io, s)])


@dataclass(frozen=True)
class Compensator:
    """A scheduled compensator: the matrices of CompensatorPoint stacked over the load grid
    ([G x ...]), the integral map H [4 x 4], the start map [n x 4], the sample period, the
    states belonging to each bending plane (the planes do not couple) and the strain prediction
    P [G x 4 x n] (None: the design has none; a bridged sample holds the last measured strains)."""

    a: np.ndarray
    b: np.ndarray
    e: np.ndarray
    c: np.ndarray
    d: np.ndarray
    ki: np.ndarray
    h: np.ndarray
    start: np.ndarray
    period_s: float
    plane_states: dict
    predict: np.ndarray | None = None

    @property
    def n_states(self) -> int:
        return self.a.shape[1]

    @property
    def n_points(self) -> int:
        return self.a.shape[0]

    def point(self, i: int) -> CompensatorPoint:
        return CompensatorPoint(*(getattr(self, m)[i] for m in MATRICES),
                                predict=None if self.predict is None else self.predict[i])

    def validate_shapes(self) -> None:
        """Raise ValueError naming the matrix whose shape does not fit."""
        g, n = self.a.shape[0], self.a.shape[1]
        expected = {"a": (g, n, n), "b": (g, n, 4), "e": (g, n, 4), "c": (g, 4, n), "d": (g, 4, 4),
                    "ki": (g, 4, 4), "h": (4, 4), "start": (n, 4)}
        if self.predict is not None:
            expected["predict"] = (g, 4, n)
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"compensator matrix {name} has shape {getattr(self, name).shape}, "
                                 f"expected {shape}")
        states = sorted(self.plane_states["y"] + self.plane_states["z"])
        if states != list(range(n)):
            raise ValueError(f"plane_states must split the {n} compensator states between y and z")


def from_integral_lqr(gains: np.ndarray, c0_phi_inv: np.ndarray, period_s: float, b0: float, b1: float,
                      a1: float, scale: float) -> Compensator:
    """The paper's controller (eq. 21-30 with the high-pass velocity estimate) as a compensator.

    With q = Ti y, Ti = (C0 Phi)^-1, the velocity estimate v = scale (b0 q + s') and the filter
    state s = scale s' (s <- scale (b1 - a1 b0) q - a1 s), the law u = -(Kq q + Kv v + Ki xi)
    becomes u = -(Kv s + (Kq + scale b0 Kv) Ti y) - Ki xi; K [G x 4 x 12] in the state order
    [q, dq/dt, xi] of eq. (22). The filter state predicts no strain: ``predict`` None (a bridged
    sample feeds the filter the last measured strains).
    """
    gains = np.asarray(gains, dtype=float)
    ti = np.asarray(c0_phi_inv, dtype=float)
    g = gains.shape[0]
    kq, kv, ki = gains[:, :, 0:4], gains[:, :, 4:8], gains[:, :, 8:12]
    eye = np.eye(4)
    return Compensator(
        a=np.broadcast_to(-a1 * eye, (g, 4, 4)).copy(),
        b=np.broadcast_to(scale * (b1 - a1 * b0) * ti, (g, 4, 4)).copy(),
        e=np.zeros((g, 4, 4)),
        c=kv.copy(),
        d=(kq + scale * b0 * kv) @ ti,
        ki=ki.copy(),
        h=ti.copy(),
        start=-scale * b0 * ti,
        period_s=float(period_s),
        plane_states={"y": [0, 2], "z": [1, 3]},
    )
