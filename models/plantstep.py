"""The simulated plant's per-sample arithmetic, compiled once (numba): what models/plant.py's
``Plant.measure`` and ``Plant.step`` do, and what the offline loop (simulation/simkernel.py) runs
inside its compiled cycles. One implementation: a change to the plant (an end stop, a
disturbance) made here is made for every run.

The arrays are the plant's own (models/plant.py allocates them; nothing here allocates):

- ``state`` the sampled plant's state [reconstruction filter, beam (q, q'), anti-aliasing
  filter]; ``work`` scratch of twice its length;
- ``ad``, ``bd`` the discretisation of the load cell in use (inputs [u_now, (u_before,) Fx]);
- ``inputs`` the step's input vector; ``history`` the ring of the last ``whole + 1`` forces;
- ``stop_rows`` the lateral deflection at the quarter points (y rows, then z) from q;
  ``stop_out`` where it is computed;
- ``ik`` (int64): ``K_HEAD`` the ring's oldest entry, ``K_FRACTIONAL`` the delay has a fraction
  of a sample, ``K_DELAYED`` any delay, ``K_Q`` and ``K_NQ`` where q starts in the state and its
  length, ``K_RESTED`` set to 1 by a step that brought the beam to rest on its end stops;
- ``pf`` (float64): ``P_LOAD`` the axial load of this step, ``P_STOP_CHECK`` the stops' reach over
  sqrt(2) (a component past it: the radius is checked), ``P_END_STOP`` the stops' reach.
"""

from __future__ import annotations

import math

import numba
import numpy as np

K_HEAD, K_FRACTIONAL, K_DELAYED, K_Q, K_NQ, K_RESTED = range(6)
N_IK = 6
P_LOAD, P_STOP_CHECK, P_END_STOP = range(3)
N_PF = 3


@numba.njit(cache=True, nogil=True)
def measure(state, c, first, noise, row, out):
    """out <- C x (the strains behind the anti-aliasing filter, C over the state from ``first``)
    plus the noise ``noise[row, :4]``."""
    for j in range(out.shape[0]):
        acc = 0.0
        for m in range(c.shape[1]):
            acc += c[j, m] * state[first + m]
        out[j] = acc + noise[row, j]


@numba.njit(cache=True, nogil=True)
def step(state, work, ad, bd, inputs, history, stop_rows, stop_out, forces, ik, pf):
    """One sample: the forces commanded now enter the I/O chain's delay (the ring), the state
    advances x <- Ad x + Bd [u_k-whole, (u_k-whole-1,) Fx], and a beam that has reached its end
    stops comes to rest against them (its shape scaled back to the stops, its velocity gone: a
    rig's catch holding a lost beam; ik[K_RESTED] = 1)."""
    n = state.shape[0]
    n_inputs = inputs.shape[0]
    if ik[K_DELAYED] == 1:
        head = ik[K_HEAD]
        length = history.shape[0]
        if length > 1:
            newest = (head + 1) % length
            for j in range(4):
                inputs[j] = history[newest, j]
        else:
            for j in range(4):
                inputs[j] = forces[j]
        if ik[K_FRACTIONAL] == 1:
            for j in range(4):
                inputs[4 + j] = history[head, j]
        for j in range(4):
            history[head, j] = forces[j]
        ik[K_HEAD] = (head + 1) % length
    else:
        for j in range(4):
            inputs[j] = forces[j]
    inputs[n_inputs - 1] = pf[P_LOAD]
    nxt = work[:n]
    forced = work[n:2 * n]
    np.dot(ad, state, nxt)
    np.dot(bd, inputs, forced)
    for j in range(n):
        state[j] = nxt[j] + forced[j]
    # the end stops
    q0, nq = ik[K_Q], ik[K_NQ]
    rows = stop_out.shape[0]
    top = 0.0
    for r in range(rows):
        acc = 0.0
        for m in range(nq):
            acc += stop_rows[r, m] * state[q0 + m]
        stop_out[r] = acc
        if abs(acc) > top:
            top = abs(acc)
    if top > pf[P_STOP_CHECK]:
        half = rows // 2
        reach = 0.0
        for r in range(half):
            radius = math.hypot(stop_out[r], stop_out[half + r])
            if radius > reach:
                reach = radius
        if reach > pf[P_END_STOP]:
            scale = pf[P_END_STOP] / reach
            for m in range(nq):
                state[q0 + m] *= scale
                state[q0 + nq + m] = 0.0
            ik[K_RESTED] = 1
