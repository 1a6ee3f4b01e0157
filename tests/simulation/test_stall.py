"""Stalls in the time domain, at the shipped settings (simulation/stall.py): the shipped
controller in lockstep with the simulated rig (a 20 um bow, 0.2 ue gauge noise), nominal and the
robust check's worst rig, a stall injected after the load was reached and held. Deterministic: the
rig's noise from a fixed seed, no clock but the samples.

At each load from 2000 N to near the table's top, on both rigs: a stall as long as the live limit
at that moment is survived (no fault, no stack at the end of its range, the strain inside the
supervisor's limit, through the stall and 0.2 s of recovery). Where the rig whose growth sets
the limit is the one it runs on, the limit is within a factor of two of the survival edge: a
stall of twice the limit is lost with the limit lifted. That is asserted where it was measured
to hold (3300 and 3400 N on both rigs, the top nominal); at 3200 N (the nominal rig just past
its Fx,cr, whose edge is set by the stacks' recovery, 2.7 x the limit), at 3500 to 3600 N
(nominal: 2.0 and 2.7, the worst rig near its onset sets the limit) and on the worst rig at 3200
to 3250 N (below its own Fx,cr, no stall lost up to the cap) one limit serving both rigs sits
further below the edge: the measured table, and the full edge per load (a search), are in
docs/pages/controller.md (``beamctl gains stalls``)."""

import pytest

from beamctl.gains.defaults import default_table_path
from beamctl.gains.table import load_table
from beamctl.simulation.stall import StallRig, worst_rig

TABLE = load_table(default_table_path())
TOP_N = float(TABLE.loads_n[-1]) - 100.0    # the load's noise (2 N) and filter stay in the table
LOADS = (2000.0, 3000.0, 3200.0, 3300.0, 3500.0, 3600.0, TOP_N)
TWICE_LOADS = (3300.0, 3400.0, TOP_N)
RIGS = ("nominal", "worst")
ONSET_MARGIN = 0.99     # the worst rig is held up to its onset (the robust check's); at 0.99 of it its
                        # loop is barely damped and the load's noise alone crosses it


@pytest.fixture(scope="module", params=RIGS)
def rig(request):
    if request.param == "nominal":
        return StallRig(TABLE)
    worst = worst_rig(TABLE)
    assert worst is not None, "the shipped table records its robust check's worst rig"
    return StallRig(TABLE, rig=worst)


def _say(o) -> str:
    return (f"{o.gap_samples} samples at {o.load_n:g} N: fault {o.fault or 'none'}, strain at "
            f"{100 * o.strain_fraction:.1f} % of the limit, stacks moved up to {o.voltage_excursion_v:.1f} V"
            f"{', saturated' if o.saturated else ''}")


def _held_here(rig, load):
    if not rig.nominal and load > ONSET_MARGIN * TABLE.robust["onset_N"]:
        pytest.skip(f"{load:g} N: the worst rig is not held there "
                    f"(unstable from {TABLE.robust['onset_N']:.0f} N)")


@pytest.mark.parametrize("load", LOADS)
def test_a_stall_as_long_as_the_live_limit_is_survived(rig, load):
    _held_here(rig, load)
    limit = rig.run(load, 1).limit_samples
    assert limit >= 1, f"at {load:g} N the live limit is {limit:g} samples: not even one is ridden through"
    at = rig.run(load, rig.stall_samples(limit))
    assert at.survived, f"a stall at the live limit was lost: {_say(at)}"


@pytest.mark.parametrize("load", TWICE_LOADS)
def test_twice_the_live_limit_is_lost_where_the_rig_sets_the_limit(rig, load):
    if not rig.nominal and load == TOP_N:
        pytest.skip("the worst rig is not held at the table's top")
    _held_here(rig, load)
    limit = rig.run(load, 1).limit_samples
    assert limit < TABLE.ride_through.gap_cap_samples, f"at {load:g} N the limit is the cap ({limit:g})"
    twice = rig.run(load, rig.stall_samples(2 * limit), lift=True)
    assert not twice.survived, (
        f"a stall of twice the live limit ({limit:g} samples) was survived with the limit lifted: "
        f"the limit is more than a factor of two below the survival edge ({_say(twice)})")


