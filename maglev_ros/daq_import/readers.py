"""Columns of a DAQ export, one reader per format, each giving values, a time base and the unit
the file states.

CSV (stdlib ``csv``: quoting, any delimiter; decimal comma), NI TDMS (``nptdms``), HDF5
(``h5py``: a dataset per channel or one 2-D / compound table with column names), MATLAB .mat
(``scipy.io`` for v5; v7.3 is HDF5, read with ``h5py`` and transposed as MATLAB stores it column
major) and ASAM MDF4 (``asammdf``). Problems are one line naming the file and the row (CSV:
the file's line number) or sample index.
"""
from __future__ import annotations

import csv
import datetime
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from maglev_ros.contract import unit_conversion
from maglev_ros.daq_import.spec import SourceSpec, parse_time_text
from maglev_ros.daq_import.timing import Timeline, _snap_rate, analyse, uniform
from maglev_ros.errors import UserError

__all__ = ["Column", "read_columns"]


def _missing(pip_name: str, what: str) -> UserError:
    """One line for a format library that is not installed (a colcon/rosdep install has no key
    for npTDMS and asammdf; pip installs them with maglev_ros)."""
    return UserError(f"reading {what} needs the Python package {pip_name} "
                     f"(pip install {pip_name}; `pip install maglev_ros` brings it)")


# dataset/variable attributes that state a rate or a sample period, and a unit
_RATE_ATTRS = ("sample_rate_hz", "sample_rate", "rate_hz", "fs")
_PERIOD_ATTRS = ("wf_increment", "dt", "sample_period_s")
_UNIT_ATTRS = ("unit", "units", "unit_string")


@dataclass(frozen=True)
class Column:
    """One channel read from a file: values (float64), their time base and the file's unit."""

    values: np.ndarray
    timeline: Timeline
    file_unit: str | None
    label: Callable[[int], str]      # sample index -> "line 12" / "sample 12"
    where: str                       # "run.csv column 'Gap 1'"


def _sample_label(i: int) -> str:
    return f"sample {i}"


def _clean_unit(u: Any) -> str | None:
    if isinstance(u, bytes):
        u = u.decode("utf-8", errors="replace")
    if not isinstance(u, str):
        return None
    u = u.strip().strip("[]()").strip()
    return u or None


def _time_factor(src: SourceSpec) -> float:
    return unit_conversion(src.time.unit)[1]


def _finite(values: np.ndarray, label, where: str) -> np.ndarray:
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        i = int(bad[0])
        raise UserError(f"{where}: {label(i)}: value {values[i]!r} is not a finite number")
    return values


