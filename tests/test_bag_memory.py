"""MemoryBag: a recording a node received, read by the verbs' own readers, gives what the bag gives.

The blocks go in as a replay publishes them (the bag's receive order, repeats and disorder
included) and everything is compared with the bag read from disk: the repaired arrays, the
sensor-health report, windowed reads and a verb's result.
"""
import json

import numpy as np
import pytest

from bagfactory import (GUIDEWAY_ACCEL, VEHICLE_GAP, VEHICLE_POSITION, Faults, example_topics,
                        make_metadata, write_foreign_bag)
from maglev_ros.bag_memory import MemoryBag, RecordingCollector, open_reader, same_source
from maglev_ros.bag_reader import BagReader
from maglev_ros.bag_windows import iter_windows, read_checked_windows


def memory_copy(path) -> MemoryBag:
    """The bag's blocks in its receive order, as a node subscribed to every topic receives them."""
    with BagReader(path) as r:
        mb = MemoryBag(str(path), r.metadata.to_json())
        for topic, block in r.iter_blocks():
            mb.add(topic, block)
    return mb


@pytest.fixture(scope="module")
def faulty_bag(tmp_path_factory):
    topics = example_topics(duration_s=3.0, seed=4)
    md = make_metadata(topics)
    faults = Faults(duplicate={GUIDEWAY_ACCEL: [3]}, swap={GUIDEWAY_ACCEL: [7], VEHICLE_GAP: [2]},
                    overlap={GUIDEWAY_ACCEL: [12]}, units={VEHICLE_GAP: {"M1G": "mm"}})
    topics[VEHICLE_GAP][3][:, 0] *= 1000.0           # recorded in mm, as the unit says
    return write_foreign_bag(tmp_path_factory.mktemp("mem") / "faulty", md, topics, faults=faults)


def test_checked_reads_equal_the_bags_repairs_units_and_health(faulty_bag):
    mem = memory_copy(faulty_bag)
    topics = [GUIDEWAY_ACCEL, VEHICLE_GAP, VEHICLE_POSITION]
    with BagReader(faulty_bag) as r:
        ref, ref_health = r.read_checked(topics, sensor_map=True)
    with open_reader(mem) as m:
        got, health = m.read_checked(topics, sensor_map=True)
    for t in topics:
        assert got[t].channels == ref[t].channels and got[t].units == ref[t].units
        np.testing.assert_array_equal(got[t].time_s, ref[t].time_s)
        np.testing.assert_array_equal(got[t].data, ref[t].data)
        assert [i.kind for i in got[t].issues] == [i.kind for i in ref[t].issues]
    # what the bag's repairs found (a duplicate, disorder, an overlap) and the mm -> m conversion
    kinds = {i.kind for i in ref[GUIDEWAY_ACCEL].issues}
    assert {"duplicate", "out_of_order", "overlap"} <= kinds
    assert json.dumps(health.to_dict()) == json.dumps(ref_health.to_dict())
    assert ref_health.converted and ref[VEHICLE_GAP].units == ("m", "m")


def test_windowed_reads_equal_the_bags(faulty_bag):
    mem = memory_copy(faulty_bag)
    with BagReader(faulty_bag) as r:
        ref, _ = read_checked_windows(r, [GUIDEWAY_ACCEL])
        ref_w = [(w.time_s, w.data) for w in iter_windows(r, ref[GUIDEWAY_ACCEL], 0.7)]
    got, _ = read_checked_windows(mem, [GUIDEWAY_ACCEL])
    got_w = [(w.time_s, w.data) for w in iter_windows(mem, got[GUIDEWAY_ACCEL], 0.7)]
    assert len(got_w) == len(ref_w) > 3
    for (t, d), (tr, dr) in zip(got_w, ref_w):
        np.testing.assert_array_equal(t, tr)
        np.testing.assert_array_equal(d, dr)


