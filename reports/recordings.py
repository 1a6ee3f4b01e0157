"""Telemetry recordings exported for the lab's tools: MDF4 (asammdf), HDF5 (h5py), MATLAB v7.3
(HDF5 that MATLAB's ``load`` reads), MATLAB v5 and CSV.

Every export streams: the recording is read in chunks of rows into one reused buffer and
written chunk by chunk, so a recording is never held in memory twice (MATLAB v5, which stores
whole variables, takes a few columns per pass over the file instead). Every export carries the
unit of each column, the sample rate, the gain table's SHA-256, the recording mode, and the
labels of the coded columns (state, fault: {code: label}) and of the bits of the bit fields
(flags), all taken from the recording's header (``describe``): as channel units and
value-to-text / bit-field-text conversions and header properties in MDF4, as attributes in
HDF5, as variables in MATLAB files and as ``#`` comment lines above the CSV table.

asammdf and h5py are the ``recordings`` extra; a format whose package is missing is refused in
one line naming it.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from beamctl.common.extras import require
from beamctl.rt.controller import code_labels, column_unit, flag_labels
from beamctl.rt.telemetry import TelemetryError, TelemetryReader

FORMATS = {"mdf": ".mf4", "h5": ".h5", "mat73": ".mat", "mat": ".mat", "csv": ".csv"}
EXTRA = "recordings"
CHUNK_BYTES = 2 << 20              # rows read per chunk: about 2 MB of them
MAT5_COLUMNS_BYTES = 64 << 20      # MATLAB v5: columns gathered per pass over the file
MAT5_VARIABLE_BYTES = 2 ** 31      # MATLAB v5 stores no variable larger than 2 GB
# variables of a MATLAB file besides the columns
MAT_VARIABLES = ("columns", "units", "labels", "sample_rate_hz", "gain_table_sha256", "recording",
                 "meta_json")


@dataclass(frozen=True)
class Description:
    """What a recording says of itself, for every export format."""

    source: str
    columns: tuple[str, ...]
    units: dict[str, str]                      # every column; "" where it has none
    labels: dict[str, dict[int, str]]          # coded columns: {column: {code: label}}
    bits: dict[str, dict[int, str]]            # bit-field columns: {column: {bit: label}}
    sample_rate_hz: float | None
    gain_table_sha256: str
    recording: dict[str, Any]                  # the mode and its settings
    created: str
    meta: dict[str, Any]

    def properties(self) -> dict[str, Any]:
        """The recording's facts as flat name: value pairs (numbers and text)."""
        out: dict[str, Any] = {"source": self.source, "created": self.created,
                               "sample_rate_hz": float("nan") if self.sample_rate_hz is None
                               else self.sample_rate_hz,
                               "gain_table_sha256": self.gain_table_sha256,
                               "recording_mode": self.recording["mode"]}
        out.update({k: v for k, v in self.recording.items() if k != "mode"})
        return out

    def coded(self) -> dict[str, tuple[str, dict[int, str]]]:
        """Every labelled column: {column: ("codes" or "bits", {value: label})}."""
        return {**{c: ("codes", t) for c, t in self.labels.items()},
                **{c: ("bits", t) for c, t in self.bits.items()}}


def _int_keys(table: dict) -> dict[str, dict[int, str]]:
    return {column: {int(k): str(v) for k, v in codes.items()} for column, codes in table.items()}


def describe(header: dict, source: str = "") -> Description:
    """The description of a recording from its header. A recording written before its header
    carried units and labels gets those of the controller's record for the columns it has; one
    without a sample rate has none (``sample_rate_hz`` None)."""
    columns = tuple(header["columns"])
    units = {c: column_unit(c) for c in columns}
    units.update({c: str(u) for c, u in header.get("units", {}).items() if c in units})
    labels = _int_keys(header["labels"]) if "labels" in header else code_labels()
    bits = _int_keys(header["bits"]) if "bits" in header else flag_labels()
    meta = header.get("meta", {})
    rate = header.get("sample_rate_hz")
    return Description(
        source=source, columns=columns, units=units,
        labels={c: t for c, t in labels.items() if c in columns},
        bits={c: t for c, t in bits.items() if c in columns},
        sample_rate_hz=None if rate is None else float(rate),
        gain_table_sha256=str(meta.get("gain_table_sha256", "")),
        recording=dict(header.get("recording", {"mode": "full"})), created=str(header.get("created", "")),
        meta=meta)


