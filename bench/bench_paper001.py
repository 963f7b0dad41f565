"""Paper 001's reported responses beside ours (issue 30's done-when): runs
``maglev-ros random-vibration paper001`` with its defaults (or reads a finished run's
``random_vibration.json``) and prints each reported quantity, ours, the ratio and whether it is
within a factor 2. The paper's values are read from its sec. 6 (accelerations in m/s^2; the
"implied" SDs assume its mean and 3-sigma bound peak at the same time); docs/system3d.md gives
the likely cause of each difference.

    .venv/bin/python bench/bench_paper001.py [--from RUN_DIR] [--out DIR] [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

# (quantity, output, summary key, paper 001's value, where it is read)
PAPER_ROWS = (
    ("cabin vertical, max mean", "cabin2_acc_z", "max_abs_mean", 0.16, "sec. 6.2, fig. 9"),
    ("cabin vertical, max 3-sigma", "cabin2_acc_z", "max_abs_3sigma", 0.32, "sec. 6.2, fig. 9"),
    ("cabin vertical, max SD (implied)", "cabin2_acc_z", "max_sd", (0.32 - 0.16) / 3, "(3-sigma - mean) / 3"),
    ("cabin lateral, max 3-sigma", "cabin2_acc_y", "max_abs_3sigma", 0.03, "sec. 6.3"),
    ("girder midpoint vertical, max mean", "girder_mid_acc_z", "max_abs_mean", 0.09, "sec. 6.2, fig. 10"),
    ("girder midpoint vertical, max 3-sigma", "girder_mid_acc_z", "max_abs_3sigma", 0.11, "sec. 6.2, fig. 10"),
    ("girder midpoint vertical, max SD (implied)", "girder_mid_acc_z", "max_sd", (0.11 - 0.09) / 3,
     "(3-sigma - mean) / 3"),
    ("girder midpoint lateral, max 3-sigma", "girder_mid_acc_y", "max_abs_3sigma", 0.03, "sec. 6.3"),
    ("cabin vertical PSD peak [Hz]", "cabin2_acc_z", "psd_peak_hz", 0.71, "fig. 9a: 0.16 rad/m at 100 km/h"),
)


def rows(doc: dict) -> list[dict]:
    """The paper rows of one ``maglev-random-vibration/1`` document."""
    out = []
    for label, name, key, paper, where in PAPER_ROWS:
        ours = float(doc["summary"][name][key])
        ratio = ours / paper
        out.append({"quantity": label, "paper": paper, "ours": ours, "ratio": ratio,
                    "within_2x": 0.5 <= ratio <= 2.0, "paper_source": where})
    car2 = doc["cars_on_girder"][1]
    ok = abs(car2["enter_s"] - 2.39) <= 0.05 and abs(car2["leave_s"] - 13.05) <= 0.05
    out.insert(0, {"quantity": "car 2 on the girder [s]", "paper": [2.39, 13.05],
                   "ours": [car2["enter_s"], car2["leave_s"]], "ratio": None, "within_2x": ok,
                   "paper_source": "sec. 6.2 (+-0.05 s)"})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--from", dest="run_dir", help="a finished run's directory (skip the run)")
    ap.add_argument("--out", help="where the run writes (default: a temporary directory)")
    ap.add_argument("--json", help="write the rows here")
    a = ap.parse_args(argv)
    if a.run_dir:
        doc = json.loads((Path(a.run_dir) / "random_vibration.json").read_text())
    else:
        from maglev_ros.cli import main as cli
        out = Path(a.out) if a.out else Path(tempfile.mkdtemp(prefix="paper001_"))
        if cli(["random-vibration", "paper001", "--out", str(out)]) != 0:
            return 1
        doc = json.loads((out / "random_vibration.json").read_text())
    rs = rows(doc)
    print(f"{'quantity':44s} {'paper':>16s} {'ours':>16s} {'ours/paper':>10s}  within 2x")
    for r in rs:
        fmt = (lambda v: f"{v[0]:.2f}-{v[1]:.2f}") if isinstance(r["paper"], list) else (lambda v: f"{v:.4g}")
        ratio = "" if r["ratio"] is None else f"{r['ratio']:.2f}"
        print(f"{r['quantity']:44s} {fmt(r['paper']):>16s} {fmt(r['ours']):>16s} {ratio:>10s}  "
              f"{'yes' if r['within_2x'] else 'NO'}")
    n_ok = sum(r["within_2x"] for r in rs)
    print(f"{n_ok} of {len(rs)} within a factor 2 (car times within 0.05 s)")
    if a.json:
        Path(a.json).write_text(json.dumps({"rows": rs, "within": n_ok, "of": len(rs)}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
