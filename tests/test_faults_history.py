"""Faults of the parameter history (maglev_ros/updating/history.py): torn and damaged lines, a second
writer, non-finite values, temp files of older versions, writers killed mid-append, a failed write,
a removed file, and the cost of an append. Each ends in a clear error, a warning with a correct
result, or a line set aside and reported: never a lost record, never a silent drop."""
from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from maglev_ros.errors import UserError
from maglev_ros.updating.history import SCHEMA, ParameterHistory, damaged_path
from rosgraph import domain_id

HERE = Path(__file__).resolve().parent


def _p(v: float) -> dict:
    return {"kp_a_per_m": {"value": float(v), "unit": "A/m"}}


def _lines(path: Path) -> list[bytes]:
    return path.read_bytes().split(b"\n")


def _damaged(path: Path) -> list[dict]:
    d = damaged_path(path)
    return [json.loads(l) for l in d.read_text().splitlines()] if d.exists() else []


def _write_history(path: Path, n: int) -> None:
    """A valid history of ``n`` records, written in one go (as a long-running updater leaves it)."""
    path.write_text("".join(json.dumps({"schema": SCHEMA, "revision": i, "time_unix_s": 1.7e9 + i, "line": "L",
                                        "parameters": _p(i), "data_used": {}, "fit": {}}) + "\n"
                            for i in range(1, n + 1)))


