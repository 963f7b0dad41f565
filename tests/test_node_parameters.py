"""Every node's parameters are declared with a ParameterDescriptor (description, type, range where
physical, read-only when read only at construction); a live one changes what the node uses, a
read-only one and an out-of-range value are refused with a reason, and a bad start value is one
line naming the parameter (exit 1, no traceback).

The nodes are built in one subprocess (this file run as a script, ``harness``: the imports are paid
once), each on its own rclpy context; the service path of the same checks (a client calling
``/replay/set_parameters``) is in test_replay_services.py.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
BAG = HERE.parent / "bags" / "paper_pass"

# node: (module, class, start parameters, a live parameter with a new value, and how the node
# shows it uses it)
CASES = {
    "replay": ("maglev_ros.nodes.replay", "ReplayNode", {"bag": str(BAG)}, ("rate", 4.0),
               lambda n: n.clock.rate),
    "irregularity": ("maglev_ros.nodes.irregularity", "IrregularityNode", {}, ("publish_period_s", 0.25),
                     lambda n: n.period_ns * 1e-9),
    "modal_id": ("maglev_ros.nodes.modal_id", "ModalIdNode", {}, None, None),
    "twin": ("maglev_ros.nodes.twin", "TwinNode", {}, ("idle_flush_s", 7.0), lambda n: n.idle_flush_s),
    "updater": ("maglev_ros.nodes.updater", "UpdaterNode", {}, ("nrmse_trigger", 0.4),
                lambda n: n.core.nrmse_trigger),
    "discrepancy": ("maglev_ros.nodes.discrepancy", "DiscrepancyNode", {"live_diagnosis": False},
                    ("recording_idle_s", 5.0), lambda n: n.idle_s),
    "summary": ("maglev_ros.nodes.summary", "SummaryNode", {}, ("idle_s", 9.0), lambda n: n.idle_s),
}
# rclpy's own parameters (their descriptors are rclpy's)
ROS_OWN = ("use_sim_time", "start_type_description_service")


def _outside(spec):
    """A value just above the range of ``spec`` (of its own type)."""
    hi = spec.range[1]
    return hi + 1 if spec.kind is int else float(hi) * 2 + 1.0


def harness(out: str) -> None:
    import importlib

    import rclpy
    from rclpy.parameter import Parameter

    from maglev_ros.errors import UserError
    from maglev_ros.launch_graph import ros_param_args
    res = {}
    for name, (module, cls, params, live, probe) in CASES.items():
        rclpy.init(args=["harness", "--ros-args", *ros_param_args(params)])
        node = None
        try:
            node = getattr(importlib.import_module(module), cls)()
            specs = node._maglev_params.specs
            names = node.list_parameters([], 0).names
            descr = {d.name: {"description": d.description, "read_only": d.read_only,
                              "ranges": len(d.floating_point_range) + len(d.integer_range)}
                     for d in node.describe_parameters(names)}
            refused, out_of_range = {}, {}
            for pname, spec in specs.items():
                if spec.apply is None:
                    r = node.set_parameters([Parameter(pname, value=node.get_parameter(pname).value)])[0]
                    refused[pname] = [r.successful, r.reason]
                elif spec.range is not None:
                    r = node.set_parameters([Parameter(pname, value=_outside(spec))])[0]
                    out_of_range[pname] = [r.successful, r.reason]
            entry = {"names": names, "descr": descr, "ours": sorted(specs), "refused": refused,
                     "out_of_range": out_of_range,
                     "has_range": sorted(p for p, s in specs.items() if s.range is not None),
                     "timers": len(list(node.timers))}
            if live is not None:
                pname, value = live
                before = probe(node)
                r = node.set_parameters([Parameter(pname, value=value)])[0]
                entry["live"] = [pname, value, before, r.successful, r.reason, probe(node)]
            res[name] = entry
        finally:
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
    # a bad start value: one line naming the parameter
    bad = {}
    for name, module, cls, params in (("twin", "maglev_ros.nodes.twin", "TwinNode", {"method": "euler"}),
                                      ("irregularity", "maglev_ros.nodes.irregularity", "IrregularityNode",
                                       {"spacing_m": 0}),
                                      ("updater", "maglev_ros.nodes.updater", "UpdaterNode",
                                       {"max_modes": "four"})):
        rclpy.init(args=["harness", "--ros-args", *ros_param_args(params)])
        try:
            getattr(importlib.import_module(module), cls)()
            bad[name] = None
        except UserError as exc:
            bad[name] = str(exc)
        finally:
            rclpy.try_shutdown()
    res["_bad_start"] = bad
    Path(out).write_text(json.dumps(res))


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    from rosgraph import ros_env
    out = tmp_path_factory.mktemp("params") / "res.json"
    p = subprocess.run([sys.executable, __file__, str(out)], env=ros_env(80), capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(out.read_text())


pytestmark = pytest.mark.ros


@pytest.mark.parametrize("node", sorted(CASES))
def test_every_parameter_has_a_descriptor(built, node):
    r = built[node]
    ours = set(r["ours"])
    # every parameter is either declared from the node's table or rclpy's own (QoS overrides included)
    foreign = [n for n in r["names"] if n not in ours and n not in ROS_OWN and not n.startswith("qos_overrides.")]
    assert not foreign, f"{node}: declared without a Param: {foreign}"
    for pname in ours:
        d = r["descr"][pname]
        assert d["description"].strip(), f"{node}.{pname} has no description"
    for pname in r["has_range"]:
        assert r["descr"][pname]["ranges"] == 1, f"{node}.{pname}: range missing from its descriptor"
    for pname in r["refused"]:
        assert r["descr"][pname]["read_only"], pname


@pytest.mark.parametrize("node", sorted(CASES))
def test_read_only_and_out_of_range_changes_are_refused_with_a_reason(built, node):
    r = built[node]
    for pname, (ok, reason) in r["refused"].items():
        assert not ok and reason == f"Trying to set a read-only parameter: {pname}.", (pname, reason)
    for pname, (ok, reason) in r["out_of_range"].items():
        assert not ok and reason and "\n" not in reason, (pname, reason)
        assert pname in reason or "range" in reason.lower(), (pname, reason)


@pytest.mark.parametrize("node", sorted(n for n, c in CASES.items() if c[3] is not None))
def test_a_live_parameter_change_is_used_by_the_node(built, node):
    pname, value, before, ok, reason, after = built[node]["live"]
    assert ok, reason
    assert before != pytest.approx(value) and after == pytest.approx(value), (pname, before, after)


# rclpy's EventsExecutor prints "the number of timers associated with this clock is large" from this
# many timers on one clock on (a timer per sensor subscription made the twin and discrepancy say it)
EVENTS_EXECUTOR_WARN_TIMERS = 8


@pytest.mark.parametrize("node", sorted(CASES))
def test_a_node_has_fewer_timers_than_rclpy_warns_about(built, node):
    assert built[node]["timers"] < EVENTS_EXECUTOR_WARN_TIMERS


def test_a_bad_start_value_is_one_line_naming_the_parameter(built):
    bad = built["_bad_start"]
    assert bad["twin"] == "parameter 'method': expected one of newmark, separated, got 'euler'"
    assert bad["irregularity"].startswith("parameter 'spacing_m': ") and "\n" not in bad["irregularity"]
    assert bad["updater"].startswith("parameter 'max_modes': expected an integer")


if __name__ == "__main__":
    sys.path.insert(0, str(HERE))
    harness(sys.argv[1])
