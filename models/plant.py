"""The beam-column as a sampled system, stepped one sample at a time, for simulation.

Reduction: a Rayleigh-Ritz basis per bending plane made of
- the first ``modes_per_plane`` bending modes (so control and observation spillover from
  modes the controller does not model are present),
- the static deflection shapes Ke^-1 f of every force the plant applies (actuator forces at
  nodes 1 and N, eccentric-load end moments): the actuators push on the extension tips
  between two stiff springs, and the beam's strain response to them is a near-cancellation
  over many modes that a truncated modal basis gets wrong, even in sign,
- the first buckling mode, so that the plant's critical load is the FE model's.
The basis is mass-orthonormalised and diagonalised at ``basis_reference_load``.

Axial load: the plant follows a load programme Fx(t) (the rig's quasi-static ramp). The
system matrix depends on Fx; the plant steps with the discretisation (zero-order hold) at
loads on a grid of spacing 2 x ``load_tolerance``, so the load used in the dynamics never
differs from the applied one by more than ``load_tolerance``. Every ``ANCHOR_CELLS``-th cell
is discretised exactly (matrix exponential); a cell between anchors takes the parabola
through the anchor below it and the two above (Lagrange, in Fx, entry by entry). The
matrices over one sample are smooth in Fx: at the default 1 N cells (16 N between anchors)
the static response of an interpolated cell differs from the exact one by at most 1e-6 of
itself, 100 times less than using the cell's load instead of the applied one changes it
(which the grid accepts); tests/models/test_plant.py checks the ratio at 2 kHz, the least
favourable rate. Cells are made only when the load crosses into them. Discretisations are shared by
every plant of the process with the same matrices, I/O chain and sample period (a least
recently used store of ``SHARED_CELLS`` cells, safe across threads): the runs of an experiment
or a benchmark that share a rig discretise each cell once; ``clear_discretisations()`` empties it.

Imperfection: a stress-free initial bow r0 (shape of the first buckling mode, largest
lateral deviation ``bow.amplitude`` in direction ``bow.angle_deg`` from +y towards +z) acts
as the load Fx Kg r0; an eccentric load application at offset ``eccentricity.amplitude``
acts as end moments Fx e at the spring elements. The beam's coordinates describe the elastic
deflection r (what the strain gauges see); the total shape is r + r0.

The rig's I/O chain (``io``, models/iochain.py): the four actuator forces reach the beam
through the reconstruction filter after a transport delay of ``io.delay_samples`` samples
from the sampling instant, and the strains are measured behind the anti-aliasing filter; the
axial load acts undelayed and unfiltered. The state is [reconstruction filter, beam (q, q'),
anti-aliasing filter], discretised exactly with the delayed zero-order hold; the default
chain (no delay, no filter) is the beam alone.
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg as sla

from beamctl.config.schema import (
    ConfigError,
    integer,
    merge,
    nonnegative,
    number,
    plausible,
    positive,
    read_yaml,
    validate,
)
from beamctl.models import plantstep as ps
from beamctl.models.analysis import buckling_mode
from beamctl.models.fe import (
    PHI_Y,
    PHI_Z,
    PLANE_DOFS,
    FEModel,
    Plane,
    dof,
    plane_eigen,
    plane_indices,
)
from beamctl.models.iochain import DelayedZOH, IOChain, delayed_zoh, io_chain, with_filters

PLANT_DEFAULTS: dict[str, Any] = {
    "sample_rate_hz": 2000.0,
    "modes_per_plane": 6,
    "basis_reference_load": 0.0,
    "load_tolerance": 0.5,
    "load": {"start": 260.0, "end": 4000.0, "rate": 50.0, "hold": 0.0},
    "bow": {"amplitude": 0.0, "angle_deg": 0.0},
    "eccentricity": {"amplitude": 0.0, "angle_deg": 0.0},
    "noise": {"strain": 0.0, "load": 0.0, "seed": 0},
}

_SCHEMA = {
    "sample_rate_hz": positive("Hz"),
    "modes_per_plane": integer(low=2, high=40),
    "basis_reference_load": nonnegative("N"),
    "load_tolerance": positive("N"),
    "load": {
        "start": nonnegative("N"),
        "end": nonnegative("N"),
        "rate": positive("N/s"),
        "hold": nonnegative("s"),
    },
    # at most 5 mm (a 400 mm beam bowed by L/80): the shipped bow is 0.161 mm = 1.61e-4 m
    "bow": {"amplitude": plausible(0.0, 5e-3, "m"), "angle_deg": number("deg")},
    "eccentricity": {"amplitude": plausible(0.0, 5e-3, "m"), "angle_deg": number("deg")},
    # strain as a fraction (0.2 ue RMS is 2e-7), not in microstrain
    "noise": {"strain": plausible(0.0, 1e-3, "strain, RMS"), "load": plausible(0.0, 1e3, "N, RMS"),
              "seed": integer(low=0)},
}

# a simulated beam rests on end stops this fraction of its length from straight: for the paper's
# beam 20 mm, beyond the strain limit's reach (about 13 mm at the shipped 0.5 x the proportional
# limit); a rig whose strain limit lies beyond its stops rests on them without a strain fault
END_STOP_FRACTION = 0.05

# discretisations kept per process, over all plants: two rigs' whole 260..4000 N ramps at 1 N
# cells (a 48-state plant's cell is 22 kB: 88 MB at most)
SHARED_CELLS = 8000
# cells from one exact discretisation to the next; those between interpolate (see the module)
ANCHOR_CELLS = 16
_shared_cells: OrderedDict[tuple, tuple[np.ndarray, np.ndarray]] = OrderedDict()
_shared_lock = threading.Lock()


def clear_discretisations() -> None:
    """Forget every shared discretisation (the next step of any plant computes its own)."""
    with _shared_lock:
        _shared_cells.clear()


def shared_discretisations() -> int:
    """How many discretisations the process holds."""
    return len(_shared_cells)

# eigenvectors of the discretised plant better conditioned than this diagonalise its frequency response
_MAX_EIGENVECTOR_CONDITION = 1e10
N_FORCES = 4        # actuator forces (Fay,A, Faz,A, Fay,B, Faz,B); the fifth input is Fx
N_STRAINS = 4


@dataclass(frozen=True)
class LoadRamp:
    """The rig's load programme: ``start`` for ``hold`` seconds, then a ramp at ``rate`` to
    ``end``, then ``end``."""

    start: float
    end: float
    rate: float
    hold: float = 0.0

    def load_at(self, time_s: float) -> float:
        """Axial load in N at ``time_s``."""
        if time_s <= self.hold:
            return self.start
        travel = self.rate * (time_s - self.hold)
        if self.end >= self.start:
            return min(self.start + travel, self.end)
        return max(self.start - travel, self.end)

    def duration(self) -> float:
        """Time in s until the end load is reached."""
        return self.hold + abs(self.end - self.start) / self.rate


@dataclass(frozen=True)
class Offset:
    """A lateral offset: magnitude in m and direction in degrees from +y towards +z."""

    amplitude: float
    angle_deg: float

    def components(self) -> tuple[float, float]:
        a = math.radians(self.angle_deg)
        return self.amplitude * math.cos(a), self.amplitude * math.sin(a)


@dataclass(frozen=True)
class Noise:
    strain: float
    load: float
    seed: int


@dataclass(frozen=True)
class PlantConfig:
    """Validated settings of the simulated plant (see the module docstring)."""

    sample_rate_hz: float
    modes_per_plane: int
    basis_reference_load: float
    load_tolerance: float
    load: LoadRamp
    bow: Offset
    eccentricity: Offset
    noise: Noise
    io: IOChain = field(default_factory=IOChain)

    @property
    def period_s(self) -> float:
        return 1.0 / self.sample_rate_hz


def plant_config(overrides: dict[str, Any] | None = None, source: str = "",
                 prefix: str = "") -> PlantConfig:
    """Validate ``overrides`` over PLANT_DEFAULTS (key by key) into a PlantConfig; ``prefix``
    names the section in messages. ``io`` is the rig's I/O chain (models/iochain.py)."""
    overrides = overrides or {}
    io = None
    if isinstance(overrides, dict):
        if "sample_rate" in overrides:
            raise ConfigError(f"{prefix}sample_rate", overrides["sample_rate"],
                              f"{prefix}sample_rate_hz in its place (the key was renamed; the same "
                              f"value, in Hz)", source)
        overrides = dict(overrides)
        io = overrides.pop("io", None)
    v = validate(merge(PLANT_DEFAULTS, overrides), _SCHEMA, source, prefix)
    return PlantConfig(
        sample_rate_hz=v["sample_rate_hz"], modes_per_plane=v["modes_per_plane"],
        basis_reference_load=v["basis_reference_load"], load_tolerance=v["load_tolerance"],
        load=LoadRamp(**v["load"]), bow=Offset(**v["bow"]),
        eccentricity=Offset(**v["eccentricity"]), noise=Noise(**v["noise"]),
        io=io_chain(io, source, f"{prefix}io"))