def test_torn_last_line_then_append_keeps_both_records_and_sets_the_tear_aside(tmp_path):
    path = tmp_path / "h.jsonl"
    with ParameterHistory(path) as h:
        h.append(_p(1))
        line2 = (json.dumps(h.append(_p(2))) + "\n").encode()
    torn = line2[: len(line2) // 2]                  # a record cut mid-write (power loss, another tool)
    with open(path, "ab") as f:
        f.write(torn)
    reader = ParameterHistory(path)
    assert [r["revision"] for r in reader.records()] == [1, 2]
    assert reader.skipped and reader.skipped[0].startswith("line 3: torn last line")
    with ParameterHistory(path) as h:
        r3 = h.append(_p(3))
        said = h.take_warnings()
    assert r3["revision"] == 3
    lines = [l for l in _lines(path) if l]
    assert [json.loads(l)["revision"] for l in lines] == [1, 2, 3]   # nothing glued onto the tear
    assert json.loads(lines[-1])["parameters"] == _p(3)
    [aside] = _damaged(path)
    assert aside["line"] == 3 and aside["text"].encode() == torn and "cut off" in aside["action"]
    assert len(said) == 1 and "line 3" in said[0] and str(damaged_path(path)) in said[0]


def test_a_torn_last_line_that_cannot_be_set_aside_stays_in_the_history_on_its_own_line(tmp_path):
    path = tmp_path / "h.jsonl"
    _write_history(path, 1)
    with open(path, "ab") as f:
        f.write(b'{"schema": "maglev-param')
    damaged_path(path).mkdir()                       # the sibling cannot be written
    with ParameterHistory(path) as h:
        [said] = h.open_writer()
        assert h.append(_p(2))["revision"] == 2
    assert "cannot be copied" in said and "stay in the history" in said
    reader = ParameterHistory(path)
    assert [r["revision"] for r in reader.records()] == [1, 2]
    assert len(reader.skipped) == 1 and reader.skipped[0].startswith("line 2: not JSON")


def test_a_last_record_missing_only_its_end_of_line_is_kept(tmp_path):
    path = tmp_path / "h.jsonl"
    _write_history(path, 2)
    path.write_bytes(path.read_bytes().rstrip(b"\n"))   # e.g. saved by an editor without a final newline
    with ParameterHistory(path) as h:
        assert h.append(_p(3))["revision"] == 3
    assert [json.loads(l)["revision"] for l in _lines(path) if l] == [1, 2, 3]
    assert not damaged_path(path).exists()


def test_damaged_lines_in_the_middle_are_kept_aside_and_reported(tmp_path):
    path = tmp_path / "h.jsonl"
    _write_history(path, 2)
    good = _lines(path)[:2]
    garbage = [b"this is not json",
               json.dumps({"hello": 1}).encode(),                                 # JSON, not a record
               json.dumps({"schema": SCHEMA, "revision": 9, "parameters": _p(1)}).replace(
                   '"value": 1.0', '"value": NaN').encode(),                     # another tool's NaN
               b"\xff\xfe binary"]
    path.write_bytes(b"\n".join([good[0], *garbage, good[1]]) + b"\n")
    reader = ParameterHistory(path)
    assert [r["revision"] for r in reader.records()] == [1, 2]
    assert [s.split(":")[0] for s in reader.skipped] == ["line 2", "line 3", "line 4", "line 5"]
    assert "not JSON" in reader.skipped[0] and "not a history record" in reader.skipped[1]
    assert "non-finite number NaN" in reader.skipped[2] and "UTF-8" in reader.skipped[3]
    [warn] = reader.take_warnings()
    assert str(path) in warn and "4 damaged line(s)" in warn
    with ParameterHistory(path) as h:
        said = h.open_writer()
        assert h.append(_p(3))["revision"] == 3
    assert len(said) == 1 and "line 2" in said[0]
    aside = _damaged(path)
    assert [d["line"] for d in aside] == [2, 3, 4, 5]
    assert aside[0]["text"] == "this is not json" and aside[3]["text"].startswith("\\xff\\xfe")
    assert b"this is not json" in path.read_bytes()              # never dropped from the history itself
    with ParameterHistory(path) as h:                            # the next writer: reported again, not copied twice
        assert len(h.open_writer()) == 1
    assert len(_damaged(path)) == 4


WRITER = """
import sys
from maglev_ros.errors import UserError
from maglev_ros.updating.history import ParameterHistory
try:
    rec = ParameterHistory(sys.argv[1]).append({"kp_a_per_m": {"value": 5.0}})
except UserError as exc:
    print(exc)
    sys.exit(1)
print("revision", rec["revision"])
"""


def test_a_second_writer_in_another_process_is_refused_naming_file_and_holder(tmp_path):
    path = tmp_path / "h.jsonl"
    env = dict(os.environ, PYTHONPATH=str(HERE.parent) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, "-c", WRITER, str(path)]
    with ParameterHistory(path) as h:
        h.append(_p(1))
        p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60)
        assert p.returncode == 1, p.stdout + p.stderr
        msg = p.stdout.strip()
        assert "\n" not in msg and str(path) in msg and f"pid {os.getpid()}" in msg, msg
        assert h.append(_p(2))["revision"] == 2                  # the first writer is unaffected
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60)   # released: next writer
    assert p.returncode == 0 and p.stdout.split() == ["revision", "3"], p.stdout + p.stderr
    assert [json.loads(l)["revision"] for l in _lines(path) if l] == [1, 2, 3]


def test_a_second_writer_in_this_process_is_refused(tmp_path):
    path = tmp_path / "h.jsonl"
    first = ParameterHistory(path)
    first.append(_p(1))
    with pytest.raises(UserError, match="already has a writer"):
        ParameterHistory(path).append(_p(2))
    assert ParameterHistory(path).last()["revision"] == 1        # readers need no lock
    first.close()
    assert ParameterHistory(path).append(_p(2))["revision"] == 2


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, "12", None])
def test_a_non_finite_parameter_is_refused_naming_it(tmp_path, bad):
    path = tmp_path / "h.jsonl"
    with ParameterHistory(path) as h:
        h.append(_p(1))
        before = path.read_bytes()
        with pytest.raises(UserError, match=r"parameter kv_a_s_per_m: value .* is not a finite number"):
            h.append({**_p(2), "kv_a_s_per_m": {"value": bad}})
        assert path.read_bytes() == before
        rec = h.append({"kp_a_per_m": {"value": np.float32(2.0), "std": math.nan}}, {"nrmse": np.inf})
    stored = ParameterHistory(path).last()
    assert rec["revision"] == stored["revision"] == 2
    assert stored["parameters"]["kp_a_per_m"] == {"value": 2.0, "std": None}   # unknown std: null
    assert stored["data_used"] == {"nrmse": None}


