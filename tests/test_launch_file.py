"""launch/monitor.launch.py starts the same graph as ``maglev-ros launch monitor``: for the same
arguments every node gets the same name, namespace, remappings, params file and parameters (the
replay's start-up gating included). launch_ros is not on PyPI, so the launch file runs against
stand-in ``launch`` / ``launch_ros`` modules that record what it builds; the command lines come
from the launcher's own ``command_lines`` (what ``launch`` starts), parsed back."""
import importlib.util
import sys
import types
from pathlib import Path

import pytest

from maglev_ros.cli import build_parser
from maglev_ros.commands.launch import launch_kwargs
from maglev_ros.errors import UserError
from maglev_ros.launch_graph import check_namespace, ros_param_args
from maglev_ros.launcher import command_lines

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / "bags" / "paper_pass"


class _Recorded:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class _LaunchConfiguration:
    def __init__(self, name):
        self.name = name

    def perform(self, context):
        return context.launch_configurations[self.name]


def _stub_modules(monkeypatch):
    launch = types.ModuleType("launch")
    launch.LaunchDescription = lambda entities: list(entities)
    actions = types.ModuleType("launch.actions")
    actions.DeclareLaunchArgument = type("DeclareLaunchArgument", (_Recorded,), {})
    actions.OpaqueFunction = type("OpaqueFunction", (_Recorded,), {})
    subs = types.ModuleType("launch.substitutions")
    subs.LaunchConfiguration = _LaunchConfiguration
    launch_ros = types.ModuleType("launch_ros")
    ros_actions = types.ModuleType("launch_ros.actions")
    ros_actions.Node = type("Node", (_Recorded,), {})
    for name, mod in {"launch": launch, "launch.actions": actions, "launch.substitutions": subs,
                      "launch_ros": launch_ros, "launch_ros.actions": ros_actions}.items():
        monkeypatch.setitem(sys.modules, name, mod)