def load_plant_config(path: str | Path) -> PlantConfig:
    """PlantConfig from a YAML file holding the plant keys at its top level."""
    return plant_config(read_yaml(path), source=str(path))


def eccentricity_moments(model: FEModel, e_y: float, e_z: float) -> np.ndarray:
    """Nodal moments per newton of axial load applied at offset (e_y, e_z) at both spring
    elements: r x F with F = +Fx ex at support A and -Fx ex at support B."""
    f = np.zeros(model.n_dof)
    a, b = 1, model.n_nodes - 2
    f[dof(a, PHI_Y)], f[dof(a, PHI_Z)] = e_z, -e_y
    f[dof(b, PHI_Y)], f[dof(b, PHI_Z)] = -e_z, e_y
    return f


def ritz_basis(model: FEModel, plane: Plane, modes: int, reference_load: float,
               extra: np.ndarray) -> np.ndarray:
    """Mass-orthonormal Ritz basis of one plane, diagonal in Ke - F_ref Kg; columns sorted by
    frequency. ``extra`` holds load vectors whose static shapes join the modes."""
    idx = plane_indices(model.n_nodes, plane)
    k_ref = model.load_stiffness(reference_load)
    _, vec = plane_eigen(k_ref, model.mass, plane, modes)
    _, buckled = buckling_mode(model, plane)
    loads = extra[idx][:, np.abs(extra[idx]).max(axis=0) > 0]
    statics = np.zeros((model.n_dof, loads.shape[1]))
    statics[idx] = sla.solve(model.elastic_stiffness[np.ix_(idx, idx)], loads, assume_a="pos")
    z = np.column_stack([vec, buckled, statics])[idx]
    m = model.mass[np.ix_(idx, idx)]
    z = z / np.sqrt(np.einsum("ij,ik,kj->j", z, m, z))  # unit mass norm: comparable columns
    # drop directions already spanned: eigen-decompose the Gram matrix in the mass metric
    gram_val, gram_vec = np.linalg.eigh(z.T @ m @ z)
    keep = gram_val > 1e-10 * gram_val.max()
    z = z @ (gram_vec[:, keep] / np.sqrt(gram_val[keep]))
    lam, y = np.linalg.eigh(z.T @ k_ref[np.ix_(idx, idx)] @ z)
    basis = np.zeros((model.n_dof, y.shape[1]))
    basis[idx] = z @ y[:, np.argsort(lam)]
    return basis


