"""The files of a model fit: measured eigenfrequencies (CSV) read, the fitted model written as a
configuration file (its parameters with the fit's figures as comments) and read back."""

from __future__ import annotations

import csv
import math

import yaml

from beamctl.assembly.run import load_model_file
from beamctl.config.schema import ConfigError, read_yaml
from beamctl.models.fit import Eigenfrequency, FitResult
from beamctl.models.measured import FrfData
from beamctl.models.params import ModelParameters


def read_eigenfrequencies(path: str) -> list[Eigenfrequency]:
    """The measured eigenfrequencies of a CSV file (see ``--eigenfrequencies``)."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = [r for r in csv.reader(f) if r and not r[0].lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError("--eigenfrequencies", path, f"a readable CSV file ({exc})") from None
    if not rows:
        raise ConfigError("--eigenfrequencies", path, "a header row and at least one row")
    header = [h.strip() for h in rows[0]]
    known = ("load_n", "mode", "frequency_hz", "plane", "sigma")
    for h in header:
        if h not in known:
            raise ConfigError("column", h, f"one of {', '.join(known)}", path)
    for h in known[:3]:
        if h not in header:
            raise ConfigError("column", h, "present (load_n, mode, frequency_hz are required)", path)
    out = []
    for n, row in enumerate(rows[1:], start=2):
        cells = dict(zip(header, (c.strip() for c in row), strict=False))
        try:
            load, mode, freq = float(cells["load_n"]), int(cells["mode"]), float(cells["frequency_hz"])
            sigma = float(cells.get("sigma") or 0.005)
        except (KeyError, ValueError):
            raise ConfigError(f"row {n}", ",".join(row), "numbers: load_n, mode (1, 2 or 3), frequency_hz",
                              path) from None
        plane = cells.get("plane") or "y"
        if not (math.isfinite(load) and load >= 0 and mode in (1, 2, 3) and math.isfinite(freq) and freq > 0
                and plane in ("y", "z") and math.isfinite(sigma) and sigma > 0):
            raise ConfigError(f"row {n}", ",".join(row),
                              "load_n >= 0, mode 1..3, frequency_hz > 0, plane y or z, sigma > 0", path)
        out.append(Eigenfrequency(load, mode, freq, plane, sigma))
    return out


def fitted_document(result: FitResult, files: list[FrfData]) -> str:
    """The fitted model as a configuration file: a header of comments with the fit, the model
    section (every model parameter), and the stack force per volt when it was fitted."""
    lines = ["# Model fitted by `beamctl model fit` to:"]
    lines += [f"#   {d.source} ({d.load_n:.0f} N, {len(d.frequencies_hz)} frequencies)" for d in files]
    misfit = "" if result.misfit is None else f"; misfit {result.misfit:.3g} (1: down to the data's noise)"
    lines.append(f"# cost {result.cost:.6g} (start {result.start_cost:.6g}), "
                 f"{result.evaluations} evaluations{misfit}")
    lines.append("# parameter: start -> fitted +- standard error")
    for k in result.keys:
        lines.append(f"#   {k}: {_fmt(result.start[k])} -> {_fmt(result.values[k])} +- "
                     f"{_fmt(result.std_errors[k])}")
    for pair, r in result.correlations.items():
        lines.append(f"# correlated (poorly separable): {pair.replace('|', ' and ')}: {r:+.3f}")
    lines += [f"# warning: {w}" for w in result.warnings]
    lines += ["# `beamctl model --config F` and `beamctl gains build --config F` read the model section;",
              "# a rig's configuration takes it with `model: F`."]
    doc: dict = {"model": result.parameters.to_dict()}
    if result.force_constant_n_per_v is not None:
        lines.append("# Set the rig's controller.actuators.force_constant_n_per_v to the fitted value below.")
        doc["controller"] = {"actuators": {"force_constant_n_per_v": result.force_constant_n_per_v}}
    return "\n".join(lines) + "\n" + yaml.safe_dump(doc, sort_keys=False)


def _fmt(v) -> str:
    return "[" + ", ".join(f"{e:.6g}" for e in v) + "]" if isinstance(v, list) else f"{v:.6g}"


def load_fitted(path: str) -> tuple[ModelParameters, float | None]:
    """A fitted model file: its parameters and the fitted force constant (None if absent)."""
    params = load_model_file(path, "--fitted")
    data = read_yaml(path)
    k = ((data.get("controller") or {}).get("actuators") or {}).get("force_constant_n_per_v")
    return params, (float(k) if k is not None else None)
