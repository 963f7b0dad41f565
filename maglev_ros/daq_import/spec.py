"""The import spec: which DAQ file, which of its columns is which contract channel, in what unit.

One YAML file the user writes (docs/import.md)::

    metadata: metadata.yaml          # the filled template, path relative to the spec
    source: {file: run.csv, format: csv, delimiter: ";", decimal: ",", header_rows: 3,
             time: {column: "Time", unit: s, absolute: false, start: "2026-04-12T10:31:00Z"}}
    block_s: 0.1
    channels:
      G3LV: {column: "Acc G3 left", unit: g}
      position_m: {column: "Pos", unit: m, source: {file: position.csv}}

A channel's ``source`` is merged over the top-level one, key by key (a second file with the same
layout: ``{file: position.csv}``; a ``time`` given there replaces the top-level ``time`` whole).
Every key is checked here; a problem is one line naming the spec file and the key.
"""
from __future__ import annotations

import datetime
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from maglev_ros.contract import Metadata, metadata_from_dict
from maglev_ros.errors import UserError
from maglev_ros.metadata_file import json_ready, load_yaml, metadata_from_file

__all__ = ["FORMATS", "EXTENSIONS", "TimeSpec", "SourceSpec", "ChannelSpec", "ImportSpec",
           "load_spec", "spec_from_dict", "parse_time_text", "format_of"]

FORMATS = ("csv", "tdms", "hdf5", "mat", "mdf")
EXTENSIONS = {".csv": "csv", ".txt": "csv", ".tsv": "csv", ".tdms": "tdms", ".h5": "hdf5",
              ".hdf5": "hdf5", ".hdf": "hdf5", ".he5": "hdf5", ".mat": "mat", ".mf4": "mdf",
              ".mdf": "mdf"}
# options each format takes beside file, format and time
_FORMAT_OPTIONS = {
    "csv": ("delimiter", "decimal", "header_rows", "names_row", "units_row", "encoding"),
    "tdms": (),
    "hdf5": ("dataset", "columns"),
    "mat": ("dataset", "columns"),
    "mdf": (),
}
_TOP_KEYS = ("metadata", "source", "block_s", "channels", "resample", "gaps", "position_start_m")
_TIME_KEYS = ("column", "unit", "absolute", "start", "rate_hz")
_CHANNEL_KEYS = ("column", "unit", "source")
GAP_POLICIES = ("keep", "fail")


@dataclass(frozen=True)
class TimeSpec:
    """How a source gives time. ``column``: a time column/channel/dataset (None: the format's own
    time, e.g. TDMS waveform properties or MDF timestamps, or ``rate_hz``); ``absolute``: its
    values are epoch seconds or ISO 8601 text, else seconds (in ``unit``) from ``start_ns``."""

    column: str | int | None = None
    unit: str = "s"
    absolute: bool = False
    start_ns: int | None = None
    rate_hz: float | None = None


@dataclass(frozen=True)
class SourceSpec:
    file: Path
    format: str
    time: TimeSpec
    options: Mapping[str, Any] = field(default_factory=dict)
    where: str = ""     # "spec.yaml: key source" - for error lines

    @property
    def key(self) -> tuple:
        """Identity of the source for caching (file, format, options and time)."""
        return (str(self.file), self.format, repr(sorted(self.options.items())), repr(self.time))


@dataclass(frozen=True)
class ChannelSpec:
    id: str
    column: str | int
    unit: str | None
    source: SourceSpec


@dataclass(frozen=True)
class ImportSpec:
    origin: str                     # the spec file (or "command line")
    metadata: Metadata
    metadata_origin: str
    channels: tuple[ChannelSpec, ...]
    block_s: float = 0.1
    resample: bool = False
    gaps: str = "keep"
    position_start_m: float | None = None


def format_of(path: Path) -> str | None:
    """The format its extension names (None: unknown)."""
    return EXTENSIONS.get(path.suffix.lower())


_ISO_FRACTION = re.compile(r"^(.*T?\d\d:\d\d:\d\d)[.,](\d+)(.*)$")