def test_the_updater_core_warns_and_goes_on_when_a_value_is_not_finite(tmp_path):
    from maglev_ros.updating.online import OnlineUpdater
    path = tmp_path / "h.jsonl"
    up = OnlineUpdater(path)

    def result(kp):
        u = SimpleNamespace(nrmse_nominal=0.5, nrmse_updated=0.2, names=("kp_a_per_m",), values=(kp,), std=(None,),
                            identifiable=(True,), identifiability=SimpleNamespace(combinations=()), uncertainty={},
                            n_model_evaluations=1)
        return {"update": u, "data_used": {"kind": "vehicle window"}, "log": None}
    assert up.accept_magnet_update(result(math.nan)) is None
    assert up.revision == 0 and up.current == {} and not path.exists()
    assert any("parameter kp_a_per_m" in w and "not a finite number" in w for w in up.warnings)
    assert not any("accepted" in line for line in up.log)
    pub = up.accept_magnet_update(result(1800.0))
    assert pub.revision == 1 and pub.values == (1800.0,)


def test_temp_files_of_older_versions_are_removed_on_open(tmp_path):
    path = tmp_path / "twin_parameters.jsonl"
    _write_history(path, 3)
    left = []
    for _ in range(3):      # what the earlier whole-file-rewrite version left when killed before its rename
        fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=tmp_path)
        os.write(fd, path.read_bytes())
        os.close(fd)
        left.append(Path(tmp))
    others = [tmp_path / "other.jsonl.abcdefgh.tmp", tmp_path / "twin_parameters.jsonl.mine.tmp"]
    for o in others:
        o.write_text("not ours")
    with ParameterHistory(path) as h:
        said = h.open_writer()
        assert h.append(_p(4))["revision"] == 4
    assert not any(p.exists() for p in left)
    assert all(o.exists() for o in others)
    assert len(said) == 1 and "removed 3 temp file(s)" in said[0] and str(path) in said[0]


def _append_forever(path: str, conn) -> None:
    h = ParameterHistory(path)
    i = 0
    while True:
        i += 1
        conn.send(h.append(_p(i), {"i": i})["revision"])   # sent only once the record is fsync'ed


def test_writers_killed_at_random_leave_a_readable_history_with_every_acknowledged_record(tmp_path):
    path = tmp_path / "h.jsonl"
    ctx = mp.get_context("fork")
    rng = np.random.default_rng(27)
    acked: list[int] = []
    for _ in range(30):
        recv, send = ctx.Pipe(duplex=False)
        p = ctx.Process(target=_append_forever, args=(str(path), send))
        p.start()
        send.close()
        for _ in range(int(rng.integers(1, 6))):
            acked.append(recv.recv())
        os.kill(p.pid, signal.SIGKILL)                           # anywhere in the next append
        p.join()
        while recv.poll():                                       # acknowledged before the kill landed
            try:
                acked.append(recv.recv())
            except EOFError:
                break
        recv.close()
    h = ParameterHistory(path)
    revs = [r["revision"] for r in h.records()]
    assert revs == list(range(1, len(revs) + 1))                 # strictly increasing, unique, no gaps
    assert set(acked) <= set(revs) and len(acked) == len(set(acked))
    aside = {d["line"] for d in _damaged(path)}
    assert len(h.skipped) == 0 or all(int(s.split()[1].rstrip(":")) in aside for s in h.skipped)
    assert not [q.name for q in tmp_path.iterdir() if q.name.endswith(".tmp")]
    with ParameterHistory(path) as w:
        assert w.append(_p(0))["revision"] == len(revs) + 1