def test_the_modes_verb_gives_the_same_floats_on_the_memory_copy():
    from maglev_ros.commands.modes import identify_modes
    bag = "bags/paper_ambient"
    ref = identify_modes(bag)
    got = identify_modes(memory_copy(bag))
    assert [(m.frequency_hz, m.damping_ratio, m.std_frequency_hz, m.mode_shape) for m in got.result.modes] == \
        [(m.frequency_hz, m.damping_ratio, m.std_frequency_hz, m.mode_shape) for m in ref.result.modes]
    assert got.info["settings"] == ref.info["settings"] and got.info["bag"] == bag


def test_collector_ends_a_recording_on_new_metadata_only_when_asked(faulty_bag):
    with BagReader(faulty_bag) as r:
        md = r.metadata.to_json()
        blocks = list(r.iter_blocks(GUIDEWAY_ACCEL))
    c = RecordingCollector([GUIDEWAY_ACCEL], name="line")
    for _, b in blocks[:5]:
        c.add(GUIDEWAY_ACCEL, b)
        c.add(VEHICLE_GAP, b)                        # not a collected topic: ignored
    assert c.set_metadata(md) is None                 # the first metadata, after the first blocks
    other = json.dumps({**json.loads(md), "description": "next recording"})
    assert c.set_metadata(other) is None and c.has_data   # a replay's ends come as events
    done = c.set_metadata(md, metadata_ends=True)     # a live stream: new metadata ends it
    assert done is not None and not c.has_data
    assert str(done.path) == "line 1" and done.metadata.description == "next recording"
    assert list(done.topics) == ["/testline/metadata", GUIDEWAY_ACCEL] and done.topics[GUIDEWAY_ACCEL].count == 5
    assert c.finish("bags/x") is None                 # nothing collected since
    assert same_source(done, done) and not same_source(done, memory_copy(faulty_bag))


def test_an_end_before_its_metadata_waits_for_it(faulty_bag):
    """A replay's end event can reach a node before the recording's (latched) metadata: the end
    waits, and the metadata that comes next completes it."""
    with BagReader(faulty_bag) as r:
        md = json.loads(r.metadata.to_json())
        blocks = [b for _, b in r.iter_blocks(GUIDEWAY_ACCEL)]
    first, second = (json.dumps({**md, "description": d}) for d in ("first", "second"))
    c = RecordingCollector([GUIDEWAY_ACCEL])
    c.set_metadata(first)
    c.add(GUIDEWAY_ACCEL, blocks[0])
    one = c.end("bags/one")
    assert one.metadata.description == "first" and not c.waiting
    c.add(GUIDEWAY_ACCEL, blocks[1])                   # the next recording's blocks, its metadata late
    assert c.end("bags/two") is None and c.waiting
    two = c.set_metadata(second)
    assert not c.waiting and str(two.path) == "bags/two" and two.metadata.description == "second"
    assert c.end("bags/three") is None and not c.waiting   # nothing collected: nothing to wait for
    c.add(GUIDEWAY_ACCEL, blocks[2])
    assert c.end("bags/four") is None and c.waiting
    assert c.abandon() == "bags/four" and not c.waiting and not c.has_data   # the next one began
    assert c.set_metadata(first) is None and c.abandon() is None


def test_collector_drops_a_recording_larger_than_its_cap(faulty_bag):
    with BagReader(faulty_bag) as r:
        md = r.metadata.to_json()
        blocks = [b for _, b in r.iter_blocks(GUIDEWAY_ACCEL)]
    cap = sum(b.data.nbytes for b in blocks[:3])
    c = RecordingCollector([GUIDEWAY_ACCEL], max_bytes=cap)
    c.set_metadata(md)
    assert [c.add(GUIDEWAY_ACCEL, b) for b in blocks[:5]] == [True, True, True, False, False]
    assert c.overflowed and c.finish() is None        # not kept: no result for it
    assert c.add(GUIDEWAY_ACCEL, blocks[0]) and c.finish().topics[GUIDEWAY_ACCEL].count == 1   # the next is
