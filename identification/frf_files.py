"""Files of measured frequency responses (``FrfData``, models/measured.py): written as a
NumPy ``.npz`` and a MATLAB ``.mat`` file side by side, read from ``.npz``, ``.mat`` or
``.csv``.

``.npz`` and ``.mat`` hold the same variables (channel order: outputs y1, z1, y2, z2 = eps_y1,
eps_z1, eps_y2, eps_z2; inputs yA, zA, yB, zB = Fay,A, Faz,A, Fay,B, Faz,B)::

    format                  "beamctl-frf"
    format_version          1
    frequencies_hz          [nf] strictly increasing, > 0 (a column in MATLAB)
    frf                     [nf x 4 x 4] complex, strain per N, frequency x output x input
                            (the layout of MATLAB's tfestimate(x, y, ..., 'mimo'));
                            NaN where not measured
    coherence               [nf x 4 x 4] in [0, 1]; NaN where not measured
    load_n                  axial load during the measurement, N (>= 0)
    sample_rate_hz          NaN when unknown
    force_constant_n_per_v  NaN when the forces were measured, not computed from voltages
    io_json                 the rig's I/O chain (models/iochain.py) as JSON, "null" for none
    settings_json           how it was measured, a JSON object ("{}" for nothing)
    outputs, inputs         the channel names (a cell array in MATLAB)

The ``.npz`` holds no pickled objects (``np.load(f, allow_pickle=False)`` reads it). A file
written by hand (in MATLAB: ``save('frf.mat', 'frequencies_hz', 'frf', 'load_n', '-v7')``)
needs only ``frequencies_hz``, ``frf`` and ``load_n``: without ``coherence`` every measured
entry is taken as fully coherent (1); ``sample_rate_hz`` and ``force_constant_n_per_v`` that
are absent, empty or NaN are unknown (None); ``io_json`` and ``settings_json`` may be left out;
a scalar may be a plain number or a 1 x 1 array, a vector a row or a column. ``format`` and
``format_version``, where present, must name this format and a version this code knows.
Other variables are ignored. MATLAB v7.3 (HDF5) files are not read.

CSV, for data from any other tool (UTF-8, comma-separated, one row per frequency)::

    # load_n: 2000
    # sample_rate_hz: 6000
    frequency_hz,re_y1_yA,im_y1_yA,coh_y1_yA,re_z1_zA,im_z1_zA
    10.0,1.25e-07,-3.1e-09,0.998,1.19e-07,-2.7e-09
    12.5,1.27e-07,-4.0e-09,0.997,1.21e-07,-3.5e-09

- optional comment lines first, ``# key: value``, for ``load_n`` (required),
  ``sample_rate_hz`` and ``force_constant_n_per_v`` (optional); other ``#`` lines are ignored;
- then a header row: ``frequency_hz`` first, then for any of the 16 (output, input) pairs the
  columns ``re_<out>_<in>`` and ``im_<out>_<in>`` (both, real and imaginary part in strain per
  N) and optionally ``coh_<out>_<in>``, with ``<out>`` one of y1, z1, y2, z2 and ``<in>`` one
  of yA, zA, yB, zB, in any order; a pair without columns was not measured (NaN), a pair
  without a ``coh_`` column is taken as fully coherent (1);
- then one row of numbers per frequency (``nan`` is a number; blank lines are skipped).

Everything read is checked, and a refusal is a ``ConfigError`` naming the file, the field and
the value found (arrays summarised: ``frf[12, 0, 0] = nan+1j``, ``shape (4, 4, 200)``) and what
was expected: frequencies a vector of finite values > 0, strictly increasing; ``frf`` and
``coherence`` nf x 4 x 4; an entry either NaN at every frequency (not measured) or finite at
every frequency, and at least one entry measured; coherence in [0, 1] where measured (values
within 1e-9 outside it are rounding and are clipped); ``load_n`` finite and >= 0;
``sample_rate_hz`` and ``force_constant_n_per_v`` > 0 where known; ``io_json`` a valid I/O
chain; ``settings_json`` a JSON object. ``write_frf`` applies the same checks before it writes,
so whatever it writes reads back.
"""

from __future__ import annotations

