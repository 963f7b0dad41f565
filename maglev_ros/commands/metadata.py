"""``maglev-ros metadata init|check``: the recording metadata a person writes for an import.

``init [--out FILE]`` writes the commented template of the contract's metadata (line, spans,
sensors, vehicle, run, optional design block) with example values of a plausible line;
``check FILE`` validates a filled one with the contract's own validation and prints one line
naming the key and what was expected on a problem (exit 1), warnings otherwise.
"""
from __future__ import annotations

import sys

NAME = "metadata"
HELP = "write the metadata template (init) or check a filled metadata file (check)"
ORDER = 16


def add_arguments(p) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    pi = sub.add_parser("init", help="write the commented metadata template")
    pi.add_argument("--out", default="metadata.yaml", metavar="FILE",
                    help="where to write it (default metadata.yaml; '-' prints it)")
    pi.add_argument("--overwrite", action="store_true", help="replace an existing FILE")
    pc = sub.add_parser("check", help="validate a metadata file (YAML or JSON) against the contract")
    pc.add_argument("file", metavar="FILE")


def run(args) -> int:
    from pathlib import Path

    from maglev_ros.errors import UserError
    from maglev_ros.metadata_file import check_metadata_file, template_text
    from maglev_ros.outputs import write_text

    if args.action == "init":
        text = template_text()
        if args.out == "-":
            sys.stdout.write(text)
            return 0
        out = Path(args.out)
        if out.exists() and not args.overwrite:
            raise UserError(f"{out}: already exists; refusing to overwrite (pass --overwrite)")
        write_text(out, text, option="--out")
        print(f"wrote {out}: fill in your line, vehicle and sensors, then "
              f"`maglev-ros metadata check {out}`")
        return 0
    md, warnings = check_metadata_file(args.file)
    for w in warnings:
        print(f"warning: {w.message}")
    print(f"{args.file}: OK ({md.schema}, run {md.run_kind}, {len(md.spans)} span(s), "
          f"{len(md.sensors)} sensor(s), {len(md.magnet_offsets_m)} magnet(s), "
          f"design block: {'yes' if md.design is not None else 'no'})")
    return 0
