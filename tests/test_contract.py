"""Metadata parsing/validation and unit checks of the recording contract (maglev_ros.contract)."""
from __future__ import annotations

import copy
import json
import re
from pathlib import Path

import pytest

from bagfactory import example_topics, make_metadata
from maglev_ros import contract as C
from maglev_ros.errors import ContractError, UserError

# the contract document itself (shared/ beside the repository, else the repo's verbatim copy)
_SHARED_MD = Path(__file__).resolve().parents[2] / "shared" / "contract" / "RECORDING.md"
RECORDING_MD = (_SHARED_MD if _SHARED_MD.exists()
                else Path(__file__).resolve().parents[1] / "docs" / "contract" / "RECORDING.md")


def _contract_example() -> dict:
    """The metadata example printed in the contract document itself (independent of our code)."""
    text = RECORDING_MD.read_text()
    block = re.search(r"## Metadata JSON.*?```json\n(.*?)```", text, re.S).group(1)
    return json.loads(block)


def _contract_design_block() -> dict:
    text = RECORDING_MD.read_text()
    block = re.search(r"## Design block.*?```json\n(.*?)```", text, re.S).group(1)
    return json.loads("{" + block + "}")["design"]


def test_topic_names_match_contract_document():
    text = RECORDING_MD.read_text()
    for topic in (C.TOPIC_METADATA, C.TOPIC_GUIDEWAY_ACCEL, C.TOPIC_GUIDEWAY_DISP,
                  C.TOPIC_VEHICLE_ACCEL, C.TOPIC_VEHICLE_GAP, C.TOPIC_VEHICLE_POSITION):
        assert f"`{topic}`" in text
    assert C.SENSORBLOCK_TYPE == "maglev_msgs/msg/SensorBlock"
    assert f"`{C.SENSORBLOCK_TYPE}`" in text


def test_contract_example_parses_with_typed_accessors():
    doc = _contract_example()
    md = C.parse_metadata(json.dumps(doc), "example.mcap")
    assert md.schema == "maglev-testline/1"
    assert md.run_kind == "pass"
    assert md.nominal_speed_mps == pytest.approx(6.944)
    assert md.magnet_offsets_m == (0.0, -1.548)
    assert md.nominal_gap_m == pytest.approx(0.010)
    (span,) = md.spans
    assert (span.id, span.start_m, span.length_m) == ("S1", 0.0, 12.384)
    assert span.end_m == pytest.approx(12.384)
    assert set(md.sensors) == {"G3LV", "M1A", "M1G"}
    g = md.sensors["G3LV"]
    assert (g.topic, g.direction, g.side, g.position_m) == (C.TOPIC_GUIDEWAY_ACCEL, "vertical",
                                                            "left", 18.576)
    assert md.sensors["M1G"].magnet == 1
    assert list(md.sensors_on_topic(C.TOPIC_VEHICLE_ACCEL)) == ["M1A"]
    assert md.sensors_on_topic("/nothing") == {}
    assert md.design is None
    assert md.vehicle["magnet_offsets_m"] == [0.0, -1.548]


def test_design_block_and_unknown_keys_are_kept_but_ignored():
    doc = _contract_example()
    doc["design"] = _contract_design_block()
    doc["future_key"] = {"anything": [1, 2]}
    doc["line"]["spans"][0]["youngs_modulus_pa"] = 3.9e10   # span override (unknown to parser)
    doc["sensors"]["G3LV"]["calibration"] = "2024-01"
    md = C.parse_metadata(json.dumps(doc), "b")
    assert md.design["guideway"]["youngs_modulus_pa"] == 4.0e10
    assert md.spans[0].extra == {"youngs_modulus_pa": 3.9e10}
    assert md.raw["future_key"] == {"anything": [1, 2]}
    assert json.loads(md.to_json()) == doc


def test_ambient_run_needs_no_vehicle():
    doc = make_metadata(example_topics(0.1), kind="ambient")
    assert "vehicle" not in doc
    md = C.metadata_from_dict(doc, "amb")
    assert md.run_kind == "ambient" and md.magnet_offsets_m == () and md.nominal_speed_mps is None


@pytest.mark.parametrize("path", ["schema", "line.spans", "sensors", "run.kind",
                                  "vehicle.magnet_offsets_m", "line", "run", "vehicle",
                                  "line.spans.0.length_m", "sensors.M1A.topic"])
def test_missing_required_key_names_bag_and_key(path):
    doc = _contract_example()
    obj = doc
    parts = path.split(".")
    for p in parts[:-1]:
        obj = obj[int(p)] if p.isdigit() else obj[p]
    del obj[parts[-1]]
    with pytest.raises(ContractError) as ei:
        C.parse_metadata(json.dumps(doc), "/data/run7.mcap")
    msg = str(ei.value)
    assert "\n" not in msg
    assert msg.startswith("/data/run7.mcap: metadata key ")
    expected_path = {"line": "line.spans", "run": "run.kind", "vehicle": "vehicle.magnet_offsets_m",
                     "line.spans.0.length_m": "line.spans[0].length_m"}.get(path, path)
    assert expected_path in msg
    assert "missing" in msg
    assert isinstance(ei.value, UserError)


