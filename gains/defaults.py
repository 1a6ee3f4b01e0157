"""Default design of the shipped gain table, and why.

Sample rate 2500 Hz, velocity filter cut-off 145.5 Hz
    The controller is not collocated: the stacks push on the extension tips, the gauges sit
    on the beam. The higher symmetric modes (3: ~950 Hz, 5: ~2.6 kHz) enter the strain-based
    estimate of q1 with the opposite sign to mode 1 and 8 to 90 times as strongly, and
    likewise mode 4 for q2. Beyond the critical load the gain that holds mode 1 must exceed
    |Ke~ - Fx Kg~| / b (3.9e6 N per modal unit at 4000 N), so those modes see loop gains of
    tens at their resonances and are stable only through the phase the sampling gives them.
    Searching sample rates the classic CAN bus carries (2.0 to 2.9 kHz, hal/) and cut-offs,
    2500 Hz with 145.5 Hz is where the discrete loop with the full FE model is stable at
    every load from 0 to 4000 N. Its margins: up to 3600 N the least stable
    poles are the open-loop modes themselves (mode 2 at |z| = 0.995) and the loop stays
    stable with the beam's stiffness 1 % off; at 4000 N the loop is stable only for the
    nominal model and this cut-off (+-0.3 %) and rate (+-0.5 %). A one-sample output delay
    makes it unstable from about 3200 N: the voltages must be out within the sample.

Q (diagonal, eq. 26) and R = I (forces in N)
    A modal unit of the mass-normalised modes is a largest deflection of about 6.6 m
    (mode 1) or 6.2 m (mode 2); a weight w on a state means that a deviation of 1/sqrt(w)
    costs as much as 1 N of force. As in the paper the largest weights are on mode 1 and on
    the integrals:
    - displacement q1: 2e10 -> 7.1e-6 modal units = 47 um of deflection per newton;
      q2: 3e5 -> 1.8e-3 = 11 mm per newton (mode 2 is left to its integral);
    - velocity dq1/dt: 5e3 -> 0.014 modal units/s (93 mm/s) per newton; dq2/dt: 0.5;
    - integrals of q1 and q2: 5e14 -> 4.5e-8 modal unit s: a 30 um deflection held for
      10 ms costs 1 N, so a static deflection (imperfection, eccentric load) is driven out.
    The displacement and velocity weights hardly matter for stability (+-25 % changes move
    the largest spectral radius by less than 1e-4); the integral weights do: doubling the
    mode-1 integral weight makes 4000 N unstable.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

from beamctl.gains.lqg import LqgSettings
from beamctl.gains.lqr import Weights
from beamctl.gains.table import DesignSettings, ScheduleSettings
from beamctl.models.iochain import AnalogFilter, IOChain

DEFAULT_WEIGHTS = Weights.from_modes(displacement=(2e10, 3e5), velocity=(5e3, 0.5),
                                     integral=(5e14, 5e14))
# the paper's design; it assumes the voltages reach the stacks within the sample, unfiltered
DEFAULT_DESIGN = DesignSettings(kind="integral-lqr", sample_rate_hz=2500.0, io=IOChain(),
                                velocity_cutoff_hz=145.5, weights=DEFAULT_WEIGHTS)
# load filter: 5 Hz first order (32 ms lag, 1.6 N behind a 50 N/s ramp, load-cell noise
# divided by ~9); hysteresis of the paper mode: 50 N, far above the filtered noise
DEFAULT_SCHEDULE = ScheduleSettings(mode="interpolate", load_filter_hz=5.0, hysteresis_n=50.0)
PAPER_GRID_N = np.arange(0.0, 3500.0 + 1e-9, 500.0)  # the experiment's 0..3500 N in 500 N steps
DEFAULT_TABLE = "default.yaml"
PAPER_TABLE = "paper.yaml"

# How the shipped LQG was found (worst held load / own Fx,cr over box B, `beamctl gains check
# --robust`; the paper's design: 0.875):
# - 2500 Hz, designed for a delay of 1 or 0.5 sample, 5-9 modes, other weights, noise levels or
#   a softened design model: 0.94-0.96 at best. Mode 5 (2.5-2.7 kHz) folds into 0-170 Hz and
#   destabilises stiff rigs as soon as the loop gain rises; soft rigs lose the slow closed-loop
#   mode 1 just below their own Fx,cr.
# - 6000 Hz without a filter: 0.95-0.98 (mode 7, 5.1 kHz, folds to 0.8-1 kHz on stiff rigs);
#   with a 2nd-order Butterworth anti-alias filter at 1 kHz: 0.982 (soft rigs limit).
# - Designing the LQR, or the whole model, softer: stiff rigs fail at mode 5 (0.93-0.97).
#   Softening the estimator's mode 1 alone (its load + 300 N): 1.000; 370 N loses a stiff rig
#   (0.994), a 1.3 kHz filter with 300-320 N a stiff one (0.995).
# The shipped default: the delay-aware LQG (gains.lqg) with the best worst case over the
# uncertainty box of the robust check (README, "Robustness"). 6000 Hz needs CAN FD (classic
# CAN carries at most 2819 Hz of these frames); the design assumes the voltages reach the stacks
# half a sample after the sampling instant (the middle of the box's 0..1 sample) and a
# second-order Butterworth anti-aliasing filter at 1.25 kHz on the four strain channels, which
# the rig must have: it keeps mode 7 (5.1 kHz) from folding into the control band. Seven modes
# per plane; the paper's weights but for q1 (x10: more stiffness for a rig softer than the
# model) and the integrals (/10). The estimator's model of mode 1 alone is softened by 300 N of
# axial load: a rig softer than the model loses its slow closed-loop mode 1 when the estimator
# believes mode 1 stiffer than it is; softening the higher modes, or the LQR's model, instead
# destabilises mode 5 on stiff rigs (a narrow optimum: 370 N loses a stiff rig, and a 1.3 kHz
# filter with 300 N a stiff one at 0.995).
LQG_SAMPLE_RATE_HZ = 6000.0
LQG_CHAIN = IOChain(delay_samples=0.5, anti_alias=AnalogFilter("butterworth", 2, 1250.0))
LQG_SETTINGS = LqgSettings(n_modes=7, q_displacement=(2e11, 3e5), q_velocity=(5e3, 0.5),
                           q_integral=(5e13, 5e13), estimator_mode1_load_offset_n=300.0)
LQG_GRID_N = np.arange(0.0, 4000.0 + 1e-9, 100.0)
DESIGNS = ("lqg", "integral-lqr")


def default_table_path() -> Path:
    """The gain table shipped in gains/: the LQG design (generated from the paper's parameters)."""
    return Path(str(resources.files("beamctl.gains") / DEFAULT_TABLE))


def paper_table_path() -> Path:
    """The paper's design (integral LQR, 2500 Hz, interpolated), shipped beside the default."""
    return Path(str(resources.files("beamctl.gains") / PAPER_TABLE))
