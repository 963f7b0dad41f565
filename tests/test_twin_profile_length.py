"""The online twin keeps only the measured profile it needs (its magnet span + 20 of the band's
longest wavelengths): on a pass whose measured profile is longer than that, its predictions equal
those of a twin that keeps 2 km."""
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))


def _predictions(md, items, **kw):
    from maglev_ros.twin.online import OnlineTwin
    tw = OnlineTwin(md, dt_max_s=5e-4, **kw)
    out = []
    for topic, block in items:
        out += tw.on_block(topic, block)
    out += tw.finish()
    groups = {}
    for o in out:
        groups.setdefault(o.group, []).append(np.asarray(o.predicted.data, float))
    return tw, {g: np.concatenate(v) for g, v in groups.items()}


def test_the_kept_profile_gives_the_predictions_of_a_long_one(tmp_path):
    from bench_keepup import make_recording   # the paper pass on a line long enough for 30 s

    from maglev_ros.bag_reader import BagReader
    from maglev_ros.twin.online import profile_length_m
    bag = make_recording(tmp_path / "pass30", 30.0)["bag"]
    with BagReader(bag) as r:
        md, items = r.metadata, list(r.iter_blocks())
    items.sort(key=lambda t: (t[1].stamp_ns, t[0]))
    short_twin, short = _predictions(md, items)
    _, long_ = _predictions(md, items, profiler_options={"max_profile_m": 2000.0})
    kept = profile_length_m(short_twin._profiler, md.magnet_offsets_m)
    assert kept < 0.25 * 2000.0                              # the cap is what a refresh processes
    assert short_twin._profiler.acc.max_points == int(kept / 0.02)
    assert short_twin._profiler.acc.n == short_twin._profiler.acc.max_points   # the pass is longer: cut
    for g in long_:
        scale = np.nanmax(np.abs(long_[g]))
        assert np.nanmax(np.abs(short[g] - long_[g])) <= 1e-6 * scale, g
