"""``maglev-ros info BAG [--json]``: what a recording holds and whether it meets the contract.

Prints topics, types, counts, duration, channels with rates and units, the metadata summary
and every contract problem found by a full streaming check. A contract *error* (NaN/inf
samples, malformed blocks, broken metadata) prints the report and then one error line, exit 1;
an unreadable/truncated bag or a missing metadata key is one error line, exit 1.
"""
from __future__ import annotations

import sys

from maglev_ros.bag_reader import BagReader
from maglev_ros.errors import ContractError
from maglev_ros.outputs import json_text

NAME = "info"
HELP = "show topics, channels, rates, units and contract problems of a recording"
ORDER = 10


def add_arguments(p) -> None:
    p.add_argument("bag", metavar="BAG", help="rosbag2 directory, .mcap/.db3 file or ROS1 .bag")
    p.add_argument("--json", action="store_true",
                   help="print one JSON document (strict: a non-finite number is written as null)")
    p.add_argument("--no-check", action="store_true",
                   help="skip the full contract check (only read metadata and first messages)")


def _metadata_summary(md) -> dict | None:
    if md is None:
        return None
    return {
        "schema": md.schema,
        "description": md.description,
        "run_kind": md.run_kind,
        "nominal_speed_mps": md.nominal_speed_mps,
        "spans": [{"id": s.id, "start_m": s.start_m, "length_m": s.length_m} for s in md.spans],
        "sensors": len(md.sensors),
        "magnet_offsets_m": list(md.magnet_offsets_m),
        "has_design": md.design is not None,
    }


def collect(bag: BagReader, check: bool = True) -> dict:
    """The info report of an open bag as a JSON-ready dict."""
    issues = bag.check() if check else list(bag.open_issues)
    topics = []
    for name, info in bag.topics.items():
        d = info.to_dict()
        if name in bag.topic_stats:
            d["stats"] = bag.topic_stats[name]
        if info.is_sensor_block and bag.metadata is not None:
            d["metadata_sensors"] = list(bag.metadata.sensors_on_topic(name))
        topics.append(d)
    stamps = [s for s in bag.topic_stats.values()]
    data_span = None
    if stamps:
        data_span = {"start_s": min(s["first_stamp_s"] for s in stamps),
                     "end_s": max(s["end_s"] for s in stamps)}
        data_span["duration_s"] = data_span["end_s"] - data_span["start_s"]
    n_err = sum(1 for i in issues if i.severity == "error")
    return {
        "path": str(bag.path),
        "storage": bag.storage,
        "message_count": bag.message_count,
        "duration_s": bag.duration_s,
        "start_time_s": bag.start_time_s,
        "data_span": data_span,
        "metadata": _metadata_summary(bag.metadata),
        "topics": topics,
        "checked": check,
        "issues": [i.to_dict() for i in issues],
        "errors": n_err,
        "warnings": len(issues) - n_err,
        "ok": n_err == 0,
    }


def format_text(rep: dict) -> str:
    lines = [f"bag:       {rep['path']}",
             f"storage:   {rep['storage']}, {rep['message_count']} messages, "
             f"{rep['duration_s']:.3f} s of receive time"]
    if rep["data_span"]:
        ds = rep["data_span"]
        lines.append(f"data:      header stamps {ds['start_s']:.6f} .. {ds['end_s']:.6f} s "
                     f"({ds['duration_s']:.3f} s)")
    md = rep["metadata"]
    if md is not None:
        speed = "" if md["nominal_speed_mps"] is None else f" at {md['nominal_speed_mps']:g} m/s"
        lines.append(f"metadata:  {md['schema']}, run {md['run_kind']}{speed}, "
                     f"{len(md['spans'])} span(s), {md['sensors']} sensor(s), "
                     f"{len(md['magnet_offsets_m'])} magnet(s), design block: "
                     f"{'yes' if md['has_design'] else 'no'}")
        if md["description"]:
            lines.append(f"           {md['description']}")
    lines.append("topics:")
    for t in rep["topics"]:
        head = f"  {t['topic']}  {t['type']}  {t['count']} msg"
        if "channels" in t:
            rate = t.get("sample_rate_hz")
            st = t.get("stats")
            if st:
                rates = ", ".join(f"{r:g}" for r in st["sample_rates_hz"])
                head += (f"  {rates} Hz  {st['samples']} samples/channel"
                         f"  {st['end_s'] - st['first_stamp_s']:.3f} s"
                         f"  blocks of {', '.join(str(b) for b in st['block_samples'])}")
            elif rate:
                head += f"  {rate:g} Hz  blocks of {t.get('block_samples')}"
            lines.append(head)
            chans = [f"{c} [{u}]" for c, u in zip(t["channels"], t["units"])]
            for i in range(0, len(chans), 6):
                lines.append("      " + "  ".join(chans[i:i + 6]))
        else:
            lines.append(head)
    if not rep["checked"]:
        lines.append("contract:  not checked (--no-check)")
    elif not rep["issues"]:
        lines.append("contract:  OK, no problems found")
    else:
        lines.append(f"contract:  {rep['errors']} error(s), {rep['warnings']} warning(s)")
        for i in rep["issues"]:
            where = i["topic"] or ""
            if i["channel"]:
                where += f" [{i['channel']}]"
            at = "" if i["time_s"] is None else f" t={i['time_s']:.6f} s"
            lines.append(f"  {i['severity']:7s} {i['kind']:16s} {where}{at}: {i['message']}")
    return "\n".join(lines)


def run(args) -> int:
    with BagReader(args.bag, strict=True) as bag:
        rep = collect(bag, check=not args.no_check)
    if args.json:
        print(json_text(rep, indent=2))      # strict JSON: a NaN/inf value prints as null
    else:
        print(format_text(rep))
    sys.stdout.flush()
    if rep["errors"]:
        first = next(i for i in rep["issues"] if i["severity"] == "error")
        where = (first["topic"] or "") + (f" [{first['channel']}]" if first["channel"] else "")
        raise ContractError(f"{rep['path']}: {rep['errors']} contract error(s); first: "
                            f"{first['kind']} on {where}: {first['message']}")
    return 0
