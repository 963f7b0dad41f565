"""The README's "Bring your own data" example, run as written (between its byod markers): the
sample pass exported to CSV in g and mm, metadata template, import, info, irregularity. The
imported bag passes the contract check cleanly and holds the original bag's samples (within the
float32 rounding of the mm/g round trip) at the original stamps. ``diagnose`` is left out: it
takes minutes, and it reads the bag with the same reader ``info`` and ``irregularity`` use.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from maglev_ros.bag_reader import BagReader

ROOT = Path(__file__).resolve().parents[1]


def _readme_steps() -> str:
    text = (ROOT / "README.md").read_text()
    m = re.search(r"<!-- byod:start -->\s*```bash\n(.*?)```\s*<!-- byod:end -->", text, re.S)
    assert m, "README lost its byod example"
    steps = m.group(1)
    assert "maglev-ros diagnose" in steps                 # the README shows the whole way
    steps = "\n".join(line for line in steps.splitlines() if "maglev-ros diagnose" not in line)
    py = sys.executable
    steps = re.sub(r"(?m)^\.venv/bin/maglev-ros ", f"{py} -m maglev_ros.cli ", steps)
    return re.sub(r"(?m)^\.venv/bin/python ", f"{py} ", steps)


@pytest.fixture(scope="module")
def byod(tmp_path_factory):
    work = tmp_path_factory.mktemp("byod")
    for name in ("bags", "docs"):
        (work / name).symlink_to(ROOT / name)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    run = subprocess.run(["bash", "-e", "-c", _readme_steps()], cwd=work, env=env,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    return work / "out" / "byod", run.stdout


def test_readme_example_runs_and_info_is_clean(byod):
    out, stdout = byod
    assert "contract:  OK, no problems found" in stdout
    assert "G1LV (Acc G1 left): g -> m/s^2, x 9.80665" in stdout
    rep = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "info", str(out / "pass"), "--json"],
                         capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    doc = json.loads(rep.stdout)
    assert doc["ok"] and doc["issues"] == []
    assert (out / "irregularity.csv").stat().st_size > 0


def test_imported_bag_holds_the_original_samples(byod):
    out, _ = byod
    with BagReader(ROOT / "bags" / "paper_pass") as a, BagReader(out / "pass") as b:
        assert set(b.sensor_topics) == set(a.sensor_topics)
        for topic in a.sensor_topics:
            ba = [blk for _, blk in a.iter_blocks([topic])]
            bb = [blk for _, blk in b.iter_blocks([topic])]
            assert bb[0].channels == ba[0].channels and bb[0].units == ba[0].units
            assert {x.sample_rate_hz for x in bb} == {x.sample_rate_hz for x in ba}
            da = np.concatenate([x.data for x in ba])
            db = np.concatenate([x.data for x in bb])
            scale = np.abs(da).max(axis=0)
            # value -> value / factor printed with 9 digits -> x factor -> float32: <= 1 float32 ulp
            # of the value, plus 1e-7 of the channel's range for values near zero
            assert np.all(np.abs(db - da) <= 1.2e-7 * np.abs(da) + 1e-7 * scale), topic

            def stamps(blocks):
                return np.concatenate([x.stamp_ns + np.round(np.arange(x.n_samples) * 1e9
                                                             / x.sample_rate_hz).astype(np.int64)
                                       for x in blocks])
            np.testing.assert_array_equal(stamps(bb), stamps(ba))
        md_a, md_b = a.metadata, b.metadata
        assert md_b.sensors.keys() == md_a.sensors.keys()
        assert md_b.magnet_offsets_m == md_a.magnet_offsets_m
        assert [(s.id, s.start_m, s.length_m) for s in md_b.spans] == \
            [(s.id, s.start_m, s.length_m) for s in md_a.spans]