def export(source: str | Path, out: str | Path, fmt: str, *, chunk_rows: int | None = None) -> int:
    """Write the telemetry file ``source`` to ``out`` in format ``fmt`` (one of ``FORMATS``),
    ``chunk_rows`` rows at a time (default: about 2 MB of them); return the rows written. The
    complete rows are exported (``TelemetryReader``: a last row cut off mid-write is not)."""
    check_format(fmt)
    with TelemetryReader(source) as reader:
        description = describe(reader.header, Path(source).name)
        rows = chunk_rows or max(1, CHUNK_BYTES // reader.row_bytes)
        WRITERS[fmt](reader, description, Path(out), rows)
        return reader.rows


def check_format(fmt: str) -> None:
    """``fmt`` is a format this installation can write (its package is installed)."""
    if fmt not in WRITERS:
        raise ValueError(f"unknown export format {fmt!r}: expected one of {', '.join(FORMATS)}")
    module = {"mdf": "asammdf", "h5": "h5py", "mat73": "h5py"}.get(fmt)
    if module:
        require(module, EXTRA, f"export to {fmt}")


# -- CSV -----------------------------------------------------------------------------------------

def _write_csv(reader: TelemetryReader, d: Description, out: Path, chunk_rows: int) -> None:
    """``# name: value`` lines (the properties, then units, labels and bits as JSON), the row of
    column names, the rows (10 significant digits; times to the nanosecond, so that an hour's
    recording keeps every sample's own time stamp)."""
    with open(out, "w", newline="") as fh:
        for key, value in d.properties().items():
            fh.write(f"# {key}: {value}\n")
        fh.write(f"# units: {json.dumps(d.units)}\n# labels: {json.dumps(d.labels)}\n"
                 f"# bits: {json.dumps(d.bits)}\n")
        fh.write(",".join(d.columns) + "\n")
        fmt = ["%.9f" if name.startswith("time") else "%.10g" for name in d.columns]
        for chunk in reader.chunks(chunk_rows):
            np.savetxt(fh, chunk, delimiter=",", fmt=fmt)


# -- MDF4 ----------------------------------------------------------------------------------------

def _mdf_conversion(kind: str, table: dict[int, str]) -> dict[str, Any]:
    """asammdf's dictionary of a value-to-text conversion (codes) or a bit-field text conversion
    (bits: each set bit's label, joined with |)."""
    conversion: dict[str, Any] = {}
    for i, (value, label) in enumerate(sorted(table.items())):
        if kind == "codes":
            conversion[f"val_{i}"] = value
            conversion[f"text_{i}"] = label
        else:
            conversion[f"mask_{i}"] = value
            conversion[f"text_{i}"] = {"val_0": value, "text_0": label, "default_addr": ""}
    if kind == "codes":
        conversion["default_addr"] = "unknown code"
    return conversion


def _mdf_header_comment(d: Description) -> str:
    from xml.sax.saxutils import escape, quoteattr

    properties = "".join(f"<e name={quoteattr(k)}>{escape(str(v))}</e>" for k, v in d.properties().items())
    return (f"<HDcomment><TX>beamctl telemetry {escape(d.source)}</TX>"
            f"<common_properties>{properties}</common_properties></HDcomment>")


MDF_COMPRESSION = 1                # deflate, which every MDF4 reader has


def _write_mdf(reader: TelemetryReader, d: Description, out: Path, chunk_rows: int) -> None:
    """One channel group: the master channel ``time`` (the recording's ``time_s``; without one,
    the row's index over the sample rate) and a channel per other column, coded columns as
    integers with their conversions. asammdf keeps the samples in a temporary file next to
    ``out`` until it writes the file."""
    asammdf = require("asammdf", EXTRA, "export to mdf")
    coded = d.coded()
    columns = [c for c in d.columns if c != "time_s"]
    index = [d.columns.index(c) for c in columns]
    time_index = d.columns.index("time_s") if "time_s" in d.columns else None
    period = 1.0 / d.sample_rate_hz if d.sample_rate_hz else 1.0
    mdf = asammdf.MDF(version="4.10", temporary_folder=str(out.parent))
    try:
        mdf.header.comment = _mdf_header_comment(d)
        first = 0
        for chunk in _chunks_or_empty(reader, chunk_rows):
            times = (chunk[:, time_index].copy() if time_index is not None
                     else (first + np.arange(len(chunk))) * period)
            values = [chunk[:, i].astype(np.int64) if c in coded else chunk[:, i].copy()
                      for c, i in zip(columns, index, strict=True)]
            if first == 0:
                mdf.append([asammdf.Signal(v, times, name=c, unit=d.units[c],
                                           conversion=_mdf_conversion(*coded[c]) if c in coded else None)
                            for c, v in zip(columns, values, strict=True)],
                           acq_name="beamctl telemetry", comment=f"{d.source} ({d.recording['mode']})")
            else:
                mdf.extend(0, [(times, None), *((v, None) for v in values)])
            first += len(chunk)
        with open(out, "wb") as fh:
            mdf.save(fh, overwrite=True, compression=MDF_COMPRESSION)
    finally:
        mdf.close()


def _chunks_or_empty(reader: TelemetryReader, chunk_rows: int) -> Iterator[np.ndarray]:
    """The reader's chunks, or one empty chunk for a recording without rows."""
    if reader.rows == 0:
        yield np.empty((0, len(reader.columns)))
    else:
        yield from reader.chunks(chunk_rows)


# -- HDF5 ----------------------------------------------------------------------------------------

# HDF5 chunks are the rows of one read chunk, so that every write fills whole chunks; with no
# chunk cache (rdcc_nbytes 0) HDF5 compresses and writes each at once instead of keeping them
H5_COMPRESSION = {"compression": "gzip", "compression_opts": 1, "shuffle": True}
H5_NO_CACHE = {"rdcc_nbytes": 0}


def _stream_columns(reader: TelemetryReader, datasets: list, chunk_rows: int,
                    write: Callable[[Any, int, np.ndarray], None]) -> None:
    position = 0
    for chunk in reader.chunks(chunk_rows):
        for i, dataset in enumerate(datasets):
            write(dataset, position, chunk[:, i])
        position += len(chunk)


def _write_h5(reader: TelemetryReader, d: Description, out: Path, chunk_rows: int) -> None:
    """A dataset per column (float64, n) with a ``unit`` attribute, and for a coded column the
    attributes ``codes`` and ``labels`` (for a bit field ``bits`` and ``labels``); the
    properties and the run's metadata (``meta_json``) as attributes of the file."""
    h5py = require("h5py", EXTRA, "export to h5")
    n = reader.rows
    coded = d.coded()
    with h5py.File(out, "w", **H5_NO_CACHE) as f:
        for key, value in d.properties().items():
            f.attrs[key] = value
        f.attrs["columns"] = list(d.columns)
        f.attrs["meta_json"] = json.dumps(d.meta)
        datasets = []
        for c in d.columns:
            ds = f.create_dataset(c, shape=(n,), dtype="<f8",
                                  **({"chunks": (min(n, chunk_rows),), **H5_COMPRESSION} if n else {}))
            ds.attrs["unit"] = d.units[c]
            if c in coded:
                kind, table = coded[c]
                ds.attrs[kind] = np.array(sorted(table), dtype=np.int64)
                ds.attrs["labels"] = [table[k] for k in sorted(table)]
            datasets.append(ds)

        def write(ds, position: int, values: np.ndarray) -> None:
            ds[position:position + len(values)] = values

        _stream_columns(reader, datasets, chunk_rows, write)


# -- MATLAB --------------------------------------------------------------------------------------
# Both MATLAB formats hold the same variables: each column as an n x 1 double; ``columns`` (a
# char matrix, one name a row); ``units`` (a struct, a field per column); ``labels`` (a struct, a
# field per coded or bit-field column, each a struct of ``kind`` 'codes' or 'bits', ``values``
# and ``names``, a char matrix, one label a row); ``sample_rate_hz``; ``gain_table_sha256``;
# ``recording`` (a struct: mode and its settings); ``meta_json``.

def _char_matrix(texts: list[str]) -> np.ndarray:
    width = max((len(t) for t in texts), default=0)
    return np.array([t.ljust(width) for t in texts]) if width else np.zeros((len(texts), 0), dtype="<U1")


def _mat_metadata(d: Description) -> dict[str, Any]:
    """The variables besides the columns, as nested dicts of text and numbers."""
    labels = {c: {"kind": kind, "values": np.array(sorted(t), dtype=float).reshape(1, -1),
                  "names": _char_matrix([t[k] for k in sorted(t)])} for c, (kind, t) in d.coded().items()}
    return {"columns": _char_matrix(list(d.columns)), "units": {c: d.units[c] for c in d.columns},
            "labels": labels, "sample_rate_hz": d.properties()["sample_rate_hz"],
            "gain_table_sha256": d.gain_table_sha256, "recording": dict(d.recording),
            "meta_json": json.dumps(d.meta)}


def _column_groups(n_rows: int, n_columns: int) -> Iterator[range]:
    per_pass = max(1, MAT5_COLUMNS_BYTES // max(1, 8 * n_rows))
    for start in range(0, n_columns, per_pass):
        yield range(start, min(start + per_pass, n_columns))


def _write_mat(reader: TelemetryReader, d: Description, out: Path, chunk_rows: int) -> None:
    """MATLAB v5 (scipy): variables appended to the file one after the other, the columns a few
    at a time, each gathered in one pass over the recording."""
    import scipy.io

    n = reader.rows
    if 8 * n >= MAT5_VARIABLE_BYTES:
        raise TelemetryError(f"{reader.path}: {n} rows make columns of {8 * n / 2 ** 30:.1f} GiB, more than "
                             f"MATLAB v5 holds in a variable (2 GiB): export with --to mat73")
    _check_mat_names(reader, d)
    with open(out, "wb") as fh:
        for group in _column_groups(n, len(d.columns)):
            columns = {d.columns[i]: np.empty((n, 1)) for i in group}
            position = 0
            for chunk in reader.chunks(chunk_rows):
                for i in group:
                    columns[d.columns[i]][position:position + len(chunk), 0] = chunk[:, i]
                position += len(chunk)
            scipy.io.savemat(fh, columns, do_compression=True)
            del columns
        scipy.io.savemat(fh, _mat_metadata(d), do_compression=True)


def _check_mat_names(reader: TelemetryReader, d: Description) -> None:
    clash = sorted(set(d.columns) & set(MAT_VARIABLES))
    if clash:
        raise TelemetryError(f"{reader.path}: its column {clash[0]!r} has the name of a variable the MATLAB "
                             f"export adds ({', '.join(MAT_VARIABLES)}): export with --to h5 or mdf")


MAT73_HEADER_TEXT = "MATLAB 7.3 MAT-file, Platform: {platform}, Created on: {date} HDF5 schema 1.00 ."


def mat73_header(date: str | None = None) -> bytes:
    """The first 128 bytes of a MATLAB v7.3 file, in the HDF5 user block: 116 bytes of text,
    8 bytes of subsystem offset (unused), the version 0x0200 and the endian indicator 'IM'."""
    text = MAT73_HEADER_TEXT.format(platform="GLNXA64", date=date or time.strftime("%a %b %d %H:%M:%S %Y"))
    return text.ljust(116).encode("ascii")[:116] + b" " * 8 + np.uint16(0x0200).tobytes() + b"IM"


def _h5_class(obj, matlab_class: str) -> None:
    obj.attrs.create("MATLAB_class", np.bytes_(matlab_class))


def _h5_char(group, name: str, text: np.ndarray | str) -> None:
    """A MATLAB char array (m x L: HDF5 [L x m] of UTF-16 code units); empty: MATLAB's empty
    marker."""
    matrix = _char_matrix([text]) if isinstance(text, str) else text
    if matrix.size == 0:
        ds = group.create_dataset(name, data=np.array(matrix.shape, dtype=np.uint64))
        _h5_class(ds, "char")
        ds.attrs.create("MATLAB_empty", np.uint32(1))
        return
    codes = np.array([[ord(ch) for ch in row] for row in matrix.tolist()], dtype=np.uint16)
    ds = group.create_dataset(name, data=codes.T)
    _h5_class(ds, "char")
    ds.attrs.create("MATLAB_int_decode", np.int32(2))


def _h5_value(h5py, group, name: str, value: Any) -> None:
    """A MATLAB variable or struct field from text, a number, an array or a dict (struct)."""
    if isinstance(value, dict):
        sub = group.create_group(name)
        _h5_class(sub, "struct")
        fields = np.empty(len(value), dtype=object)        # MATLAB's field names: strings of 1-byte chars
        for i, key in enumerate(value):
            fields[i] = np.frombuffer(key.encode("ascii"), dtype="S1")
        sub.attrs.create("MATLAB_fields", fields, dtype=h5py.vlen_dtype(np.dtype("S1")))
        for key, item in value.items():
            _h5_value(h5py, sub, key, item)
    elif isinstance(value, str) or (isinstance(value, np.ndarray) and value.dtype.kind == "U"):
        _h5_char(group, name, value)
    else:
        array = np.atleast_2d(np.asarray(value, dtype=float))
        ds = group.create_dataset(name, data=array.T)
        _h5_class(ds, "double")


def _write_mat73(reader: TelemetryReader, d: Description, out: Path, chunk_rows: int) -> None:
    """MATLAB v7.3: HDF5 (readable by HDF5 1.8, as MATLAB writes it) behind a 512-byte user block
    that holds MATLAB's file header; each variable carries its MATLAB_class."""
    h5py = require("h5py", EXTRA, "export to mat73")
    _check_mat_names(reader, d)
    n = reader.rows
    with h5py.File(out, "w", userblock_size=512, libver=("earliest", "v108"), **H5_NO_CACHE) as f:
        datasets = []
        for c in d.columns:
            if n:
                ds = f.create_dataset(c, shape=(1, n), dtype="<f8", chunks=(1, min(n, chunk_rows)),
                                      **H5_COMPRESSION)
                _h5_class(ds, "double")
                datasets.append(ds)
            else:
                ds = f.create_dataset(c, data=np.array([0, 1], dtype=np.uint64))
                _h5_class(ds, "double")
                ds.attrs.create("MATLAB_empty", np.uint32(1))
        for name, value in _mat_metadata(d).items():
            _h5_value(h5py, f, name, value)

        def write(ds, position: int, values: np.ndarray) -> None:
            ds[0, position:position + len(values)] = values

        _stream_columns(reader, datasets, chunk_rows, write)
    with open(out, "r+b") as fh:
        fh.write(mat73_header())


WRITERS: dict[str, Callable[[TelemetryReader, Description, Path, int], None]] = {
    "mdf": _write_mdf, "h5": _write_h5, "mat73": _write_mat73, "mat": _write_mat, "csv": _write_csv}