import csv
import json
import math
import re
from io import BytesIO
from pathlib import Path
from typing import Any

import numpy as np
import scipy.io

from beamctl.common.outputs import check_file, replacing
from beamctl.config.schema import ConfigError
from beamctl.models.iochain import io_chain
from beamctl.models.measured import INPUTS, OUTPUTS, FrfData

FORMAT = "beamctl-frf"
FORMAT_VERSION = 1
READ_SUFFIXES = (".npz", ".mat", ".csv")
COHERENCE_ROUNDING = 1e-9      # coherence this far outside [0, 1] is rounding, and is clipped
CSV_KEYS = ("load_n", "sample_rate_hz", "force_constant_n_per_v")

_LAYOUT = (f"frequency x output ({', '.join(OUTPUTS)}) x input ({', '.join(INPUTS)}), the layout of "
           "MATLAB's tfestimate(x, y, ..., 'mimo'); NaN for an entry not measured")
_CSV_COLUMN = re.compile(rf"(re|im|coh)_({'|'.join(OUTPUTS)})_({'|'.join(INPUTS)})")
_CSV_NAMES = (f"a column name re_<out>_<in>, im_<out>_<in> or coh_<out>_<in> with <out> one of "
              f"{', '.join(OUTPUTS)} and <in> one of {', '.join(INPUTS)} (e.g. re_y1_yA)")
_MAT = "a MATLAB .mat file of version 5 to 7.2 (in MATLAB: save(f, ..., '-v7'))"
_NPZ = "a NumPy .npz archive as numpy.savez writes it"


class _Found(str):
    """What a file held, shown as it is (without quotes) in a ConfigError's message."""

    def __repr__(self) -> str:
        return str(self)


def check_frf_out(path: str | Path) -> list[Path]:
    """The two files ``write_frf`` writes for ``path`` (``<stem>.npz``, ``<stem>.mat``), each
    checked writable: a command refuses a bad ``--out`` before its work starts."""
    p = Path(path)
    if p.suffix.lower() not in ("", ".npz", ".mat"):
        raise ConfigError("--out", str(path), "a file name ending in .npz or .mat (both are written)")
    stem = p.with_suffix("")
    targets = [stem.with_name(stem.name + ".npz"), stem.with_name(stem.name + ".mat")]
    for target in targets:
        check_file(target, "--out")
    return targets


def write_frf(data: FrfData, path: str | Path) -> list[Path]:
    """Write ``data`` as ``<stem>.npz`` and ``<stem>.mat`` next to each other and return both
    paths (``path`` ends in ``.npz`` or ``.mat``, or has no suffix).

    Each file is replaced whole (``common/outputs.py``). ``data`` that ``read_frf`` would refuse
    is refused with the same ConfigError, so whatever is written reads back; a place that
    cannot be written is refused with OutputPathError, before anything is written.
    """
    targets = check_frf_out(path)
    source = f"{data.source or 'measurement'} (to be written to {targets[0].with_suffix('')})"
    checked = _validated(data.frequencies_hz, data.frf, data.coherence, data.load_n, data.sample_rate_hz,
                         data.force_constant_n_per_v, data.io, data.settings, source)
    variables: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "frequencies_hz": checked.frequencies_hz,
        "frf": checked.frf,
        "coherence": checked.coherence,
        "load_n": checked.load_n,
        "sample_rate_hz": math.nan if checked.sample_rate_hz is None else checked.sample_rate_hz,
        "force_constant_n_per_v": (math.nan if checked.force_constant_n_per_v is None
                                   else checked.force_constant_n_per_v),
        "io_json": _json_text(checked.io, "io", source),
        "settings_json": _json_text(checked.settings, "settings", source),
    }
    with replacing(targets[0]) as temp, open(temp, "wb") as stream:
        np.savez(stream, **variables, outputs=np.array(OUTPUTS), inputs=np.array(INPUTS))
    with replacing(targets[1]) as temp:
        scipy.io.savemat(temp, {**variables, "outputs": np.array(OUTPUTS, dtype=object),
                                "inputs": np.array(INPUTS, dtype=object)},
                         appendmat=False, format="5", do_compression=True, oned_as="column")
    return targets