def _epoch_parts(text: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Epoch seconds written as text -> (whole seconds, fraction), parsing whole and fractional
    digits apart (a float64 holds epoch seconds to 0.2 us only); ValueError if not plain digits."""
    parts = np.char.partition(text, ".")
    whole = parts[:, 0].astype(np.int64)
    frac = np.char.add("0.", np.where(parts[:, 2] == "", "0", parts[:, 2])).astype(np.float64)
    return whole, frac


def _numbers_from_numeric(values: np.ndarray, src: SourceSpec, label, where: str) -> Timeline:
    """Time base from a numeric time column (relative in its unit, or absolute epoch seconds)."""
    if np.issubdtype(np.asarray(values).dtype, np.datetime64):
        ns = np.asarray(values).astype("datetime64[ns]").astype(np.int64)
        return analyse(int(ns[0]), (ns - ns[0]) * 1e-9, label, where)
    t = _finite(np.asarray(values, dtype=np.float64), label, where)
    if src.time.absolute:
        base = int(np.floor(t[0]))
        return analyse(base * 1_000_000_000, t - base, label, where)
    return analyse(src.time.start_ns or 0, t * _time_factor(src), label, where)


# ------------------------------------------------------------------------------------ CSV
def _read_csv(src: SourceSpec, columns: Sequence) -> dict:
    o = src.options
    path = src.file
    want = list(columns)
    if src.time.column is not None:
        want.append(src.time.column)
    try:
        fh = open(path, newline="", encoding=o["encoding"])
    except FileNotFoundError:
        raise UserError(f"{src.where}.file: {path} not found") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except LookupError:
        raise UserError(f"{src.where}.encoding: unknown encoding {o['encoding']!r}") from None
    with fh:
        try:
            skip = o["header_rows"]
            for i in range(skip):
                if not fh.readline():
                    raise UserError(f"{path}: ends at line {i + 1}, inside the {skip} header rows "
                                    f"(source header_rows)")
            reader = csv.reader(fh, delimiter=o["delimiter"])

            def line() -> int:
                return skip + reader.line_num

            names = units = None
            if o["names_row"]:
                names = [c.strip() for c in next(reader, [])]
                if not any(names):
                    raise UserError(f"{path}: line {line()}: expected the column names row after "
                                    f"{skip} header rows (source header_rows, names_row)")
                if o["units_row"]:
                    units = [c.strip() for c in next(reader, [])]
            idx = {}
            for c in want:
                if isinstance(c, int):
                    idx[c] = c
                elif names is None:
                    raise UserError(f"{src.where}: column {c!r} named but the file has no names row "
                                    "(names_row: false): give 0-based column indices")
                elif c in names:
                    idx[c] = names.index(c)
                else:
                    shown = ", ".join(repr(n) for n in names[:15]) + (" ..." if len(names) > 15 else "")
                    raise UserError(f"{path}: no column {c!r} in the names row (line {skip + 1}); "
                                    f"columns: {shown}")
            need = max(idx.values()) + 1
            cols = sorted(set(idx.values()))
            pos = {j: k for k, j in enumerate(cols)}
            width = len(names) if names is not None else None
            conv = _CsvChunks(path, o["decimal"], src, idx, pos, columns)
            cells: list[list[str]] = []
            lines: list[int] = []
            for row in reader:
                if not row or all(not c.strip() for c in row):
                    continue
                while len(row) > (width or need) and not row[-1].strip():
                    row = row[:-1]      # a trailing delimiter
                if len(row) < need or (width is not None and len(row) != width):
                    raise UserError(f"{path}: line {line()}: {len(row)} fields, expected "
                                    f"{width or need}" + (" (as in the names row)" if width else ""))
                cells.append([row[j] for j in cols])
                lines.append(line())
                if len(cells) == _CSV_CHUNK_ROWS:
                    conv.add(cells, lines)
                    cells, lines = [], []
            if cells:
                conv.add(cells, lines)
        except csv.Error as exc:
            raise UserError(f"{path}: line {skip + reader.line_num}: not valid CSV ({exc})") from None
        except UnicodeDecodeError as exc:
            raise UserError(f"{path}: not {o['encoding']} text ({exc.reason} at byte {exc.start}); "
                            "set source encoding (e.g. latin-1)") from None
    n = conv.n
    if n < 2:
        raise UserError(f"{path}: {n} data row(s) after the header; at least 2 are needed")
    line_no = np.concatenate(conv.lines)

    def label(i: int) -> str:
        return f"line {int(line_no[i])}"

    where = str(path)          # the time checks name the line; "time" is in their message
    if src.time.column is None:
        tl = uniform(n, src.time.rate_hz, src.time.start_ns or 0)
    elif src.time.absolute and conv.time_kind == "iso":
        ns = np.concatenate(conv.time)
        tl = analyse(int(ns[0]), (ns - ns[0]) * 1e-9, label, where)
    elif src.time.absolute:
        whole = np.concatenate([w for w, _ in conv.time])
        frac = np.concatenate([f for _, f in conv.time])
        base = int(whole[0])
        tl = analyse(base * 1_000_000_000, (whole - base).astype(np.float64) + frac, label, where)
    else:
        tl = analyse(src.time.start_ns or 0, np.concatenate(conv.time) * _time_factor(src), label, where)
    out = {}
    for c in columns:
        unit = _clean_unit(units[idx[c]]) if units is not None and idx[c] < len(units) else None
        out[c] = Column(np.concatenate(conv.values[c]), tl, unit, label, f"{path} column {c!r}")
    return out


_CSV_CHUNK_ROWS = 50_000      # rows held as text at a time: a long export is converted as it is read


class _CsvChunks:
    """Numbers (and the time column) of a CSV converted chunk by chunk, each problem named by
    the file line of its row."""

    def __init__(self, path, decimal: str, src: SourceSpec, idx: dict, pos: dict, columns) -> None:
        self.path, self.decimal, self.src, self.idx, self.pos = path, decimal, src, idx, pos
        self.columns = list(columns)
        self.values: dict = {c: [] for c in self.columns}
        self.time: list = []
        self.lines: list = []
        self.time_kind: str | None = None
        self.n = 0

    def _text(self, table, c) -> np.ndarray:
        s = np.char.strip(table[self.pos[self.idx[c]]])
        return np.char.replace(s, ",", ".") if self.decimal == "," else s

    def _numbers(self, table, line_no, c, what: str) -> np.ndarray:
        s = self._text(table, c)
        try:
            v = s.astype(np.float64)
        except ValueError:
            for i, x in enumerate(s):
                try:
                    float(x)
                except ValueError:
                    raw = str(table[self.pos[self.idx[c]]][i])
                    why = "empty cell" if not raw.strip() else f"{raw!r} is not a number"
                    raise UserError(f"{self.path}: line {int(line_no[i])} column {c!r}: {why} "
                                    f"(expected {what})") from None
            raise
        return _finite(v, lambda i: f"line {int(line_no[i])}", f"{self.path} column {c!r}")

    def add(self, cells: list, lines: list) -> None:
        table = np.array(cells, dtype=str).T
        line_no = np.asarray(lines, dtype=np.int64)
        for c in self.columns:
            self.values[c].append(self._numbers(table, line_no, c, "a number"))
        tc = self.src.time.column
        if tc is not None:
            if not self.src.time.absolute:
                self.time.append(self._numbers(table, line_no, tc, "a time"))
            else:
                s = self._text(table, tc)
                if self.time_kind is None:
                    self.time_kind = "epoch" if all(ch in "0123456789.+-eE" for ch in s[0]) else "iso"
                if self.time_kind == "epoch":
                    try:
                        self.time.append(_epoch_parts(s))
                    except ValueError:     # e.g. 1.7e9: plain floats (0.2 us at epoch scale)
                        v = self._numbers(table, line_no, tc, "epoch seconds")
                        w = np.floor(v).astype(np.int64)
                        self.time.append((w, v - w))
                else:
                    raw = np.char.strip(table[self.pos[self.idx[tc]]])
                    ns = np.empty(raw.size, dtype=np.int64)
                    for i, x in enumerate(raw):
                        try:
                            ns[i] = parse_time_text(str(x))
                        except ValueError:
                            raise UserError(f"{self.path}: line {int(line_no[i])} column {tc!r}: "
                                            f"{str(x)!r} is not ISO 8601 date-time text nor epoch "
                                            "seconds") from None
                    self.time.append(ns)
        self.lines.append(line_no)
        self.n += line_no.size


# ----------------------------------------------------------------------------------- TDMS
def _datetime64_ns(x: Any) -> int | None:
    if x is None:
        return None
    if isinstance(x, np.datetime64):
        return int(x.astype("datetime64[ns]").astype(np.int64))
    if isinstance(x, datetime.datetime):
        if x.tzinfo is None:
            x = x.replace(tzinfo=datetime.timezone.utc)
        d = x - datetime.datetime(1970, 1, 1, tzinfo=datetime.timezone.utc)
        return ((d.days * 86400 + d.seconds) * 1_000_000 + d.microseconds) * 1000
    return None


def _read_tdms(src: SourceSpec, columns: Sequence) -> dict:
    try:
        from nptdms import TdmsFile
    except ImportError:
        raise _missing("npTDMS", "TDMS files") from None
    path = src.file
    if not path.exists():
        raise UserError(f"{src.where}.file: {path} not found")
    try:
        f = TdmsFile.read(path)
    except Exception as exc:  # nptdms raises assorted errors for a damaged file
        raise UserError(f"{path}: not a readable TDMS file ({type(exc).__name__}: "
                        f"{str(exc).splitlines()[0] if str(exc) else ''})") from None
    names = [f"{g.name}/{c.name}" for g in f.groups() for c in g.channels()]

    def find(col):
        if isinstance(col, str):
            for g in f.groups():
                if col.startswith(g.name + "/"):
                    rest = col[len(g.name) + 1:]
                    for c in g.channels():
                        if c.name == rest:
                            return c
        shown = ", ".join(repr(n) for n in names[:15]) + (" ..." if len(names) > 15 else "")
        raise UserError(f"{path}: no channel {col!r} (TDMS channels are named \"group/channel\"): {shown}")

    tcol = None
    if src.time.column is not None:
        tc = find(src.time.column)
        tcol = tc[:]
    out = {}
    for col in columns:
        ch = find(col)
        raw = ch[:]
        where = f"{path} channel {col!r}"
        if not np.issubdtype(raw.dtype, np.number):
            raise UserError(f"{where}: holds {raw.dtype} values, expected numbers")
        values = _finite(np.asarray(raw, dtype=np.float64), _sample_label, where)
        props = ch.properties
        if tcol is not None:
            if len(tcol) != len(values):
                raise UserError(f"{where}: {len(values)} samples but time channel "
                                f"{src.time.column!r} has {len(tcol)}")
            tl = _numbers_from_numeric(tcol, src, _sample_label, f"{path} time channel {src.time.column!r}")
        elif src.time.rate_hz is not None:
            tl = uniform(len(values), src.time.rate_hz, src.time.start_ns or 0)
        elif props.get("wf_increment"):
            start = src.time.start_ns
            if start is None:
                start = _datetime64_ns(props.get("wf_start_time")) or 0
                start += int(round(float(props.get("wf_start_offset", 0.0)) * 1e9))
            tl = uniform(len(values), _snap_rate(1.0 / float(props["wf_increment"])), start,
                         "TDMS wf_increment")
        else:
            raise UserError(f"{where}: no wf_increment property; give source time.column (a time "
                            "channel) or time.rate_hz")
        out[col] = Column(values, tl, _clean_unit(props.get("unit_string")), _sample_label, where)
    return out


# --------------------------------------------------------------------- HDF5 / MATLAB arrays
class _H5Store:
    """Named arrays of an HDF5 file; ``matlab``: a v7.3 .mat (column-major: arrays transposed,
    struct fields as groups, char arrays as uint16, cell arrays as object references)."""

    def __init__(self, path: Path, matlab: bool) -> None:
        try:
            import h5py
        except ImportError:
            raise _missing("h5py", "HDF5 and MATLAB v7.3 files") from None
        self.path = path
        self.matlab = matlab
        try:
            self.f = h5py.File(path, "r")
        except OSError as exc:
            raise UserError(f"{path}: not a readable HDF5 file ({exc})") from None

    def close(self) -> None:
        self.f.close()

    def _key(self, name: str) -> str:
        return name.replace(".", "/") if self.matlab else name

    def has(self, name: str) -> bool:
        import h5py
        return isinstance(self.f.get(self._key(name)), h5py.Dataset)

    def names(self) -> list[str]:
        import h5py
        out = []
        self.f.visititems(lambda n, o: out.append(n) if isinstance(o, h5py.Dataset)
                          and not n.startswith("#refs#") else None)
        return [n.replace("/", ".") if self.matlab else "/" + n for n in out]

    def array(self, name: str) -> np.ndarray:
        ds = self.f[self._key(name)]
        a = ds[()]
        return a.T if self.matlab and a.ndim >= 2 else a

    def attrs(self, name: str) -> dict:
        return dict(self.f[self._key(name)].attrs)

    def strings(self, name: str) -> list[str] | None:
        """A list of names: a string dataset, a MATLAB char matrix or cellstr, or None."""
        import h5py

        ds = self.f[self._key(name)]
        if self.matlab:
            cls = ds.attrs.get("MATLAB_class", b"")
            cls = cls.decode() if isinstance(cls, bytes) else str(cls)
            if cls == "cell":
                refs = ds[()].T.reshape(-1)
                return ["".join(map(chr, np.asarray(self.f[r][()]).reshape(-1))) for r in refs]
            if cls == "char":
                a = np.asarray(ds[()]).T
                return ["".join(map(chr, row)).rstrip() for row in np.atleast_2d(a)]
        a = ds[()]
        if isinstance(a, (bytes, str)):
            a = [a]
        a = np.asarray(a).reshape(-1)
        if a.dtype.kind in "SOU":
            return [x.decode() if isinstance(x, bytes) else str(x) for x in a]
        return None if ds.dtype != h5py.string_dtype() else [str(x) for x in a]


class _MatStore:
    """Named arrays of a MATLAB v4-v7.2 file (scipy.io.loadmat); ``a.b`` names a struct field."""

    def __init__(self, path: Path) -> None:
        from scipy.io import loadmat

        self.path = path
        try:
            self.d = loadmat(path, simplify_cells=True)
        except Exception as exc:  # scipy raises assorted errors for a damaged file
            raise UserError(f"{path}: not a readable MATLAB file ({type(exc).__name__}: "
                            f"{str(exc).splitlines()[0] if str(exc) else ''})") from None

    def close(self) -> None:
        pass

    def _get(self, name: str):
        obj: Any = self.d
        for part in name.split("."):
            if not isinstance(obj, dict) or part not in obj:
                return None
            obj = obj[part]
        return obj

    def has(self, name: str) -> bool:
        return self._get(name) is not None

    def names(self) -> list[str]:
        out = []

        def walk(d, prefix):
            for k, v in d.items():
                if k.startswith("__"):
                    continue
                if isinstance(v, dict):
                    walk(v, f"{prefix}{k}.")
                else:
                    out.append(prefix + k)
        walk(self.d, "")
        return out

    def array(self, name: str) -> np.ndarray:
        return np.asarray(self._get(name))

    def attrs(self, name: str) -> dict:
        return {}

    def strings(self, name: str) -> list[str] | None:
        v = self._get(name)
        if isinstance(v, str):
            return [v]
        a = np.asarray(v, dtype=object).reshape(-1) if isinstance(v, (list, np.ndarray)) else None
        if a is None or not all(isinstance(x, str) for x in a):
            return None
        return [x.rstrip() for x in a]


def _store_for(src: SourceSpec):
    path = src.file
    if not path.exists():
        raise UserError(f"{src.where}.file: {path} not found")
    if src.format == "hdf5":
        return _H5Store(path, matlab=False)
    with open(path, "rb") as fh:
        head = fh.read(1032)
    # v7.3 is HDF5 behind a 512-byte MATLAB header (the HDF5 signature at 0, 512 or 1024)
    if b"MATLAB 7.3" in head[:128] or any(head[o:o + 8] == b"\x89HDF\r\n\x1a\n" for o in (0, 512, 1024)):
        return _H5Store(path, matlab=True)
    return _MatStore(path)


def _attr_str(v: Any) -> Any:
    if isinstance(v, bytes):
        return v.decode("utf-8", errors="replace")
    if isinstance(v, np.ndarray) and v.dtype.kind in "SOU":
        return [_attr_str(x) for x in v.reshape(-1)]
    return v


def _read_arrays(src: SourceSpec, columns: Sequence) -> dict:
    store = _store_for(src)
    path = src.file
    kind = "variable" if src.format == "mat" else "dataset"
    try:
        def missing(name) -> UserError:
            names = store.names()
            shown = ", ".join(repr(n) for n in names[:15]) + (" ..." if len(names) > 15 else "")
            return UserError(f"{path}: no {kind} {name!r}; {kind}s: {shown or 'none'}")

        table = None
        tnames: list[str] = []
        tunits: list | None = None
        dataset = src.options.get("dataset")
        if dataset is not None:
            if not store.has(dataset):
                raise missing(dataset)
            table = store.array(dataset)
            attrs = {k: _attr_str(v) for k, v in store.attrs(dataset).items()}
            if table.dtype.names:                      # compound (e.g. a pandas/pytables table)
                tnames = list(table.dtype.names)
            else:
                cols = src.options.get("columns")
                if isinstance(cols, list):
                    tnames = list(cols)
                elif isinstance(cols, str):
                    if cols in attrs and isinstance(attrs[cols], list):
                        tnames = [str(x) for x in attrs[cols]]
                    elif store.has(cols) and store.strings(cols) is not None:
                        tnames = store.strings(cols)
                    else:
                        raise UserError(f"{src.where}.columns: {cols!r} is neither an attribute of "
                                        f"{dataset!r} nor a {kind} of text in {path}")
                else:
                    for a in ("columns", "column_names", "names"):
                        if isinstance(attrs.get(a), list):
                            tnames = [str(x) for x in attrs[a]]
                            break
                if table.ndim != 2:
                    raise UserError(f"{path}: {kind} {dataset!r} has shape {table.shape}, expected a "
                                    "2-D table (samples x columns)")
                if tnames and table.shape[1] != len(tnames) and table.shape[0] == len(tnames):
                    table = table.T                    # stored channels x samples
                if tnames and table.shape[1] != len(tnames):
                    raise UserError(f"{path}: {kind} {dataset!r} has {table.shape[1]} columns but "
                                    f"{len(tnames)} column names")
            if isinstance(attrs.get("units"), list) and len(attrs["units"]) == len(tnames):
                tunits = [str(u) for u in attrs["units"]]

        def get(name) -> tuple[np.ndarray, str | None, dict]:
            """(values, unit from the file, attrs) of a column: a table column or an array."""
            if table is not None and (isinstance(name, int) or name in tnames):
                j = name if isinstance(name, int) else tnames.index(name)
                if table.dtype.names:
                    if j >= len(tnames):
                        raise UserError(f"{path}: column index {j} but {dataset!r} has {len(tnames)} columns")
                    v = table[tnames[j]]
                else:
                    if j >= table.shape[1]:
                        raise UserError(f"{path}: column index {j} but {dataset!r} has "
                                        f"{table.shape[1]} columns")
                    v = table[:, j]
                return np.asarray(v), (tunits[j] if tunits else None), store.attrs(dataset)
            if isinstance(name, int):
                raise UserError(f"{src.where}: column index {name} needs source dataset (a 2-D table)")
            if not store.has(name):
                if table is not None:
                    raise UserError(f"{path}: no column {name!r} in {dataset!r} (columns: "
                                    f"{', '.join(map(repr, tnames[:15]))}) nor a {kind} of that name")
                raise missing(name)
            a = np.asarray(store.array(name))
            if a.ndim > 1:
                if sum(d > 1 for d in a.shape) > 1:
                    raise UserError(f"{path}: {kind} {name!r} has shape {a.shape}; a channel is one "
                                    "column of samples (for a table give source dataset and columns)")
                a = a.reshape(-1)
            attrs = {k: _attr_str(v) for k, v in store.attrs(name).items()}
            unit = next((attrs[u] for u in _UNIT_ATTRS if isinstance(attrs.get(u), str)), None)
            return a, unit, attrs

        tl_cache: dict = {}
        out = {}
        for col in columns:
            raw, unit, attrs = get(col)
            where = f"{path} {kind} {col!r}"
            if raw.dtype.kind not in "iufb":
                raise UserError(f"{where}: holds {raw.dtype} values, expected numbers")
            values = _finite(raw.astype(np.float64), _sample_label, where)
            if src.time.column is not None:
                if "t" not in tl_cache:
                    tv, _, _ = get(src.time.column)
                    tl_cache["t"] = (len(tv), _numbers_from_numeric(
                        tv.astype(np.float64) if tv.dtype.kind in "iub" else tv, src, _sample_label,
                        f"{path} time {kind} {src.time.column!r}"))
                n_t, tl = tl_cache["t"]
                if n_t != values.size:
                    raise UserError(f"{where}: {values.size} samples but the time {kind} "
                                    f"{src.time.column!r} has {n_t}")
            elif src.time.rate_hz is not None:
                tl = uniform(values.size, src.time.rate_hz, src.time.start_ns or 0)
            else:
                rate = next((float(attrs[a]) for a in _RATE_ATTRS if _is_num(attrs.get(a))), None)
                if rate is None:
                    per = next((float(attrs[a]) for a in _PERIOD_ATTRS if _is_num(attrs.get(a))), None)
                    rate = None if per is None or per <= 0 else _snap_rate(1.0 / per)
                if rate is None or rate <= 0:
                    raise UserError(f"{where}: no time: give source time.column (a time {kind}) or "
                                    f"time.rate_hz (or an attribute {'/'.join(_RATE_ATTRS)})")
                tl = uniform(values.size, rate, src.time.start_ns or 0, f"{kind} attribute")
            out[col] = Column(values, tl, _clean_unit(unit), _sample_label, where)
        return out
    finally:
        store.close()


def _is_num(x: Any) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) and np.isfinite(x)


# ------------------------------------------------------------------------------------ MDF
def _read_mdf(src: SourceSpec, columns: Sequence) -> dict:
    try:
        from asammdf import MDF
    except ImportError:
        raise _missing("asammdf", "MDF files") from None
    path = src.file
    if not path.exists():
        raise UserError(f"{src.where}.file: {path} not found")
    try:
        mdf = MDF(path)
    except Exception as exc:  # asammdf raises assorted errors for a damaged file
        raise UserError(f"{path}: not a readable MDF file ({type(exc).__name__}: "
                        f"{str(exc).splitlines()[0] if str(exc) else ''})") from None
    try:
        start = src.time.start_ns
        if start is None:
            start = _datetime64_ns(mdf.header.start_time) or 0
        out = {}
        for col in columns:
            where = f"{path} signal {col!r}"
            if not isinstance(col, str):
                raise UserError(f"{src.where}: MDF signals are named, got column {col!r}")
            try:
                sig = mdf.get(col, raw=False)
            except Exception as exc:  # MdfException: not found / several of that name
                raise UserError(f"{where}: {str(exc).splitlines()[0] if str(exc) else 'not found'}") from None
            samples = np.asarray(sig.samples)
            if samples.dtype.kind not in "iufb":
                raise UserError(f"{where}: holds {samples.dtype} values, expected numbers")

            def label(i: int) -> str:
                return f"record {i}"
            values = _finite(samples.astype(np.float64), label, where)
            tl = analyse(start, np.asarray(sig.timestamps, dtype=np.float64), label,
                         f"{where} timestamps", origin="MDF timestamps")
            out[col] = Column(values, tl, _clean_unit(sig.unit), label, where)
        return out
    finally:
        mdf.close()


_READERS = {"csv": _read_csv, "tdms": _read_tdms, "hdf5": _read_arrays, "mat": _read_arrays,
            "mdf": _read_mdf}


def read_columns(src: SourceSpec, columns: Sequence) -> dict:
    """{column: Column} for the named columns of one source."""
    return _READERS[src.format](src, list(dict.fromkeys(columns)))