LET_GO_LOADS = {"nominal": (3300.0, 3400.0), "worst": (3300.0, 3400.0)}


@pytest.mark.parametrize("at", range(2), ids=("3300", "3400"))
def test_a_stall_past_the_limit_within_the_let_go_is_ridden_through_and_one_past_it_faults(rig, at):
    """Between the live limit (3.5 sigma to spare) and the let-go (the recovery's expected peak at
    the headroom) the loop does not let go: at 3300 and 3400 N, past the nominal Fx,cr, a stall
    halfway between them is ridden through without a fault and survived (measured edges: 121 and
    95 samples nominal, 158 and 70 on the worst rig, against halfway 111 and 75, 109 and 63); two
    samples past the let-go it faults STALE_INPUT."""
    load = LET_GO_LOADS["nominal" if rig.nominal else "worst"][at]
    still = rig.run(load, 1)
    limit, let_go = still.limit_samples, still.let_go_samples
    assert let_go > limit + 2, f"at {load:g} N the let-go ({let_go:.1f}) is not past the limit ({limit:.1f})"
    middle = rig.run(load, rig.stall_samples(0.5 * (limit + let_go)))
    assert middle.gap_samples > limit, f"the stall of {middle.gap_samples} samples is within the limit"
    assert not middle.fault, f"a stall between the limit and the let-go faulted: {_say(middle)}"
    assert middle.survived, f"a stall between the limit and the let-go was lost: {_say(middle)}"
    past = rig.run(load, rig.stall_samples(let_go) + 2)
    assert past.fault == "STALE_INPUT", f"a stall two samples past the let-go did not fault: {_say(past)}"


SECOND_LOADS = {"nominal": (3200.0, 3300.0, 3400.0), "worst": (3300.0, 3400.0, 3500.0)}


@pytest.mark.parametrize("at", range(3), ids=("lowest", "middle", "highest"))
def test_a_second_stall_of_the_limit_right_after_the_first_is_survived(rig, at):
    """A stall of the limit, one sample answered, then another stall of the limit then in force:
    the recovery the first leaves (the stacks up to 40 V from their operating point at 3300 N) is
    the excursion the live limit grows from, so the second is shorter and survived, past the
    nominal Fx,cr on both rigs (the worst rig up to 3500 N, 0.97 of its onset). Counted through
    the spreads alone, the second was lost at 3300 N nominal (34 samples: 102 V moved) and at
    3500 N on the worst rig (38: 73 V)."""
    load = SECOND_LOADS["nominal" if rig.nominal else "worst"][at]
    limit = rig.run(load, 1).limit_samples
    o = rig.run(load, None, before=(rig.stall_samples(limit), 1))
    assert o.gap_samples >= 1, f"at {load:g} N nothing was ridden through after the first stall"
    assert o.survived, f"a stall at the live limit right after another was lost: {_say(o)}"


def test_at_3300_n_the_live_limit_is_10_ms_nominal_and_5_ms_on_the_worst_rig(rig):
    """The acceptance's floor at 3300 N (above the nominal Fx,cr of 3194 N), at the rig's own
    sample rate."""
    floor_ms = 10.0 if rig.nominal else 5.0
    limit = rig.run(3300.0, 1).limit_samples
    assert 1e3 * limit / rig.rate >= floor_ms, (
        f"the live limit at 3300 N is {1e3 * limit / rig.rate:.1f} ms ({limit:g} samples), "
        f"below {floor_ms:g} ms")


LOSS_LOADS = (2500.0, 3300.0, 3500.0)


@pytest.mark.parametrize("load", LOSS_LOADS)
def test_every_other_sample_lost_for_300_ms_is_survived(rig, load):
    """A loss that persists (each gap a single sample, as a datagram queue that overflows
    gives): the compensator catches up on each sample missed and keeps the beam's time, so the
    loop is the same loop answering every other sample. Held still instead (the estimate held),
    it ran at half its rate and went unstable from 2500 N on both rigs within 300 ms."""
    _held_here(rig, load)
    o = rig.loss(load, every=2, duration_s=0.3)
    assert o.gap_samples > 0.25 * 0.3 * rig.rate, f"the loss was not injected ({o.gap_samples} samples lost)"
    assert o.survived, f"every other sample lost for 300 ms: {_say(o)}"