def read_frf(path: str | Path) -> FrfData:
    """The measurement in ``path``, a ``.npz``, ``.mat`` or ``.csv`` file (by its suffix, in
    any case), checked (see the module docstring); anything wrong is refused with a
    ConfigError naming the file, the field, the value found and what was expected."""
    p = Path(path)
    source = str(path)
    suffix = p.suffix.lower()
    if suffix not in READ_SUFFIXES:
        found = f"a file name ending in {p.suffix!r}" if p.suffix else "a file name without a suffix"
        raise ConfigError("", _Found(found), "a file ending in .npz, .mat or .csv (the suffix names the "
                          "format)", source)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ConfigError("", _Found((exc.strerror or str(exc)).lower()), f"a readable {suffix} file",
                          source) from None
    if suffix == ".csv":
        return _from_csv(raw, source)
    return _from_variables(_load_npz(raw, source) if suffix == ".npz" else _load_mat(raw, source), source)


def _reason(exc: BaseException) -> str:
    """An exception's message in one line."""
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def _load_npz(raw: bytes, source: str) -> dict[str, Any]:
    if not raw.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        found = "an empty file" if not raw else "a file that is not a zip archive"
        raise ConfigError("", _Found(found), _NPZ, source)
    try:
        with np.load(BytesIO(raw), allow_pickle=False) as archive:
            return {name: archive[name] for name in archive.files}
    except Exception as exc:     # a damaged archive fails in zipfile, zlib or numpy, in many ways
        found = f"an archive numpy cannot read ({_reason(exc)})"
        raise ConfigError("", _Found(found), _NPZ, source) from None


def _load_mat(raw: bytes, source: str) -> dict[str, Any]:
    try:
        variables = scipy.io.loadmat(BytesIO(raw), squeeze_me=False, chars_as_strings=True)
    except NotImplementedError:   # scipy's answer to an HDF5-based file
        raise ConfigError("", _Found("a MATLAB v7.3 (HDF5) file"), _MAT, source) from None
    except Exception as exc:     # a damaged or foreign file fails in scipy's parser in many ways
        found = "an empty file" if not raw else f"a file scipy cannot read as MATLAB data ({_reason(exc)})"
        raise ConfigError("", _Found(found), _MAT, source) from None
    return {name: value for name, value in variables.items() if not name.startswith("__")}


def _from_variables(variables: dict[str, Any], source: str) -> FrfData:
    """An FrfData from the variables of an ``.npz`` or ``.mat`` file."""
    if "format" in variables:
        name = _text(variables["format"])
        if name != FORMAT:
            raise ConfigError("format", name if name is not None else _Found(_describe(variables["format"])),
                              f"{FORMAT!r} (this file holds another kind of data)", source)
    if "format_version" in variables:
        version = _scalar(variables["format_version"], "format_version", source)
        if version is None or not version.is_integer() or version < 1:
            raise ConfigError("format_version", version, f"an integer from 1 to {FORMAT_VERSION}", source)
        if version > FORMAT_VERSION:
            raise ConfigError("format_version", int(version),
                              f"{FORMAT_VERSION} or older: the file was written by a newer beamctl, "
                              "read it with that version", source)
    for key, names in (("outputs", OUTPUTS), ("inputs", INPUTS)):
        if key in variables:
            found = [_text(v) for v in np.asarray(variables[key], dtype=object).reshape(-1)]
            if tuple(found) != names:
                raise ConfigError(key, _Found(", ".join(map(str, found))),
                                  f"{', '.join(names)} in this order (the order of frf's axes)", source)
    return _validated(
        variables.get("frequencies_hz"), variables.get("frf"), variables.get("coherence"),
        _scalar(variables.get("load_n"), "load_n", source),
        _scalar(variables.get("sample_rate_hz"), "sample_rate_hz", source),
        _scalar(variables.get("force_constant_n_per_v"), "force_constant_n_per_v", source),
        _json_value(variables.get("io_json"), "io_json", None, source),
        _json_value(variables.get("settings_json"), "settings_json", {}, source),
        source)