@pytest.mark.parametrize("mutate, key, expect", [
    (lambda d: d.update(schema="maglev-testline/2"), "schema", "maglev-testline/1"),
    (lambda d: d["run"].update(kind="race"), "run.kind", "pass, ambient"),
    (lambda d: d["sensors"]["G3LV"].update(side="top"), "sensors.G3LV.side", "left"),
    (lambda d: d["sensors"]["G3LV"].update(direction="up"), "sensors.G3LV.direction", "vertical"),
    (lambda d: d["sensors"]["G3LV"].update(position_m="18"), "sensors.G3LV.position_m", "number"),
    (lambda d: d["sensors"]["M1A"].update(magnet=3), "sensors.M1A.magnet", "2 magnets"),
    (lambda d: d["sensors"]["M1A"].update(magnet=0), "sensors.M1A.magnet", "1-based"),
    (lambda d: d["line"]["spans"][0].update(length_m=-1.0), "line.spans[0].length_m", "> 0"),
    (lambda d: d["vehicle"].update(magnet_offsets_m=[]), "vehicle.magnet_offsets_m", "non-empty"),
    (lambda d: d["sensors"].update(X={"topic": "no-slash"}), "sensors.X.topic", "topic name"),
    (lambda d: d.update(design=[1]), "design", "object"),
    (lambda d: d["sensors"].update(B1A={"topic": C.TOPIC_BODY_ACCEL, "quantity": "acceleration"}),
     "sensors.B1A.body_x_m", "car-body point"),
])
def test_bad_values_name_key_and_expectation(mutate, key, expect):
    doc = copy.deepcopy(_contract_example())
    mutate(doc)
    with pytest.raises(ContractError, match=re.escape(key)) as ei:
        C.metadata_from_dict(doc, "bag1")
    assert expect in str(ei.value)
    assert str(ei.value).startswith("bag1: ")


def test_unlisted_span_and_position_outside_span_are_warnings():
    # The contract's own example refers to span S2 but lists only S1: valid, but reported.
    md = C.metadata_from_dict(_contract_example(), "b")
    (w,) = C.metadata_issues(md)
    assert (w.severity, w.kind, w.channel) == ("warning", "unknown_span", "G3LV")
    assert "sensors.G3LV.span" in w.message and "'S2'" in w.message
    doc = _contract_example()
    doc["line"]["spans"].append({"id": "S2", "start_m": 12.384, "length_m": 12.384})
    assert C.metadata_issues(C.metadata_from_dict(doc, "b")) == []
    doc["sensors"]["G3LV"]["position_m"] = 30.0          # S2 spans 12.384 .. 24.768 m
    (w,) = C.metadata_issues(C.metadata_from_dict(doc, "b"))
    assert w.kind == "position_outside_span"


def test_invalid_json_and_non_object():
    with pytest.raises(ContractError, match=r"^b\.mcap: metadata is not valid JSON"):
        C.parse_metadata("{not json", "b.mcap")
    with pytest.raises(ContractError, match="JSON object"):
        C.parse_metadata("[1, 2]", "b.mcap")


# ------------------------------------------------------------------------------- units
@pytest.mark.parametrize("unit", ["m/s^2", "m", "m/s", "rad", "N", "Pa", "1"])
def test_si_units_accepted(unit):
    assert C.is_si_unit(unit)
    assert C.unit_conversion(unit) == (unit, 1.0)


@pytest.mark.parametrize("unit, si, factor", [
    ("g", "m/s^2", 9.80665),            # standard gravity, exact by definition
    ("mm", "m", 0.001),
    ("mm/s", "m/s", 0.001),
    ("km/h", "m/s", 1000.0 / 3600.0),
    ("um", "m", 1e-6),
    ("cm/s^2", "m/s^2", 0.01),
    ("mm/s^2", "m/s^2", 0.001),
    ("m/s2", "m/s^2", 1.0),             # DAQ spellings of the SI unit itself
    ("m/s²", "m/s^2", 1.0),
    ("μm", "m", 1e-6),                  # Greek mu as well as the micro sign
])
def test_non_si_units_known_factor(unit, si, factor):
    assert not C.is_si_unit(unit)
    got_si, got_factor = C.unit_conversion(unit)
    assert got_si == si
    assert got_factor == pytest.approx(factor, rel=1e-12)


def test_check_units_names_topic_channel_and_factor():
    issues = C.check_units(C.TOPIC_GUIDEWAY_ACCEL, ("G1LV", "G2LV", "G3LV"),
                           ("m/s^2", "g", "furlong"), time_s=1.5)
    assert [(i.channel, i.kind) for i in issues] == [("G2LV", "non_si_unit"),
                                                      ("G3LV", "non_si_unit")]
    assert all(i.topic == C.TOPIC_GUIDEWAY_ACCEL and i.time_s == 1.5 for i in issues)
    assert "9.80665" in issues[0].message and "'m/s^2'" in issues[0].message
    assert "furlong" in issues[1].message
    # SI but wrong quantity for the topic
    (mis,) = C.check_units(C.TOPIC_VEHICLE_GAP, ("M1G",), ("m/s",))
    assert mis.kind == "unit_mismatch" and "'m'" in mis.message
    # position topic: per channel rule
    assert C.check_units(C.TOPIC_VEHICLE_POSITION, ("position_m", "speed_mps"), ("m", "m/s")) == []
    (bad,) = C.check_units(C.TOPIC_VEHICLE_POSITION, ("position_m", "speed_mps"), ("m", "km/h"))
    assert bad.channel == "speed_mps" and f"{1 / 3.6:.9g}" in bad.message


def test_issue_to_dict_is_json_ready():
    i = C.Issue("error", "/t", "A", 1.25, "nan", "bad")
    assert json.loads(json.dumps(i.to_dict())) == {"severity": "error", "topic": "/t",
                                                   "channel": "A", "time_s": 1.25, "kind": "nan",
                                                   "message": "bad"}
    assert "nan" in str(i) and "[A]" in str(i)
