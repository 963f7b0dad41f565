#!/usr/bin/env python3
"""Regenerate the sample bags from the built-in scenarios (reproducible: fixed seeds).

    .venv/bin/python bags/make_sample_bags.py [--out-dir bags]

- bags/paper_pass     ``paper-field`` scenario, seed 1: one pass at 25 km/h over span S3 of a
                      5-span line, 10 vertical guideway accelerations + midspan displacement at
                      2 kHz, 4 magnet accelerations and gaps at 2 kHz, position/speed at 200 Hz,
                      2 s lead-in, 6 s free decay (~12.7 s).
- bags/paper_pass2    ``paper-field`` scenario, seed 3, 30 km/h: the held-out pass for
                      ``maglev-ros diagnose`` (another irregularity stretch, another speed).
- bags/paper_ambient  ``paper-ambient`` scenario: 120 s of ambient vibration, the same 10 guideway
                      accelerations at 500 Hz.
The two passes conceal ONE physical effect that the nominal twin lacks (which one: see the
``effects`` of <bag>.truth.json, or maglev_ros/config/scenarios/paper-field.yaml; the bags'
metadata does not say). Each bag gets ``<bag>.truth.json`` (hidden truth: never read by the
nodes) and the passes also ``<bag>.irregularity.csv``.
"""
import argparse
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from maglev_ros.twin.simulate import simulate  # noqa: E402

# name: (scenario, seed, --set overrides)
SAMPLES = {"paper_pass": ("paper-field", 1, ()),
           "paper_pass2": ("paper-field", 3, ("speed_mps=8.333",)),
           "paper_ambient": ("paper-ambient", 2, ())}


def bag_size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out-dir", default=str(HERE))
    args = ap.parse_args()
    out_dir = Path(args.out_dir)
    for name, (scenario, seed, sets) in SAMPLES.items():
        res = simulate(scenario, out_dir / name, sets=sets, seed=seed, overwrite=True)
        print(f"{res.bag}: {res.kind}, {res.duration_s:.1f} s, {bag_size(Path(res.bag)) / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