def _text(value: Any) -> str | None:
    """A string from a str, an ``.npz`` string array or a MATLAB char array (or a 1 x 1 cell
    holding one); None for anything else."""
    if isinstance(value, str):
        return str(value)
    arr = np.asarray(value)
    if arr.dtype.kind == "U" and arr.size <= 1:
        return str(arr.reshape(-1)[0]) if arr.size else ""
    if arr.dtype.kind == "O" and arr.size == 1:
        return _text(arr.reshape(-1)[0])
    return None


def _describe(value: Any) -> str:
    """What a variable holds, for a message about one that holds the wrong kind of thing."""
    arr = np.asarray(value)
    kind = arr.dtype.kind
    if kind in "US":
        text = _text(arr)
        return f"text {text[:40]!r}" if text is not None else f"text (shape {arr.shape})"
    names = {"O": "a cell array", "V": "a MATLAB struct or object", "b": "logical values",
             "c": "complex numbers"}
    return f"{names.get(kind, f'{arr.dtype} values')} (shape {arr.shape})"


def _scalar(value: Any, key: str, source: str) -> float | None:
    """One real number from a number or a 1-element array; None for a missing or empty one."""
    if value is None:
        return None
    arr = np.asarray(value)
    if arr.dtype.kind not in "iuf":
        raise ConfigError(key, _Found(_describe(arr)), "a real number", source)
    if arr.size == 0:
        return None
    if arr.size != 1:
        raise ConfigError(key, _Found(f"shape {arr.shape}"), "one number", source)
    return float(arr.reshape(-1)[0])


def _json_value(value: Any, key: str, absent: Any, source: str) -> Any:
    """The value of a JSON text variable; ``absent`` when it is missing or empty."""
    if value is None:
        return absent
    text = _text(value)
    if text is None:
        raise ConfigError(key, _Found(_describe(value)), "JSON text (a char array in MATLAB)", source)
    if not text.strip():
        return absent
    try:
        return json.loads(text)
    except ValueError as exc:
        found = f"text that is not JSON ({_reason(exc)})"
        raise ConfigError(key, _Found(found), "JSON text", source) from None