def parse_time_text(text: str) -> int:
    """ISO 8601 date-time text -> epoch ns (no time zone: UTC). Keeps all fraction digits
    (datetime holds microseconds only); ValueError when it is not ISO 8601."""
    s = text.strip()
    frac_ns = 0
    m = _ISO_FRACTION.match(s)
    if m:
        digits = m.group(2)
        frac_ns = int((digits + "0" * 9)[:9])
        s = m.group(1) + m.group(3)
    if s.endswith(("Z", "z")):
        s = s[:-1] + "+00:00"
    dt = datetime.datetime.fromisoformat(s)
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=datetime.timezone.utc)
    epoch = datetime.datetime(1970, 1, 1, tzinfo=datetime.timezone.utc)
    # the fraction was cut off above, so dt holds whole seconds (exact in a float)
    return int(round((dt - epoch).total_seconds())) * 1_000_000_000 + frac_ns


class _Keys:
    """One-line errors "<origin>: key <path>: <what>"."""

    def __init__(self, origin: str) -> None:
        self.origin = origin

    def fail(self, path: str, what: str) -> UserError:
        return UserError(f"{self.origin}: key {path}: {what}")

    def mapping(self, obj: Any, path: str) -> dict:
        if not isinstance(obj, dict):
            raise self.fail(path, f"expected a mapping, got {type(obj).__name__} {obj!r}")
        return obj

    def only(self, obj: dict, allowed, path: str) -> None:
        for k in obj:
            if k not in allowed:
                where = f"{path}.{k}" if path else str(k)
                raise self.fail(where, f"unknown key (expected one of {', '.join(allowed)})")

    def number(self, v: Any, path: str, positive: bool = False) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.fail(path, f"expected a finite number, got {v!r}")
        if positive and v <= 0:
            raise self.fail(path, f"expected a number > 0, got {v!r}")
        return float(v)

    def boolean(self, v: Any, path: str) -> bool:
        if not isinstance(v, bool):
            raise self.fail(path, f"expected true or false, got {v!r}")
        return v

    def text(self, v: Any, path: str) -> str:
        if not isinstance(v, str) or not v:
            raise self.fail(path, f"expected a non-empty string, got {v!r}")
        return v


def _time_spec(k: _Keys, obj: Any, path: str, fmt: str) -> TimeSpec:
    if obj is None:
        obj = {}
    t = k.mapping(obj, path)
    k.only(t, _TIME_KEYS, path)
    column = t.get("column")
    if column is not None and not (isinstance(column, int) and not isinstance(column, bool) and column >= 0) \
            and not (isinstance(column, str) and column):
        raise k.fail(f"{path}.column", f"expected a column name or a 0-based index, got {column!r}")
    unit = k.text(t.get("unit", "s"), f"{path}.unit")
    from maglev_ros.contract import unit_conversion
    conv = unit_conversion(unit)
    if conv is None or conv[0] != "s":
        raise k.fail(f"{path}.unit", f"expected a time unit (s, ms), got {unit!r}")
    absolute = k.boolean(t.get("absolute", False), f"{path}.absolute")
    start = t.get("start")
    start_ns = None
    if start is not None:
        if isinstance(start, datetime.datetime):   # YAML reads an unquoted ISO time as datetime
            start = start.isoformat()
        if isinstance(start, str):
            try:
                start_ns = parse_time_text(start)
            except ValueError:
                raise k.fail(f"{path}.start", f"expected ISO 8601 date-time text "
                             f"(e.g. 2026-04-12T10:31:00Z) or epoch seconds, got {start!r}") from None
        else:
            start_ns = int(round(k.number(start, f"{path}.start") * 1e9))
        if absolute:
            raise k.fail(f"{path}.start", "given with absolute: true (absolute times carry their own start)")
    rate = t.get("rate_hz")
    rate_hz = None if rate is None else k.number(rate, f"{path}.rate_hz", positive=True)
    if column is not None and rate_hz is not None:
        raise k.fail(f"{path}.rate_hz", "given with a time column (give one: the column or the rate)")
    if absolute and column is None:
        raise k.fail(f"{path}.absolute", "true needs time.column (the column of absolute times)")
    if fmt == "mdf" and (column is not None or rate_hz is not None or absolute):
        raise k.fail(path, "MDF signals carry their own timestamps: only time.start may be given")
    if column is None and rate_hz is None and fmt == "csv":
        raise k.fail(f"{path}", "a CSV needs time.column (its time column) or time.rate_hz "
                     "(the sample rate of a file without one)")
    return TimeSpec(column=column, unit=unit, absolute=absolute, start_ns=start_ns, rate_hz=rate_hz)


