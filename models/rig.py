"""A rig that differs from the model a design was made for: the one description that the robust
check (gains/robust.py), the uncertainty study (simulation/study.py) and the simulated
experiment on such a rig (simulation/experiment.py, ``rig_scenario``) all take.

A rig is the design's model parameters, I/O chain, sample rate and stacks with changes applied.
A change names a key and how it changes the design's value:

- a model key as in a parameter file (``beam.youngs_modulus``, a list element
  ``sensors.strain_gauge_positions[0]`` or a whole list ``damping.ratios``, element by element);
- ``io.delay_samples``: the rig's I/O delay in samples;
- ``actuators.force_constant_n_per_v``: the rig's stacks, as a factor on the force per volt the
  controller believes (``force_gain``);
- ``sample_rate_hz``: the rig's DAQ rate, as a factor on the design's.

and its kind: ``factor`` multiplies the design's value, ``offset`` adds to it (SI units),
``value`` replaces it. ``set_parameter`` is the one place a change is applied.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from beamctl.config.schema import dotted_update
from beamctl.models.iochain import IOChain
from beamctl.models.params import ModelParameters, parameters_from_dict

KINDS = ("factor", "offset", "value")
# the keys of a change that are not model parameters
SPECIAL_KEYS = ("io.delay_samples", "actuators.force_constant_n_per_v", "sample_rate_hz")


@dataclass(frozen=True)
class Rig:
    """One rig: its model parameters, I/O chain, sample rate and stacks' force per volt relative
    to what the controller believes (``force_gain``)."""

    params: ModelParameters
    chain: IOChain
    sample_rate_hz: float
    force_gain: float = 1.0


def changed(old: float, kind: str, value: float) -> float:
    """``old`` changed by ``value`` of ``kind`` (one of KINDS)."""
    if kind == "factor":
        return old * value
    if kind == "offset":
        return old + value
    if kind == "value":
        return value
    raise ValueError(f"change kind {kind!r}: expected one of {', '.join(KINDS)}")


def set_parameter(model: dict[str, Any], key: str, kind: str, value: float) -> None:
    """Apply one change to a model parameter dict (``ModelParameters.to_dict()``) in place; a
    whole list changes element by element."""
    dotted_update(model, key, lambda old: changed(old, kind, value))


def rig_with(params: ModelParameters, chain: IOChain, sample_rate_hz: float,
             changes: Mapping[str, tuple[str, float]], source: str = "rig") -> Rig:
    """The rig of the design (``params``, ``chain``, ``sample_rate_hz``) with ``changes`` ({key:
    (kind, value)}, see the module docstring) applied. Parameters that make no valid model are
    refused (ConfigError) naming ``source``."""
    model = params.to_dict()
    delay = chain.delay_samples
    gain = 1.0
    rate = sample_rate_hz
    for key, (kind, value) in changes.items():
        if key == "io.delay_samples":
            delay = changed(delay, kind, value)
        elif key == "actuators.force_constant_n_per_v":
            gain = changed(gain, kind, value)
        elif key == "sample_rate_hz":
            rate = changed(rate, kind, value)
        else:
            set_parameter(model, key, kind, value)
    return Rig(params=parameters_from_dict(model, source=source),
               chain=IOChain(delay_samples=max(delay, 0.0), anti_alias=chain.anti_alias,
                             reconstruction=chain.reconstruction),
               sample_rate_hz=rate, force_gain=gain)