def test_an_append_writes_one_line_whatever_the_length_of_the_history(tmp_path, monkeypatch):
    real_write, real_fsync = os.write, os.fsync
    per_append = {}
    for n in (10, 5000):
        path = tmp_path / f"h{n}.jsonl"
        _write_history(path, n)
        with ParameterHistory(path) as h:
            h.open_writer()
            size0 = path.stat().st_size
            calls = {"write": [], "fsync": 0}

            def write(fd, data):
                calls["write"].append(len(data))
                return real_write(fd, data)

            def fsync(fd):
                calls["fsync"] += 1
                return real_fsync(fd)

            def no_whole_file(*a, **k):
                raise AssertionError("an append read or replaced the whole history")
            monkeypatch.setattr(os, "write", write)
            monkeypatch.setattr(os, "fsync", fsync)
            monkeypatch.setattr(os, "replace", no_whole_file)
            monkeypatch.setattr(ParameterHistory, "_read_bytes", no_whole_file)
            rec = h.append(_p(n + 1))
            monkeypatch.undo()
        last = _lines(path)[-2] + b"\n"
        assert rec["revision"] == n + 1 and json.loads(last)["revision"] == n + 1
        assert calls["write"] == [len(last)] and calls["fsync"] == 1
        assert path.stat().st_size - size0 == len(last)
        per_append[n] = len(last)
    assert per_append[5000] <= per_append[10] + 8                # a longer revision number, nothing more


def test_a_failed_write_leaves_no_partial_record_and_says_so(tmp_path, monkeypatch):
    path = tmp_path / "h.jsonl"
    real_write = os.write
    with ParameterHistory(path) as h:
        h.append(_p(1))
        before = path.read_bytes()
        monkeypatch.setattr(os, "write", lambda fd, data: real_write(fd, data[:20]))   # disk full mid-line
        with pytest.raises(UserError, match=r"cannot append to the parameter history .*revision 2 not stored"):
            h.append(_p(2))
        monkeypatch.undo()
        assert path.read_bytes() == before
        assert h.append(_p(2))["revision"] == 2
    assert [r["revision"] for r in ParameterHistory(path).records()] == [1, 2]


def test_a_history_removed_under_its_writer_is_written_again_with_its_records(tmp_path):
    path = tmp_path / "h.jsonl"
    with ParameterHistory(path) as h:
        h.append(_p(1))
        h.append(_p(2))
        path.unlink()                                            # a cleanup script, a user
        assert h.append(_p(3))["revision"] == 3
        [said] = h.take_warnings()
        assert "removed by another program" in said and str(path) in said
        with pytest.raises(UserError, match="already has a writer"):   # still the one writer of the new file
            ParameterHistory(path).append(_p(9))
    assert [r["parameters"] for r in ParameterHistory(path).records()] == [_p(1), _p(2), _p(3)]


def test_a_history_replaced_under_its_writer_continues_there_with_increasing_revisions(tmp_path):
    path = tmp_path / "h.jsonl"
    with ParameterHistory(path) as h:
        h.append(_p(1))
        h.append(_p(2))
        _write_history(tmp_path / "restored.jsonl", 1)           # e.g. a backup put back with mv
        os.replace(tmp_path / "restored.jsonl", path)
        assert h.append(_p(3))["revision"] == 3                  # never a revision handed out twice
        [said] = h.take_warnings()
        assert "replaced by another program" in said
    assert [r["revision"] for r in ParameterHistory(path).records()] == [1, 3]


@pytest.mark.ros
def test_a_second_updater_node_on_the_same_history_exits_with_one_line(tmp_path):
    path = tmp_path / "h.jsonl"
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id(170)), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONPATH=str(HERE.parent) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    with ParameterHistory(path) as h:
        h.open_writer()
        p = subprocess.run([sys.executable, "-m", "maglev_ros.nodes.updater", "--ros-args",
                            "-p", f"history_path:={path}", "-p", "magnet_layer:=false"],
                           env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 1, p.stdout + p.stderr
    err = [l for l in p.stderr.splitlines() if l.strip()]
    assert len(err) == 1 and "Traceback" not in p.stderr, p.stderr
    assert str(path) in err[0] and f"pid {os.getpid()}" in err[0] and "already has a writer" in err[0]