def _from_launch_file(monkeypatch, given: dict) -> dict:
    """{node name: (namespace, remaps, params file, {param: value text})} as the launch file builds it."""
    _stub_modules(monkeypatch)
    spec = importlib.util.spec_from_file_location("monitor_launch", ROOT / "launch" / "monitor.launch.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    entities = mod.generate_launch_description()
    declared = {e.args[0]: e.kwargs["default_value"] for e in entities if type(e).__name__ == "DeclareLaunchArgument"}
    assert set(given) <= set(declared), set(given) - set(declared)
    context = types.SimpleNamespace(launch_configurations={**declared, **given})
    [opaque] = [e for e in entities if type(e).__name__ == "OpaqueFunction"]
    out = {}
    for node in opaque.kwargs["function"](context):
        kw = node.kwargs
        assert kw["package"] == "maglev_ros" and kw["executable"] == kw["name"]
        files = [p for p in kw["parameters"] if isinstance(p, str)]
        [params] = [p for p in kw["parameters"] if isinstance(p, dict)]
        args = ros_param_args(params)
        out[kw["name"]] = (kw["namespace"] or "", tuple(map(tuple, kw["remappings"])), files[0] if files else None,
                           dict(a.split(":=", 1) for a in args[1::2]))
    return out


def _cli_launch(monkeypatch, argv: list[str]) -> dict:
    """The keyword arguments ``maglev-ros launch monitor ARGV`` (the verb's own ``run``) hands the
    launcher, the --record/--view nodes included; nothing is started."""
    import maglev_ros.launcher
    from maglev_ros.commands.launch import run
    seen = {}

    def fake_launch(graph_name, **kwargs):
        seen.update(kwargs)
        return 0
    monkeypatch.setattr(maglev_ros.launcher, "launch", fake_launch)
    assert run(build_parser().parse_args(["launch", "monitor", *argv])) == 0
    return seen


def _from_launcher(argv: list[str], monkeypatch=None) -> dict:
    """The same, parsed from the command lines ``maglev-ros launch monitor ARGV`` starts (with
    ``monkeypatch``: as the verb's ``run`` builds them, extra nodes included)."""
    if monkeypatch is not None:
        kwargs = _cli_launch(monkeypatch, argv)
    else:
        kwargs = launch_kwargs(build_parser().parse_args(["launch", "monitor", *argv]))
    out = {}
    for spec, cmd in command_lines("monitor", **kwargs):
        ros = cmd[cmd.index("--ros-args") + 1:]
        name, ns, remaps, pfile, params = None, "", [], None, {}
        for flag, value in zip(ros[::2], ros[1::2]):
            if flag == "--params-file":
                pfile = value
                continue
            key, val = value.split(":=", 1)
            if flag == "-p":
                params[key] = val
            elif key == "__node":
                name = val
            elif key == "__ns":
                ns = val
            else:
                remaps.append((key, val))
        assert cmd[cmd.index("-m") + 1] == spec.module and name == spec.name
        out[name] = (ns, tuple(remaps), pfile, params)
    return out


def test_launch_file_and_launcher_give_every_node_the_same_setup(monkeypatch, tmp_path):
    params_file = tmp_path / "p.yaml"
    params_file.write_text("/**:\n  ros__parameters: {}\n")
    argv = ["--bag", str(BAG), "--rate", "2.5", "--namespace", "/line7", "--use-sim-time",
            "--params-file", str(params_file), "--out", str(tmp_path / "o"), "--linger", "12"]
    given = {"bag": str(BAG), "rate": "2.5", "namespace": "/line7", "use_sim_time": "true",
             "params_file": str(params_file), "out": str(tmp_path / "o"), "linger_s": "12"}
    cli = _from_launcher(argv)
    assert _from_launch_file(monkeypatch, given) == cli
    # what both give: every node in the namespace with /clock remapped into it, the replay gated
    # on the graph's other nodes and on one subscriber per data topic, the others on sim time
    others = sorted(n for n in cli if n != "replay")
    assert set(cli) == {"replay", "irregularity", "modal_id", "updater", "discrepancy", "twin"}
    for name, (ns, remaps, pfile, params) in cli.items():
        assert ns == "/line7" and remaps == (("/clock", "/line7/clock"),) and pfile == str(params_file)
        assert params.get("use_sim_time") == (None if name == "replay" else "true")
    replay = cli["replay"][3]
    assert sorted(replay["wait_nodes"].strip("[]").replace("'", "").split(",")) == others
    assert replay["wait_subscribers"] == "1" and replay["rate"] == "2.5" and replay["linger_s"] == "12.0"
    assert cli["updater"][3]["history_path"] == str(tmp_path / "o" / "twin_parameters.jsonl")


def test_the_defaults_agree_too(monkeypatch):
    cli = _from_launcher(["--bag", str(BAG)])
    assert _from_launch_file(monkeypatch, {"bag": str(BAG)}) == cli
    assert all(ns == "" and remaps == () for ns, remaps, *_ in cli.values())
    # without a bag: no replay, in both
    assert "replay" not in _from_launch_file(monkeypatch, {}) and "replay" not in _from_launcher([])


def test_record_and_view_start_the_same_recorder_and_bridge(monkeypatch, tmp_path):
    """``--record/--record-inputs/--view/--view-port`` and the launch file's ``record:=`` ... give
    the same recorder (path, inputs, log time on the replay's clock) and Foxglove bridge."""
    rec = tmp_path / "run.mcap"
    argv = ["--bag", str(BAG), "--record", str(rec), "--record-inputs", "--view", "--view-port", "9001",
            "--view-host", "0.0.0.0", "--out", str(tmp_path / "o")]
    given = {"bag": str(BAG), "record": str(rec), "record_inputs": "true", "view": "true",
             "view_port": "9001", "view_host": "0.0.0.0", "out": str(tmp_path / "o")}
    cli = _from_launcher(argv, monkeypatch)
    assert _from_launch_file(monkeypatch, given) == cli
    assert {"recorder", "foxglove_bridge"} <= set(cli)
    recorder, bridge = cli["recorder"][3], cli["foxglove_bridge"][3]
    assert recorder["path"] == str(rec) and recorder["include_inputs"] == "true"
    assert recorder["reliable"] == "false" and recorder["use_sim_time"] == "true"
    assert bridge == {"host": "0.0.0.0", "port": "9001"}
    # the replay does not wait for the observer (the bridge), it does for the recorder's topics' nodes
    assert "foxglove_bridge" not in cli["replay"][3]["wait_nodes"]
    # without record/view: neither, in both
    plain = _from_launch_file(monkeypatch, {"bag": str(BAG)})
    assert not {"recorder", "foxglove_bridge"} & set(plain)


@pytest.mark.parametrize("given, match", [
    ({"record": "run.bag"}, r"^record run.bag: expected a file name ending in .mcap$"),
    ({"record_inputs": "true"}, r"^record_inputs / record_reliable: given without a record file"),
    ({"view": "true", "view_port": "70000"}, r"^view_port: expected a port 1-65535, got 70000$"),
])
def test_the_launch_files_record_and_view_mistakes_are_one_line(monkeypatch, given, match):
    with pytest.raises(UserError, match=match) as err:
        _from_launch_file(monkeypatch, given)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("bad", ["line 1", "/1line", "/a//b", "/a-b"])
def test_a_bad_namespace_is_one_line(bad):
    with pytest.raises(UserError, match=r"^namespace .*: expected names of letters") as err:
        check_namespace(bad)
    assert "\n" not in str(err.value)


def test_a_namespace_is_made_fully_qualified():
    assert check_namespace("line1") == "/line1" and check_namespace("/a/b/") == "/a/b"
    assert check_namespace("") == check_namespace("/") == ""


def test_the_replays_rate_reaches_the_nodes_that_pace_their_outputs_in_wall_time():
    """The irregularity node gets the replay's rate as ``stream_rate`` (live profiles about once per
    wall second); unpaced (``fast``) or without a bag it keeps 1; an explicit override wins."""
    from maglev_ros.launch_graph import launch_overrides, node_launches

    def stream_rate(**kw):
        bag = kw.pop("bag", str(BAG))
        extra = kw.pop("irregularity", None)
        ov = launch_overrides(**kw)
        if extra is not None:
            ov["irregularity"] = extra
        nl = {n.name: n for n in node_launches("monitor", bag=bag, overrides=ov)}
        return nl["irregularity"].params.get("stream_rate", 1.0), nl["twin"].params.get("stream_rate")

    assert stream_rate(rate=10.0) == (10.0, None)          # the twin's predictions do not depend on it
    assert stream_rate(rate=0.5) == (0.5, None)
    assert stream_rate(rate=10.0, fast=True) == (1.0, None)
    assert stream_rate(rate=10.0, irregularity={"stream_rate": 1.0}) == (1.0, None)
    assert stream_rate(rate=10.0, bag=None)[0] == 1.0
