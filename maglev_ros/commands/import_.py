"""``maglev-ros import SPEC.yaml --out BAG``: a DAQ export (CSV, TDMS, HDF5, MATLAB, MDF4) into a
contract bag, channels mapped by an import spec (docs/import.md), or by flags for one file.

Units are converted to SI at the edge (each conversion printed), rates checked per topic, gaps
reported with the row or sample before which they happen, position/speed completed from each
other; the bag appears at BAG only when it is complete.
"""
from __future__ import annotations

from pathlib import Path

from maglev_ros.errors import UserError

NAME = "import"
HELP = "import a DAQ export (CSV, TDMS, HDF5, .mat, MDF4) into a contract bag"
ORDER = 15


def add_arguments(p) -> None:
    p.add_argument("spec", metavar="SPEC_OR_FILE",
                   help="the import spec (.yaml/.yml: metadata, source, channels) or, with "
                        "--metadata and --channel, the DAQ file itself")
    p.add_argument("--out", required=True, metavar="BAG", help="the contract bag to write (MCAP)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing BAG (once the new one is complete)")
    p.add_argument("--json", metavar="FILE", help="also write what was done (maglev-import/1) as JSON")
    simple = p.add_argument_group("without a spec file (one DAQ file)")
    simple.add_argument("--metadata", metavar="FILE", help="the filled metadata template (YAML/JSON)")
    simple.add_argument("--channel", nargs=3, action="append", metavar=("ID", "COLUMN", "UNIT"),
                        help="contract channel ID <- COLUMN of the file, in UNIT (repeat per channel)")
    simple.add_argument("--format", help="csv, tdms, hdf5, mat or mdf (default: from the extension)")
    simple.add_argument("--delimiter", help="CSV field delimiter (default ',' or ';' with --decimal ,)")
    simple.add_argument("--decimal", help="CSV decimal mark, '.' (default) or ','")
    simple.add_argument("--header-rows", type=int, help="CSV lines before the column names row")
    simple.add_argument("--units-row", action="store_true",
                        help="CSV: a units row follows the column names")
    simple.add_argument("--time-column", help="the time column (relative seconds unless --absolute-time)")
    simple.add_argument("--time-unit", help="unit of a relative time column (default s)")
    simple.add_argument("--absolute-time", action="store_true",
                        help="the time column holds epoch seconds or ISO 8601 text")
    simple.add_argument("--rate-hz", type=float, help="sample rate of a file without a time column")
    simple.add_argument("--start", help="ISO 8601 time of the first sample (relative time or --rate-hz)")
    simple.add_argument("--block-s", type=float, help="SensorBlock length [s] (default 0.1)")
    simple.add_argument("--resample", action="store_true",
                        help="interpolate a topic's channels onto one grid when their rates differ")
    simple.add_argument("--position-start-m", type=float,
                        help="position at the first sample, to integrate a speed channel")


_FLAG_ONLY = ("metadata", "channel", "format", "delimiter", "decimal", "header_rows", "time_column",
              "time_unit", "rate_hz", "start", "block_s", "position_start_m")


def _spec_from_flags(args):
    from maglev_ros.daq_import.spec import spec_from_dict
    from maglev_ros.metadata_file import metadata_from_file

    if not args.metadata or not args.channel:
        raise UserError(f"{args.spec}: not a .yaml import spec; to import the file directly give "
                        "--metadata FILE and at least one --channel ID COLUMN UNIT")
    src = {"file": str(Path(args.spec).resolve())}
    for key, val in (("format", args.format), ("delimiter", args.delimiter), ("decimal", args.decimal),
                     ("header_rows", args.header_rows)):
        if val is not None:
            src[key] = val
    time = {}
    if args.time_column is not None:
        time["column"] = int(args.time_column) if args.time_column.isdigit() else args.time_column
    if args.time_unit:
        time["unit"] = args.time_unit
    if args.absolute_time:
        time["absolute"] = True
    if args.rate_hz is not None:
        time["rate_hz"] = args.rate_hz
    if args.start is not None:
        time["start"] = args.start
    if args.units_row:
        src["units_row"] = True
    if time:
        src["time"] = time
    doc = {"source": src, "channels": {}}
    for cid, col, unit in args.channel:
        doc["channels"][cid] = {"column": int(col) if col.isdigit() else col, "unit": unit}
    if args.block_s is not None:
        doc["block_s"] = args.block_s
    if args.resample:
        doc["resample"] = True
    if args.position_start_m is not None:
        doc["position_start_m"] = args.position_start_m
    return spec_from_dict(doc, "command line", Path("."), metadata=metadata_from_file(args.metadata),
                          metadata_origin=args.metadata)


def run(args) -> int:
    from maglev_ros.daq_import import import_to_bag, load_spec
    from maglev_ros.outputs import check_file, write_json

    if args.json:
        check_file(args.json, "--json")
    if Path(args.spec).suffix.lower() in (".yaml", ".yml"):
        given = [f"--{k.replace('_', '-')}" for k in _FLAG_ONLY if getattr(args, k) not in (None, False)]
        given += [f for f, on in (("--resample", args.resample), ("--units-row", args.units_row),
                                  ("--absolute-time", args.absolute_time)) if on]
        if given:
            raise UserError(f"{args.spec}: an import spec says everything itself; "
                            f"{', '.join(given)} belong(s) in the spec")
        spec = load_spec(args.spec)
    else:
        spec = _spec_from_flags(args)
    res = import_to_bag(spec, args.out, overwrite=args.overwrite)
    print("\n".join(res.lines()))
    if args.json:
        write_json(args.json, res.to_dict(), option="--json")
    return 0