class Plant:
    """The beam-column sampled at ``config.sample_rate_hz``.

    Each sample: ``measure()`` gives the strains (behind the anti-aliasing filter) and the
    load-cell reading of the current state; ``step(forces_n)`` applies the four actuator forces
    (Fay,A, Faz,A, Fay,B, Faz,B) commanded at this sampling instant, held for one sample and
    reaching the beam through the I/O chain's delay and reconstruction filter, and advances
    one sample along the load programme.
    """

    def __init__(self, model: FEModel, config: PlantConfig) -> None:
        self.model = model
        self.config = config
        self.period_s = config.period_s
        e_y, e_z = config.eccentricity.components()
        ecc = eccentricity_moments(model, e_y, e_z)
        bow_y, bow_z = config.bow.components()
        self.critical_load, mode_y = buckling_mode(model, "y")
        _, mode_z = buckling_mode(model, "z")
        self.bow = bow_y * mode_y + bow_z * mode_z  # r0, stress free

        # static shapes of unit actuator forces and unit-offset end moments, per plane
        extra = np.column_stack([model.input_matrix,
                                 eccentricity_moments(model, 1.0, 0.0),
                                 eccentricity_moments(model, 0.0, 1.0)])
        basis = np.column_stack([
            ritz_basis(model, plane, config.modes_per_plane, config.basis_reference_load, extra)
            for plane in ("y", "z")])
        self.basis = basis
        n = basis.shape[1]
        self.n_coordinates = n
        self._k_elastic = basis.T @ model.elastic_stiffness @ basis
        self._k_geometric = basis.T @ model.geometric_stiffness @ basis
        self._damping = basis.T @ model.damping @ basis
        # generalised forces: 4 actuator forces, and per newton of axial load the bow and
        # eccentricity loads
        load_shape = model.geometric_stiffness @ self.bow + ecc
        self._input = basis.T @ np.column_stack([model.input_matrix, load_shape])
        self._strain = model.output_matrix @ basis
        nodes = model.beam_nodes
        self._lateral = np.stack([basis[[dof(k, PLANE_DOFS[p][0]) for k in nodes]]
                                  for p in ("y", "z")])  # [2 x n_beam x n]

        # the I/O chain: state [reconstruction filter, beam (q, q'), anti-aliasing filter]
        io = config.io
        a, b, c, d = self._with_filters(0.0)    # C, D and the filters' rows do not depend on Fx
        for m in (b, c, d):
            m.setflags(write=False)
        self._augmented0 = (a, b, c, d)
        n_states = a.shape[0]
        n_aa = 0 if io.anti_alias is None else N_STRAINS * io.anti_alias.state_space()[0].shape[0]
        n_rec = n_states - 2 * n - n_aa
        self.n_states = n_states
        self._q = slice(n_rec, n_rec + n)       # the beam's coordinates within the state
        used = np.flatnonzero(np.any(c != 0.0, axis=0))
        self._measured = slice(int(used[0]), int(used[-1]) + 1)
        self._c = np.ascontiguousarray(c[:, self._measured])
        # the step's inputs: u_k-whole, and u_k-whole-1 when the delay has a fraction of a
        # sample; then Fx. The last ``whole + 1`` forces are kept in a ring, the oldest at
        # ``_head``.
        whole = int(math.floor(io.delay_samples))
        self._fractional = io.delay_samples != whole
        n_inputs = N_FORCES * (2 if self._fractional else 1) + 1
        self._inputs = np.zeros(n_inputs)
        self._history = np.zeros((whole + 1, N_FORCES))
        self._delayed = whole > 0 or self._fractional
        # feedthrough y = C x + D u: u is the input held just before the sampling instant,
        # i.e. the previous step's (u_k-1-whole, Fx_k-1); zero for this beam, kept general
        feedthrough = np.zeros((N_STRAINS, n_inputs))
        feedthrough[:, :N_FORCES], feedthrough[:, -1] = d[:, :N_FORCES], d[:, N_FORCES]
        self._feedthrough = feedthrough if np.any(feedthrough) else None
        # the anti-aliasing filter at rest: x_aa = settle [recon, beam] + settle_load Fx
        aa = slice(n_states - n_aa, n_states)
        self._aa = aa
        self._settle = -np.linalg.solve(a[aa, aa], a[aa, :aa.start]) if n_aa else None
        self._settle_load = -np.linalg.solve(a[aa, aa], b[aa, N_FORCES]) if n_aa else None

        # the end stops: the lateral deflection at the beam's quarter points, checked each step
        quarter = [nodes[round(f * (len(nodes) - 1))] for f in (0.25, 0.5, 0.75)]
        self._stop_rows = np.vstack([basis[[dof(k, PLANE_DOFS[p][0]) for k in quarter]] for p in ("y", "z")])
        self._stop_out = np.zeros(self._stop_rows.shape[0])
        self.end_stop_m = END_STOP_FRACTION * model.params.beam.length
        self.on_stops_since: float | None = None     # the time the beam first came to rest on its stops

        # the compiled step's arrays (models/plantstep.py)
        self._state = np.zeros(n_states)
        self._work = np.zeros(2 * n_states)
        self._ik = np.zeros(ps.N_IK, dtype=np.int64)
        self._ik[ps.K_FRACTIONAL] = 1 if self._fractional else 0
        self._ik[ps.K_DELAYED] = 1 if self._delayed else 0
        self._ik[ps.K_Q], self._ik[ps.K_NQ] = self._q.start, n
        self._pf = np.zeros(ps.N_PF)
        self._pf[ps.P_STOP_CHECK] = self.end_stop_m / math.sqrt(2.0)
        self._pf[ps.P_END_STOP] = self.end_stop_m
        self._fingerprint = self._digest()
        self._bin = None
        self._ad = self._bd = None
        self._strain_out = np.zeros(N_STRAINS)
        self._rng = np.random.default_rng(config.noise.seed)
        self._noise_block = np.zeros((0, 5))
        self._noise_index = 0
        self.discretisations = 0
        self.reset()

    # -- load-dependent discretisation -------------------------------------------------
    def continuous(self, axial_load: float) -> tuple[np.ndarray, np.ndarray]:
        """The beam alone in continuous time: A(Fx) [2n x 2n] and B [2n x 5] (inputs: 4
        forces, Fx)."""
        n = self.n_coordinates
        a = np.zeros((2 * n, 2 * n))
        a[:n, n:] = np.eye(n)
        a[n:, :n] = -(self._k_elastic - axial_load * self._k_geometric)
        a[n:, n:] = -self._damping
        b = np.vstack([np.zeros((n, 5)), self._input])
        return a, b

    def _with_filters(self, axial_load: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        a, b = self.continuous(axial_load)
        c = np.hstack([self._strain, np.zeros_like(self._strain)])
        return with_filters(a, b, c, self.config.io, N_FORCES)

    def augmented(self, axial_load: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The beam with the I/O chain's filters in continuous time (A, B, C, D): inputs the 4
        forces (through the reconstruction filter) and Fx, outputs the 4 measured strains.
        Only the beam's stiffness block depends on Fx: the rest is assembled once (the filters
        place the beam's matrix unchanged, so this is the same matrix entry for entry)."""
        a0, b, c, d = self._augmented0
        a = a0.copy()
        n, first = self.n_coordinates, self._q.start
        a[first + n:first + 2 * n, first:first + n] = -(self._k_elastic - axial_load * self._k_geometric)
        return a, b, c, d

    def discretise(self, axial_load: float) -> DelayedZOH:
        """Exact discretisation at ``axial_load``: zero-order hold, the chain's delay on the
        forces, Fx undelayed."""
        a, b, _, _ = self.augmented(axial_load)
        self.discretisations += 1
        return delayed_zoh(a, b[:, :N_FORCES], self.period_s, self.config.io.delay_samples,
                           b_direct=b[:, N_FORCES:])

    def _digest(self) -> str:
        """What a discretisation depends on: the reduced matrices, the I/O chain, the period
        and the load grid (two plants with the same digest step the same system)."""
        h = hashlib.sha256()
        for m in (self._k_elastic, self._k_geometric, self._damping, self._input, self._strain):
            h.update(np.ascontiguousarray(m).tobytes())
        h.update(repr((self.config.io.to_dict(), self.period_s, self.config.load_tolerance)).encode())
        return h.hexdigest()

    def _cell_matrices(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(ad, [b_now, (b_before,) b_direct]) of the cell ``index``: exact at every
        ``ANCHOR_CELLS``-th cell, between them the parabola through the anchors below and the
        two above (see the module)."""
        cell = 2.0 * self.config.load_tolerance
        below, offset = divmod(index, ANCHOR_CELLS)
        if offset == 0:
            return self._anchor(below, cell)
        w = offset / ANCHOR_CELLS
        weights = (0.5 * (w - 1.0) * (w - 2.0), w * (2.0 - w), 0.5 * w * (w - 1.0))
        anchors = [self._anchor(below + j, cell) for j in range(3)]
        pairs = list(zip(weights, anchors, strict=True))
        return tuple(np.ascontiguousarray(sum(c * anchor[i] for c, anchor in pairs)) for i in range(2))

    def _anchor(self, anchor: int, cell: float) -> tuple[np.ndarray, np.ndarray]:
        key = (self._fingerprint, anchor, "anchor")
        with _shared_lock:
            entry = _shared_cells.get(key)
            if entry is not None:
                _shared_cells.move_to_end(key)
        if entry is None:
            zoh = self.discretise(anchor * ANCHOR_CELLS * cell)
            before = (zoh.b_before,) if self._fractional else ()
            entry = (np.ascontiguousarray(zoh.ad), np.hstack([zoh.b_now, *before, zoh.b_direct]))
            with _shared_lock:
                _shared_cells[key] = entry
        return entry

    def _cell(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """The shared discretisation of cell ``index``, made now if no plant has made it."""
        key = (self._fingerprint, index)
        with _shared_lock:
            entry = _shared_cells.get(key)
            if entry is not None:
                _shared_cells.move_to_end(key)
        if entry is None:
            entry = self._cell_matrices(index)
            with _shared_lock:
                _shared_cells[key] = entry
                while len(_shared_cells) > SHARED_CELLS:
                    _shared_cells.popitem(last=False)
        return entry

    def _use_load(self, axial_load: float) -> None:
        cell = 2.0 * self.config.load_tolerance
        index = round(axial_load / cell)
        if index == self._bin:
            return
        self._bin = index
        self._ad, self._bd = self._cell(index)

    def prepare(self) -> int:
        """Make now every discretisation the load programme will step through (from its start
        load to its end load), so that a run in wall-clock time never stops to make one (an
        exact cell takes milliseconds: a DAQ that stops that long is a stall the controller has
        to ride through). Returns the number of cells."""
        cell = 2.0 * self.config.load_tolerance
        load = self.config.load
        low, high = sorted((round(load.start / cell), round(load.end / cell)))
        if high - low + 1 > SHARED_CELLS:
            raise ValueError(f"a load programme from {load.start:g} to {load.end:g} N passes "
                             f"{high - low + 1} cells of {cell:g} N; at most {SHARED_CELLS} are kept")
        for index in range(low, high + 1):
            self._cell(index)
        return high - low + 1

    # -- simulation ------------------------------------------------------------------------
    def reset(self, time_s: float = 0.0) -> None:
        """Place the beam at rest in static equilibrium under the programme's load at
        ``time_s`` with no actuator force (none in the delay either), the filters at rest."""
        self.time = time_s
        self.on_stops_since = None
        self.axial_load = self.config.load.load_at(time_s)
        k = self._k_elastic - self.axial_load * self._k_geometric
        self._state[:] = 0.0
        self._state[self._q] = np.linalg.solve(k, self._input[:, 4] * self.axial_load)
        np.dot(self._stop_rows, self._state[self._q], out=self._stop_out)
        self._rest_on_stops()            # a static shape past the stops (loaded near Fx,cr) rests on them
        if self._settle is not None:
            aa = self._aa
            self._state[aa] = self._settle @ self._state[:aa.start] + self._settle_load * self.axial_load
        self._history[:] = 0.0
        self._ik[ps.K_HEAD] = 0
        self._ik[ps.K_RESTED] = 0
        self._inputs[:] = 0.0
        self._inputs[-1] = self.axial_load
        self._use_load(self.axial_load)

    def step(self, forces_n: np.ndarray) -> None:
        """Apply the actuator forces (N) commanded now for one sample period and advance (the
        arithmetic: models/plantstep.py ``step``, the one the offline loop runs too)."""
        self._pf[ps.P_LOAD] = self.axial_load
        ps.step(self._state, self._work, self._ad, self._bd, self._inputs, self._history, self._stop_rows,
                self._stop_out, forces_n, self._ik, self._pf)
        if self._ik[ps.K_RESTED] and self.on_stops_since is None:
            self.on_stops_since = self.time
        self.time += self.period_s
        self.axial_load = self.config.load.load_at(self.time)
        self._use_load(self.axial_load)

    def _rest_on_stops(self) -> None:
        """A static shape past the stops (placed by ``reset``): at rest against them, as ``step``
        brings a beam that reaches them (models/plantstep.py)."""
        n = len(self._stop_out) // 2
        reach = float(np.hypot(self._stop_out[:n], self._stop_out[n:]).max())
        if not reach > self.end_stop_m:
            return
        self._state[self._q] *= self.end_stop_m / reach
        self.on_stops_since = self.time

    def follow_load(self, programme: LoadRamp) -> None:
        """From now on follow another load programme (on the plant's own clock): an operator
        moving the load by hand."""
        self.config = replace(self.config, load=programme)

    def _refill_noise(self) -> None:
        """The next block of measurement noise (strains, load cell) from the seeded stream."""
        self._noise_block = self._rng.standard_normal((4096, 5))
        self._noise_block[:, :4] *= self.config.noise.strain
        self._noise_block[:, 4] *= self.config.noise.load
        self._noise_index = 0

    def measure(self) -> tuple[np.ndarray, float]:
        """(strains [eps_y1, eps_z1, eps_y2, eps_z2] behind the anti-aliasing filter, load-cell
        reading in N) of the current state, noise included. The strain array is reused by the
        next call."""
        if self._noise_index >= len(self._noise_block):
            self._refill_noise()
        row = self._noise_index
        self._noise_index += 1
        ps.measure(self._state, self._c, self._measured.start, self._noise_block, row, self._strain_out)
        if self._feedthrough is not None:
            self._strain_out += self._feedthrough @ self._inputs
        return self._strain_out, self.axial_load + float(self._noise_block[row, 4])

    # -- observation for experiments and tests ------------------------------------------------
    def elastic_deflection(self) -> np.ndarray:
        """Elastic lateral deflection (v, w) at the beam nodes in m, [n_beam x 2]."""
        return (self._lateral @ self._state[self._q]).T

    def deflection(self) -> tuple[float, float]:
        """Largest elastic lateral deflection magnitude along the beam (m) and its direction
        (degrees from +y towards +z, in [0, 360))."""
        vw = self.elastic_deflection()
        mag = np.hypot(vw[:, 0], vw[:, 1])
        k = int(np.argmax(mag))
        return float(mag[k]), math.degrees(math.atan2(vw[k, 1], vw[k, 0])) % 360.0

    def displacement(self) -> np.ndarray:
        """Elastic FE displacement vector r (4N) of the current state."""
        return self.basis @ self._state[self._q]

    # -- frequency response of the sampled plant -------------------------------------------------
    def frequency_response(self, axial_load: float, freqs_hz) -> np.ndarray:
        """The sampled plant's response from the four commanded forces to the four measured
        strains at ``axial_load``, [nf x 4 x 4] complex (strain per N), at each frequency below
        the Nyquist frequency: G(z) = C (zI - Ad)^-1 (B_now + B_before z^-1) z^-whole with
        z = exp(j 2 pi f T), i.e. exactly the discretisation ``step`` runs (zero-order hold, the
        I/O chain's delay and filters). A sample's strains answer the forces commanded at the
        samples before it, as a recorded run pairs them."""
        freqs = np.asarray(freqs_hz, dtype=float)
        zoh = self.discretise(axial_load)
        _, _, c, d = self.augmented(axial_load)
        z = np.exp(2j * np.pi * freqs * self.period_s)
        shift = z[:, None, None] ** (-zoh.whole)
        # the feedthrough acts with the input held before the sampling instant (``measure``)
        direct = d[None, :, :N_FORCES] * (shift / z[:, None, None]) if np.any(d[:, :N_FORCES]) else 0.0
        lam, vec = np.linalg.eig(zoh.ad)
        if np.linalg.cond(vec) < _MAX_EIGENVECTOR_CONDITION:
            # diagonalised once: each frequency costs a scaling of C V and V^-1 B
            left = c @ vec
            now, before = np.linalg.solve(vec, zoh.b_now), np.linalg.solve(vec, zoh.b_before)
            resolvent = 1.0 / (z[:, None] - lam[None, :])
            g = (np.einsum("in,fn,nj->fij", left, resolvent, now)
                 + np.einsum("in,fn,nj->fij", left, resolvent, before) / z[:, None, None])
            return g * shift + direct
        eye = np.eye(zoh.ad.shape[0])          # near-defective: one solve per frequency
        b = zoh.b_now[None] + zoh.b_before[None] / z[:, None, None]
        return (c @ np.linalg.solve(z[:, None, None] * eye[None] - zoh.ad[None], b)) * shift + direct
