"""The shipped LQG design: it is what `beamctl gains build` makes, and it is built for the I/O
chain it declares."""

import numpy as np
import pytest

from beamctl.gains.build import build_lqg_table
from beamctl.gains.compensator import MATRICES
from beamctl.gains.defaults import LQG_CHAIN, LQG_SETTINGS, default_table_path
from beamctl.gains.lqg import design
from beamctl.gains.table import load_table
from beamctl.models import build_model, load_parameters
from beamctl.models.iochain import AnalogFilter, IOChain
from beamctl.models.modal import reduce


def test_the_shipped_default_is_the_lqg_that_gains_build_makes():
    """Rebuilt from the paper's parameters, every compensator matrix equals the shipped one to
    1e-6 of its largest entry (BLAS kernels differ from machine to machine by far less; a changed
    design or setting differs by far more)."""
    shipped = load_table(default_table_path())
    assert shipped.design.kind == "lqg" and shipped.design.io == LQG_CHAIN
    rebuilt = build_lqg_table(build_model(load_parameters()), check=False)
    for name in MATRICES:
        ours, theirs = getattr(rebuilt.compensator, name), getattr(shipped.compensator, name)
        scale = max(np.max(np.abs(theirs)), 1e-300)
        assert np.max(np.abs(ours - theirs)) <= 1e-6 * scale, f"compensator matrix {name} differs"
    assert shipped.all_stable and not shipped.forced


def test_the_design_does_not_pretend_to_model_a_reconstruction_filter():
    model = build_model(load_parameters())
    chain = IOChain(delay_samples=0.5, reconstruction=AnalogFilter("butterworth", 2, 2000.0))
    with pytest.raises(ValueError, match="reconstruction filter"):
        design(model, [0.0, 100.0], 6000.0, chain, reduce(model).c0_phi_inv, LQG_SETTINGS)
