"""Gain table files: the shipped default, round trips, and refusal of every bad file."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from beamctl.gains.build import build_table, check_points, closed_loop_checks
from beamctl.gains.compensator import MATRICES
from beamctl.gains.defaults import paper_table_path
from beamctl.gains.table import (
    DesignSettings,
    GainTable,
    GainTableError,
    content_sha256,
    load_table,
    write_table,
)
from beamctl.models import build_model, parameters_from_dict
from beamctl.models.iochain import AnalogFilter, IOChain

FORMAT2_CHECK = Path(__file__).parent / "data" / "default_table_format2_check.json"

# libyaml where it is installed: the same YAML documents as the pure-Python reader and writer
# make, read and written several times faster (a gain table is mostly long lists of numbers)
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


@pytest.fixture(scope="module")
def default_table(paper_params):
    return load_table(paper_table_path(), paper_params)


@pytest.fixture(scope="module")
def small_table(paper_model):
    return build_table(paper_model, [0.0, 1000.0, 2000.0], check=True)


def test_default_table_covers_0_to_4000_N_every_50_N(default_table):
    np.testing.assert_array_equal(default_table.loads_n, np.arange(0.0, 4001.0, 50.0))
    assert default_table.gains.shape == (81, 4, 12)
    assert default_table.compensator.n_points == 81 and default_table.compensator.n_states == 4
    assert default_table.schedule.mode == "interpolate"
    assert default_table.design.kind == "integral-lqr" and default_table.design.io.is_direct
    assert default_table.design.sample_rate_hz == 2500.0
    assert default_table.all_stable and not default_table.forced


def test_default_table_is_stable_at_every_point_and_midpoint_beyond_the_critical_load(
        paper_model, default_table):
    """Recomputed, not read from the file: the discrete loop with the full FE model."""
    checks = closed_loop_checks(paper_model, default_table)
    assert [c.load_n for c in checks] == check_points(default_table.loads_n)
    assert len(checks) == 161 and checks[-1].load_n == 4000.0
    unstable = [(c.load_n, round(c.spectral_radius, 6)) for c in checks if not c.stable]
    assert not unstable, f"closed loop unstable at (load N, spectral radius): {unstable}"


STALE = ("gains/default.yaml is stale: rebuild it with `beamctl gains build --out gains/default.yaml` "
         "and check it with `beamctl gains check gains/default.yaml`")


def test_regenerating_the_default_table_gives_the_same_gains(paper_model, default_table):
    """The gains to a relative 1e-5. Beyond the critical load the Riccati problem is ill
    conditioned and LAPACK's result depends on the OpenBLAS kernel the CPU selects: its errors
    are relative to the whole solution (up to 2e-10 of the largest gain), so the smallest
    gains carry them magnified. The mode-2 displacement gain, 88.6 against 1.6e7 for the
    integrals at 4000 N, differs by up to 1.4e-5 of itself between the Haswell and SkylakeX
    kernels. Below 1e-9 of the largest gain (0.016 N per modal unit: against a mode-2
    displacement of micrometres, 1e-6 modal units, 1e-8 N) a difference is not physical."""
    fresh = build_table(paper_model, check=False)
    assert fresh.design == default_table.design and fresh.schedule == default_table.schedule, STALE
    np.testing.assert_array_equal(fresh.loads_n, default_table.loads_n, err_msg=STALE)
    floor = 1e-9 * np.abs(default_table.gains).max()
    np.testing.assert_allclose(
        fresh.gains, default_table.gains, rtol=1e-5, atol=floor,
        err_msg=f"the rebuilt gains differ from the shipped ones by more than 1e-5 relative (LAPACK "
                f"kernels differ by up to 1.4e-5 on the smallest gains beyond the critical load, "
                f"{floor:.2g} absolute): {STALE}")
    # (C0 Phi)^-1 is well conditioned (cond 3.2): the kernels agree to 5e-10
    np.testing.assert_allclose(fresh.c0_phi_inv, default_table.c0_phi_inv, rtol=1e-8, err_msg=STALE)


def test_the_compensator_form_checks_the_same_loop_as_format_2_did(default_table):
    """The shipped table, rebuilt in format 3 (the same gains K), is checked on the compensator
    the step runs with the delayed-ZOH loop of gains/closedloop.py; the format-2 table's check
    analysed the same loop written out (q, velocity filter, K) in gains/discrete.py. Their
    spectral radii at all 161 points agree to rounding."""
    old = json.loads(FORMAT2_CHECK.read_text())
    assert [p[0] for p in old["points"]] == [c.load_n for c in default_table.checks]
    diff = max(abs(c.spectral_radius - p[1])
               for c, p in zip(default_table.checks, old["points"], strict=True))
    assert diff <= 1e-12, f"spectral radii differ from format 2's check by up to {diff:.3g}"


def test_regenerating_the_default_table_gives_the_same_closed_loop(paper_model, default_table):
    """What matters of the gains is the loop they close: the rebuilt table's spectral radius
    at every check point equals the stored check's within 1 % of the table's stability margin
    (1 - 0.999942 = 5.8e-5); the kernels agree to 1e-13. (The ride-through analysis is not
    needed for that: it costs seconds.)"""
    fresh = build_table(paper_model, analyse_ride_through=False)
    stored = default_table.checks
    assert [c.load_n for c in fresh.checks] == [c.load_n for c in stored], STALE
    margin = 1.0 - max(c.spectral_radius for c in stored)
    assert margin > 0, f"the stored check says the shipped table is unstable: {STALE}"
    diff = np.array([f.spectral_radius - s.spectral_radius
                     for f, s in zip(fresh.checks, stored, strict=True)])
    worst = int(np.argmax(np.abs(diff)))
    assert np.abs(diff[worst]) <= 0.01 * margin, (
        f"at {stored[worst].load_n:g} N the rebuilt closed loop has spectral radius "
        f"{fresh.checks[worst].spectral_radius:.9f}, the stored check {stored[worst].spectral_radius:.9f}: "
        f"a difference of {diff[worst]:.2g} against a stability margin of {margin:.2g}. {STALE}")


def test_a_written_table_reads_back_bit_for_bit(tmp_path, small_table, paper_params):
    path = write_table(small_table, tmp_path / "t.yaml")
    back = load_table(path, paper_params)
    np.testing.assert_array_equal(back.gains, small_table.gains)
    for m in (*MATRICES, "h", "start"):
        np.testing.assert_array_equal(getattr(back.compensator, m), getattr(small_table.compensator, m),
                                      err_msg=m)
    assert back.compensator.plane_states == small_table.compensator.plane_states
    assert back.compensator.period_s == small_table.compensator.period_s
    np.testing.assert_array_equal(back.loads_n, small_table.loads_n)
    np.testing.assert_array_equal(back.c0_phi_inv, small_table.c0_phi_inv)
    assert back.design == small_table.design and back.checks == small_table.checks
    assert back.created == small_table.created and back.tool_version == small_table.tool_version
    assert back.intact, "the content hash of a table as written must match when read back"
    assert yaml.load(path.read_text(), Loader=_LOADER)["sha256"] == content_sha256(small_table.to_dict())


def _edited(tmp_path, table, edit) -> str:
    data = table.to_dict()
    edit(data)
    path = tmp_path / "edited.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _set_nan(d):
    d["compensator"]["d"][1][0][3] = float("nan")


def _swap_loads(d):
    d["loads_N"][0], d["loads_N"][1] = d["loads_N"][1], d["loads_N"][0]


@pytest.mark.parametrize(("edit", "field", "words"), [
    (_set_nan, "compensator.d", "non-finite"),
    (lambda d: d["compensator"]["a"][2].pop(), "compensator.a", "shape"),
    (lambda d: d["compensator"]["start"].pop(), "compensator.a", "shape"),
    (lambda d: d["compensator"]["plane_states"].__setitem__("y", [0, 1]), "compensator.plane_states",
     "splits the states"),
    (lambda d: d["compensator"].pop("ki"), "compensator.ki", "missing"),
    (lambda d: d["design"]["gains"][2].pop(), "design.gains", "shape"),
    (lambda d: d["design"].__setitem__("kind", "pid"), "design.kind", "one of"),
    (lambda d: d["design"].__setitem__("parameters", {}), "design.parameters", "integral-lqr"),
    (lambda d: d["design"]["io"].__setitem__("delay_samples", -1), "design.io.delay_samples", ">= 0"),
    (lambda d: d["design"].pop("io"), "design.io", "missing"),
    (_swap_loads, "loads_N", "strictly increasing"),
    (lambda d: d["c0_phi_inv"][0].__setitem__(0, "x"), "c0_phi_inv", "numbers"),
    (lambda d: d["model"]["parameters"]["beam"].__setitem__("radius", 0.0041), "model.sha256",
     "edited after"),
    (lambda d: d.pop("design"), "design", "missing"),
    (lambda d: d["design"].__setitem__("velocity_cutoff_hz", 2000.0), "design.velocity_cutoff_hz",
     "Nyquist"),
    (lambda d: d["design"]["R_diagonal"].__setitem__(0, 0.0), "design.R_diagonal", "positive"),
    (lambda d: d["schedule"].__setitem__("mode", "nearest"), "schedule.mode", "one of"),
    (lambda d: d["check"]["points"][0].__setitem__("spectral_radius", 1.2), "sha256",
     "changed after it was built"),
    (lambda d: d.__setitem__("format", "something-else/1"), "format", "not a beamctl gain table"),
    (lambda d: d.__setitem__("format", "beamctl-gain-table/1"), "format", "rebuild it with"),
    (lambda d: d.__setitem__("format", "beamctl-gain-table/2"), "format", "written by an earlier beamctl"),
])
def test_hand_edited_table_is_refused_naming_the_field(tmp_path, small_table, paper_params,
                                                       edit, field, words):
    path = _edited(tmp_path, small_table, edit)
    with pytest.raises(GainTableError) as err:
        load_table(path, paper_params)
    assert err.value.key == field, str(err.value)
    assert words in str(err.value), str(err.value)


def test_truncated_table_is_refused(tmp_path, small_table, paper_params):
    text = write_table(small_table, tmp_path / "full.yaml").read_text()
    for cut in (len(text) // 3, len(text) // 2, len(text) - 40):
        path = tmp_path / f"cut{cut}.yaml"
        path.write_text(text[:cut])
        with pytest.raises(GainTableError) as err:
            load_table(path, paper_params)
        assert "expected" in str(err.value)


def test_corrupted_bytes_are_refused(tmp_path, paper_params):
    path = tmp_path / "garbage.yaml"
    path.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(GainTableError):
        load_table(path, paper_params)
    missing = tmp_path / "absent.yaml"
    with pytest.raises(GainTableError, match="readable"):
        load_table(missing, paper_params)


def test_table_for_another_model_is_refused(tmp_path, small_table):
    path = write_table(small_table, tmp_path / "t.yaml")
    other = parameters_from_dict({"supports": {"rotational_stiffness": 200.0}})
    with pytest.raises(GainTableError) as err:
        load_table(path, other)
    assert err.value.key == "model.sha256" and "regenerate" in str(err.value)


def test_unstable_table_is_written_only_when_forced_and_never_runs(tmp_path, paper_model):
    unstable = build_table(paper_model, [4000.0, 4500.0])
    assert not unstable.all_stable, "beyond 4000 N the sampled loop cannot hold the beam"
    with pytest.raises(GainTableError, match="--force"):
        write_table(unstable, tmp_path / "u.yaml")
    path = write_table(replace(unstable, forced=True), tmp_path / "u.yaml")
    back = load_table(path, paper_model.params, verify=False)
    assert back.forced and not back.all_stable and back.intact
    with pytest.raises(GainTableError) as err:
        load_table(path, paper_model.params)
    assert err.value.key == "check.forced" and "unstable at [4250.0, 4500.0] N" in str(err.value)
    assert f"beamctl gains build --design integral-lqr --out {path}" in str(err.value)


def _rewritten(path, edit) -> None:
    data = yaml.load(path.read_text(), Loader=_LOADER)
    edit(data)
    path.write_text(yaml.dump(data, Dumper=_DUMPER, sort_keys=False))


def _scale_gain_at(load_n: float, factor: float):
    def edit(d):
        d["compensator"]["d"][d["loads_N"].index(load_n)][0][0] *= factor
    return edit


def _other_model_with_its_own_hash(d):
    d["model"]["parameters"]["beam"]["radius"] = 4.1e-3
    d["model"]["sha256"] = parameters_from_dict(d["model"]["parameters"]).digest()


@pytest.mark.parametrize("edit", [
    _scale_gain_at(2000.0, 10.0),
    lambda d: d["loads_N"].__setitem__(1, 900.0),
    lambda d: d["c0_phi_inv"][0].__setitem__(0, d["c0_phi_inv"][0][0] * (1 + 1e-15)),
    lambda d: d["design"].__setitem__("velocity_cutoff_hz", 150.0),
    lambda d: d["design"]["io"].__setitem__("delay_samples", 0.5),
    lambda d: d["design"]["gains"][0][0].__setitem__(0, 1.0),
    lambda d: d["schedule"].__setitem__("mode", "paper"),
    _other_model_with_its_own_hash,
    lambda d: d["check"]["points"].pop(),
    lambda d: d["check"].__setitem__("forced", True),
    lambda d: d.__setitem__("tool_version", "9.9"),
    lambda d: d.__setitem__("created", "2020-01-01T00:00:00+00:00"),
    lambda d: d.__setitem__("note", "checked by hand"),
], ids=["gain", "grid", "c0_phi_inv-last-bit", "design", "design-io", "design-gains", "schedule",
        "model-and-its-hash",
        "check", "forced", "version", "created", "extra-field"])
def test_the_content_hash_covers_every_field(tmp_path, small_table, paper_params, edit):
    path = write_table(small_table, tmp_path / "t.yaml")
    _rewritten(path, edit)
    with pytest.raises(GainTableError) as err:
        load_table(path)
    message = str(err.value)
    assert err.value.key == "sha256", message
    assert "changed after it was built" in message and f"beamctl gains check {path}" in message, message
    changed = load_table(path, verify=False)
    assert not changed.intact, "read for inspection, the change is reported"
    with pytest.raises(GainTableError, match="changed after it was built"):
        write_table(changed, tmp_path / "laundered.yaml")


def test_a_table_built_without_its_check_is_refused_to_run(tmp_path, paper_model):
    unchecked = build_table(paper_model, [0.0, 1000.0], check=False)
    assert not unchecked.checked and not unchecked.all_stable
    path = write_table(unchecked, tmp_path / "unchecked.yaml")
    with pytest.raises(GainTableError) as err:
        load_table(path, paper_model.params)
    assert err.value.key == "check.points" and "built without it" in str(err.value), str(err.value)
    assert load_table(path, verify=False).intact


def test_model_parameters_in_the_table_rebuild_the_same_model(default_table, paper_model):
    rebuilt = build_model(default_table.model_parameters)
    np.testing.assert_array_equal(rebuilt.elastic_stiffness, paper_model.elastic_stiffness)


def test_format_2_is_refused_in_one_line_saying_what_to_run(tmp_path, small_table):
    path = _edited(tmp_path, small_table, lambda d: d.__setitem__("format", "beamctl-gain-table/2"))
    with pytest.raises(GainTableError) as err:
        load_table(path, verify=False)
    message = str(err.value)
    assert "\n" not in message and "written by an earlier beamctl" in message, message
    assert f"beamctl gains build --out {path}" in message and f"beamctl gains check {path}" in message


def test_a_table_of_another_design_is_built_from_its_compensator_and_reads_back(tmp_path, small_table,
                                                                              paper_model):
    """What a model-based design does: a GainTable from a Compensator and its design settings
    (kind, rate, the I/O chain it assumes, its parameters as a free mapping), checked on the
    chain it declares, written, and read back as it was."""
    io = IOChain(delay_samples=1.0, anti_alias=AnalogFilter("butterworth", 2, 1000.0))
    design = DesignSettings(kind="lqg", sample_rate_hz=small_table.design.sample_rate_hz, io=io,
                            parameters={"modes_per_plane": 7, "noise": {"strain": 1e-7}, "q": [1.0, 2.0]})
    table = GainTable(loads_n=small_table.loads_n, compensator=small_table.compensator,
                      c0_phi_inv=small_table.c0_phi_inv, design=design, schedule=small_table.schedule,
                      model_parameters=paper_model.params)
    table = replace(table, checks=closed_loop_checks(paper_model, table))
    path = write_table(replace(table, forced=not table.all_stable), tmp_path / "lqg.yaml")
    back = load_table(path, paper_model.params, verify=False)
    assert back.design == design and back.gains is None and back.intact
    assert back.checks == table.checks
    np.testing.assert_array_equal(back.compensator.d, table.compensator.d)
    data = yaml.load(path.read_text(), Loader=_LOADER)
    assert data["design"]["io"]["anti_alias"]["type"] == "butterworth"
    assert set(data["design"]) == {"kind", "sample_rate_hz", "io", "parameters"}


def test_a_table_refuses_a_compensator_that_does_not_fit(small_table):
    comp = small_table.compensator
    with pytest.raises(ValueError, match="grid points"):
        replace(small_table, loads_n=small_table.loads_n[:2])
    with pytest.raises(ValueError, match="period"):
        replace(small_table, compensator=replace(comp, period_s=1e-3))
    with pytest.raises(ValueError, match="shape"):
        replace(small_table, compensator=replace(comp, d=comp.d[:, :2]))
    with pytest.raises(ValueError, match="integral-lqr"):
        replace(small_table, gains=None)