def _source_spec(k: _Keys, obj: Any, path: str, base_dir: Path) -> SourceSpec:
    src = k.mapping(obj, path)
    allowed = ("file", "format", "time") + tuple(sorted({o for v in _FORMAT_OPTIONS.values() for o in v}))
    k.only(src, allowed, path)
    file = k.text(src.get("file"), f"{path}.file") if "file" in src else None
    if file is None:
        raise k.fail(f"{path}.file", "missing (the DAQ export to read)")
    fpath = Path(file)
    if not fpath.is_absolute():
        fpath = base_dir / fpath
    fmt = src.get("format")
    if fmt is None:
        fmt = format_of(fpath)
        if fmt is None:
            raise k.fail(f"{path}.format", f"missing and the extension of {file!r} names no format "
                         f"(state one of {', '.join(FORMATS)})")
    elif fmt not in FORMATS:
        raise k.fail(f"{path}.format", f"expected one of {', '.join(FORMATS)}, got {fmt!r}")
    opts = {}
    for o in allowed[3:]:
        if o in src:
            if o not in _FORMAT_OPTIONS[fmt]:
                raise k.fail(f"{path}.{o}", f"not an option of format {fmt} "
                             f"(its options: {', '.join(_FORMAT_OPTIONS[fmt]) or 'none'})")
            opts[o] = src[o]
    if fmt == "csv":
        decimal = opts.get("decimal", ".")
        if decimal not in (".", ","):
            raise k.fail(f"{path}.decimal", f"expected '.' or ',', got {decimal!r}")
        delim = opts.get("delimiter", ";" if decimal == "," else ",")
        if delim in ("\\t", "tab"):
            delim = "\t"
        if not isinstance(delim, str) or len(delim) != 1:
            raise k.fail(f"{path}.delimiter", f"expected one character (e.g. ',', ';', tab), got {delim!r}")
        if delim == decimal:
            raise k.fail(f"{path}.delimiter", f"{delim!r} is also the decimal mark")
        hr = opts.get("header_rows", 0)
        if isinstance(hr, bool) or not isinstance(hr, int) or hr < 0:
            raise k.fail(f"{path}.header_rows", f"expected the number of lines before the names row "
                         f"(an integer >= 0), got {hr!r}")
        names_row = k.boolean(opts.get("names_row", True), f"{path}.names_row")
        units_row = k.boolean(opts.get("units_row", False), f"{path}.units_row")
        if units_row and not names_row:
            raise k.fail(f"{path}.units_row", "true needs names_row: true (units follow the names)")
        enc = k.text(opts.get("encoding", "utf-8-sig"), f"{path}.encoding")
        opts = {"delimiter": delim, "decimal": decimal, "header_rows": hr, "names_row": names_row,
                "units_row": units_row, "encoding": enc}
    if fmt in ("hdf5", "mat"):
        if "dataset" in opts:
            k.text(opts["dataset"], f"{path}.dataset")
        cols = opts.get("columns")
        if cols is not None and not (isinstance(cols, str) and cols) and not (
                isinstance(cols, list) and cols and all(isinstance(c, str) and c for c in cols)):
            raise k.fail(f"{path}.columns", "expected a list of column names or the name of the "
                         f"dataset/variable/attribute holding them, got {cols!r}")
        if cols is not None and "dataset" not in opts:
            raise k.fail(f"{path}.columns", "given without dataset (the 2-D table they name)")
    time = _time_spec(k, src.get("time"), f"{path}.time", fmt)
    return SourceSpec(file=fpath, format=fmt, time=time, options=opts, where=f"{k.origin}: key {path}")


def _merge_source(base: Any, over: Any) -> dict:
    out = dict(base) if isinstance(base, dict) else {}
    out.update(over)       # keys replaced whole: a time given here is this file's whole time
    if "file" in over and "format" not in over and isinstance(base, dict) and "format" in base:
        # a second file of another kind must not inherit the first one's format
        if format_of(Path(str(over["file"]))) not in (None, base["format"]):
            out.pop("format")
    return out