def _json_text(value: Any, key: str, source: str) -> str:
    try:
        return json.dumps(value, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ConfigError(key, _Found(_reason(exc)), "JSON-ready values (str, finite numbers, booleans, "
                          "None, lists and mappings of them)", source) from None


def _complex_text(value: complex) -> str:
    return repr(complex(value)).strip("()")


def _entry(index: np.ndarray, frequencies_hz: np.ndarray) -> str:
    k, out, inp = (int(i) for i in index)
    return f"output {OUTPUTS[out]}, input {INPUTS[inp]}, at {frequencies_hz[k]:g} Hz"


def _array(value: Any, key: str, source: str, *, real: bool) -> np.ndarray:
    """An array of numbers (complex allowed unless ``real``); a missing one is refused."""
    if value is None:
        raise ConfigError(key, _Found("missing"), f"a variable {key} (README.md, 'Measured frequency "
                          "responses: file formats')", source)
    arr = np.asarray(value)
    if arr.dtype.kind not in ("iuf" if real else "iufc"):
        raise ConfigError(key, _Found(_describe(arr)), "real numbers" if real else "numbers", source)
    return arr.astype(float if real else complex)


def _matrix_shape(arr: np.ndarray, key: str, nf: int, source: str) -> None:
    if arr.shape == (nf, 4, 4):
        return
    expected = f"shape ({nf}, 4, 4) for {nf} frequencies: {_LAYOUT}"
    if arr.shape == (4, 4, nf):
        expected += f"; this is 4 x 4 x nf, permute({key}, [3 1 2]) in MATLAB gives nf x 4 x 4"
    raise ConfigError(key, _Found(f"shape {arr.shape}"), expected, source)


def _frequencies(value: Any, source: str) -> np.ndarray:
    f = _array(value, "frequencies_hz", source, real=True)
    if f.ndim == 2 and 1 in f.shape or f.ndim == 0:       # a MATLAB row or column, or one number
        f = f.reshape(-1)
    if f.ndim != 1 or f.size == 0:
        raise ConfigError("frequencies_hz", _Found(f"shape {f.shape}"), "a vector of at least one frequency",
                          source)
    bad = np.flatnonzero(~np.isfinite(f))
    if bad.size:
        raise ConfigError(f"frequencies_hz[{bad[0]}]", float(f[bad[0]]), "a finite frequency in Hz", source)
    bad = np.flatnonzero(f <= 0)
    if bad.size:
        raise ConfigError(f"frequencies_hz[{bad[0]}]", float(f[bad[0]]), "a frequency > 0 Hz (leave out the "
                          "0 Hz bin that tfestimate and scipy.signal.csd give first)", source)
    bad = np.flatnonzero(np.diff(f) <= 0) + 1
    if bad.size:
        k = bad[0]
        raise ConfigError(f"frequencies_hz[{k}]", float(f[k]), f"a frequency above frequencies_hz[{k - 1}] = "
                          f"{float(f[k - 1])!r} (strictly increasing)", source)
    return f


def _known(value: float | None, key: str, unit: str, source: str) -> float | None:
    """A quantity > 0 or unknown (None, or NaN in a file)."""
    if value is None or math.isnan(value):
        return None
    if not math.isfinite(value) or value <= 0:
        raise ConfigError(key, value, f"a finite number > 0 (in {unit}), or NaN or absent when unknown",
                          source)
    return float(value)


def _validated(frequencies_hz: Any, frf: Any, coherence: Any, load_n: Any, sample_rate_hz: Any,
               force_constant_n_per_v: Any, io: Any, settings: Any, source: str) -> FrfData:
    """The checks of every read and write (see the module docstring): an FrfData whose
    unmeasured entries are NaN in frf and coherence, or a ConfigError."""
    f = _frequencies(frequencies_hz, source)
    nf = f.size
    h = _array(frf, "frf", source, real=False)
    _matrix_shape(h, "frf", nf, source)
    measured = ~np.all(np.isnan(h), axis=0)
    if not measured.any():
        raise ConfigError("frf", _Found("NaN in all 16 entries"), "at least one measured entry, finite at "
                          "every frequency (in a CSV file, a pair of columns re_<out>_<in>, im_<out>_<in>)",
                          source)
    bad = np.argwhere(measured & ~np.isfinite(h))
    if bad.size:
        k, out, inp = bad[0]
        raise ConfigError(f"frf[{k}, {out}, {inp}]", _Found(_complex_text(h[k, out, inp])),
                          f"a finite value ({_entry(bad[0], f)}): a measured entry is finite at every "
                          "frequency, one not measured is NaN at all of them", source)
    if coherence is None:
        c = np.ones((nf, 4, 4))       # taken as fully coherent
    else:
        c = _array(coherence, "coherence", source, real=True)
        _matrix_shape(c, "coherence", nf, source)
    bad = np.argwhere(measured & ~((c >= -COHERENCE_ROUNDING) & (c <= 1 + COHERENCE_ROUNDING)))
    if bad.size:
        k, out, inp = bad[0]
        raise ConfigError(f"coherence[{k}, {out}, {inp}]", float(c[k, out, inp]),
                          f"a number from 0 to 1 where frf is measured ({_entry(bad[0], f)})", source)
    if load_n is None:
        raise ConfigError("load_n", _Found("missing"), "the axial load during the measurement in N", source)
    load = float(load_n)
    if not math.isfinite(load) or load < 0:
        raise ConfigError("load_n", load, "a finite number >= 0 (in N): the axial load during the "
                          "measurement", source)
    rate = _known(sample_rate_hz, "sample_rate_hz", "Hz", source)
    force_constant = _known(force_constant_n_per_v, "force_constant_n_per_v", "N/V", source)
    if io is not None:
        io_chain(io, source, prefix="io")
    if not isinstance(settings, dict):
        raise ConfigError("settings", settings, "a mapping (a JSON object)", source)
    return FrfData(
        frequencies_hz=f,
        frf=np.where(measured, h, complex(math.nan, math.nan)),
        coherence=np.where(measured, np.clip(c, 0.0, 1.0), math.nan),
        load_n=load, sample_rate_hz=rate, force_constant_n_per_v=force_constant,
        io=io, settings=settings, source=source)


def _from_csv(raw: bytes, source: str) -> FrfData:
    """An FrfData from a CSV file (see the module docstring)."""
    try:
        lines = raw.decode("utf-8-sig").splitlines()
    except UnicodeDecodeError as exc:
        raise ConfigError("", _Found(f"a file that is not UTF-8 text (byte {exc.start})"),
                          "a UTF-8 text file of comma-separated values", source) from None
    keys: dict[str, tuple[int, float]] = {}
    header_line = 0
    for number, line in enumerate(lines, 1):
        stripped = line.strip()
        if not stripped:
            continue
        if not stripped.startswith("#"):
            header_line = number
            break
        key, colon, text = stripped[1:].partition(":")
        key = key.strip()
        if not colon or key not in CSV_KEYS:
            continue
        if key in keys:
            raise ConfigError(key, text.strip(), f"the value once (it is given on line {keys[key][0]} and "
                              f"line {number})", source)
        try:
            keys[key] = (number, float(text))
        except ValueError:
            raise ConfigError(key, text.strip(), f"a number (in the comment line {number})", source) from None
    if not header_line:
        found = "a file with comment lines only" if any(s.strip() for s in lines) else "an empty file"
        raise ConfigError("", _Found(found), "a header row frequency_hz,re_<out>_<in>,im_<out>_<in>,... "
                          "and a row of numbers per frequency", source)
    rows = csv.reader(lines[header_line - 1:])
    names = [cell.strip() for cell in next(rows)]
    columns = _csv_columns(names, source)
    values = []
    for number, row in enumerate(rows, header_line + 1):
        if not any(cell.strip() for cell in row):
            continue
        if len(row) != len(names):
            raise ConfigError(f"line {number}", _Found(f"{len(row)} cells"),
                              f"{len(names)} cells, one per header column", source)
        values.append([_csv_number(cell, number, name, source)
                       for cell, name in zip(row, names, strict=True)])
    table = np.array(values, dtype=float).reshape(len(values), len(names))
    frf = np.full((len(values), 4, 4), complex(math.nan, math.nan))
    coherence = np.full((len(values), 4, 4), math.nan)
    for (out, inp), parts in columns.items():
        frf[:, out, inp].real = table[:, parts["re"]]
        frf[:, out, inp].imag = table[:, parts["im"]]
        coherence[:, out, inp] = table[:, parts["coh"]] if "coh" in parts else 1.0    # fully coherent
    return _validated(table[:, 0], frf, coherence, *(keys[k][1] if k in keys else None for k in CSV_KEYS),
                      None, {}, source)


def _csv_columns(names: list[str], source: str) -> dict[tuple[int, int], dict[str, int]]:
    """The header row: for each (output, input) pair present, the column of each part."""
    if names[0] != "frequency_hz":
        raise ConfigError("header column 1", names[0], "frequency_hz (the first column of a comma-separated "
                          "header row)", source)
    pairs: dict[tuple[int, int], dict[str, int]] = {}
    seen: dict[str, int] = {}
    for j, name in enumerate(names[1:], 1):
        match = _CSV_COLUMN.fullmatch(name)
        if match is None:
            raise ConfigError(f"header column {j + 1}", name, _CSV_NAMES, source)
        if name in seen:
            raise ConfigError(f"header column {j + 1}", name, f"each column once (it is column "
                              f"{seen[name] + 1} already)", source)
        seen[name] = j
        part, out, inp = match.groups()
        pairs.setdefault((OUTPUTS.index(out), INPUTS.index(inp)), {})[part] = j
    for (out, inp), parts in pairs.items():
        for part in ("re", "im"):
            if part not in parts:
                pair = f"{OUTPUTS[out]}_{INPUTS[inp]}"
                raise ConfigError(f"{part}_{pair}", _Found("missing"), f"a column {part}_{pair} as well: a "
                                  f"pair needs re_{pair} and im_{pair}, the real and imaginary parts", source)
    return pairs


def _csv_number(cell: str, line: int, column: str, source: str) -> float:
    try:
        return float(cell)
    except ValueError:
        raise ConfigError(f"line {line}, column {column}", cell, "a number (nan for a value not measured)",
                          source) from None