def spec_from_dict(doc: Any, origin: str, base_dir: Path, metadata: Metadata | None = None,
                   metadata_origin: str | None = None) -> ImportSpec:
    """Check an import spec document and resolve it (files relative to ``base_dir``).

    ``metadata``: already loaded metadata (flags); else the spec's ``metadata`` key is read."""
    k = _Keys(origin)
    if doc is None:
        raise UserError(f"{origin}: the import spec is empty (see docs/import.md)")
    d = k.mapping(doc, "(top level)")
    k.only(d, _TOP_KEYS, "")
    md_origin = metadata_origin or origin
    if metadata is None:
        if "metadata" not in d:
            raise k.fail("metadata", "missing (the metadata file: `maglev-ros metadata init`, filled in)")
        m = d["metadata"]
        if isinstance(m, str) and m:
            mp = Path(m) if Path(m).is_absolute() else base_dir / m
            metadata = metadata_from_file(mp)
            md_origin = str(mp)
        elif isinstance(m, dict):
            metadata = metadata_from_dict(json_ready(m, f"{origin} (metadata)"), f"{origin} (metadata)")
            md_origin = f"{origin} (metadata)"
        else:
            raise k.fail("metadata", f"expected the path of the metadata file or the metadata itself, got {m!r}")
    if "source" not in d:
        raise k.fail("source", "missing (the DAQ export: {file: ..., format: ..., time: {...}})")
    base_src = k.mapping(d["source"], "source")
    default = _source_spec(k, base_src, "source", base_dir)
    block_s = k.number(d.get("block_s", 0.1), "block_s", positive=True)
    if not 0.001 <= block_s <= 10.0:
        raise k.fail("block_s", f"expected a SensorBlock length of 0.001-10 s (typically 0.05-0.2), got {block_s!r}")
    resample = k.boolean(d.get("resample", False), "resample")
    gaps = d.get("gaps", "keep")
    if gaps not in GAP_POLICIES:
        raise k.fail("gaps", f"expected one of {', '.join(GAP_POLICIES)}, got {gaps!r}")
    pos0 = d.get("position_start_m")
    pos0 = None if pos0 is None else k.number(pos0, "position_start_m")
    if "channels" not in d:
        raise k.fail("channels", "missing (contract channel id -> {column: ..., unit: ...})")
    chans = k.mapping(d["channels"], "channels")
    if not chans:
        raise k.fail("channels", "empty (map at least one contract channel to a column)")
    sensors = metadata.sensors
    out = []
    for cid, entry in chans.items():
        p = f"channels.{cid}"
        if not isinstance(cid, str):
            raise k.fail(p, f"expected a channel id (text), got {cid!r}")
        if cid not in sensors:
            raise k.fail(p, f"not a sensor of the metadata {md_origin} (its sensors: "
                         f"{', '.join(sensors) or 'none'})")
        if isinstance(entry, (str, int)) and not isinstance(entry, bool):
            entry = {"column": entry}
        e = k.mapping(entry, p)
        k.only(e, _CHANNEL_KEYS, p)
        col = e.get("column")
        if col is None:
            raise k.fail(f"{p}.column", "missing (the column, channel, dataset or signal name in the file)")
        if isinstance(col, bool) or not ((isinstance(col, int) and col >= 0) or (isinstance(col, str) and col)):
            raise k.fail(f"{p}.column", f"expected a name or a 0-based column index, got {col!r}")
        unit = e.get("unit")
        if unit is not None:
            unit = k.text(unit, f"{p}.unit")
        src = default
        if "source" in e:
            over = k.mapping(e["source"], f"{p}.source")
            src = _source_spec(k, _merge_source(base_src, over), f"{p}.source", base_dir)
        out.append(ChannelSpec(id=cid, column=col, unit=unit, source=src))
    return ImportSpec(origin=origin, metadata=metadata, metadata_origin=md_origin, channels=tuple(out),
                      block_s=block_s, resample=resample, gaps=gaps, position_start_m=pos0)


def load_spec(path: str | Path) -> ImportSpec:
    """Read and check an import spec YAML file (paths in it relative to its directory)."""
    path = Path(path)
    doc = load_yaml(path, "import spec")
    return spec_from_dict(doc, str(path), path.parent)
