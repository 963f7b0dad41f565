"""``maglev-ros batch`` without a cluster: manifests (CSV, YAML) and their one-line errors, the
--glob pairing of passes with ambients, and one job run in-process (a failure leaves no directory)."""
from __future__ import annotations

import json
from datetime import datetime, timezone

import numpy as np
import pytest

from bagfactory import GUIDEWAY_ACCEL, make_metadata, write_contract_bag
from maglev_ros.batch.jobs import Job, run_job
from maglev_ros.batch.manifest import jobs_from_glob, jobs_from_manifest, pair_ambient
from maglev_ros.cli import main
from maglev_ros.errors import UserError

DAY_S = 86400
T0_S = 1_790_000_000


def _bag(path, kind: str, day: float):
    fs = 100.0
    y = np.sin(2 * np.pi * 7.0 * np.arange(100) / fs)[:, None] * np.ones((1, 2))
    topics = {GUIDEWAY_ACCEL: (("G1LV", "G2LV"), ("m/s^2",) * 2, fs, y)}
    return write_contract_bag(path, make_metadata(topics, kind=kind), topics, t0_ns=int((T0_S + day * DAY_S) * 1e9))


@pytest.fixture(scope="module")
def line(tmp_path_factory):
    """An ambient on days 0 and 2, passes on days -1, 1, 1.5 and 3."""
    d = tmp_path_factory.mktemp("line")
    bags = {"amb0": _bag(d / "amb0.mcap", "ambient", 0), "amb2": _bag(d / "amb2.mcap", "ambient", 2),
            "p_early": _bag(d / "p_early.mcap", "pass", -1), "p1": _bag(d / "p1.mcap", "pass", 1),
            "p15": _bag(d / "p15.mcap", "pass", 1.5), "p3": _bag(d / "p3.mcap", "pass", 3)}
    (d / "notes.txt").write_text("not a recording")
    return d, bags


def test_glob_pairs_each_pass_with_the_last_ambient_before_it(line):
    d, bags = line
    jobs = {j.name: j for j in jobs_from_glob(str(d / "*"), "diagnose")}
    assert set(jobs) == {"p_early", "p1", "p15", "p3"}            # the passes; ambients and notes are not jobs
    amb = {n: j.ambient for n, j in jobs.items()}
    assert amb == {"p_early": str(bags["amb0"].resolve()),             # none before: the first after
                   "p1": str(bags["amb0"].resolve()), "p15": str(bags["amb0"].resolve()),
                   "p3": str(bags["amb2"].resolve())}
    # info runs on every recording, with no ambient
    assert {j.name: j.ambient for j in jobs_from_glob(str(d / "*.mcap"), "info")} == {n: None for n in bags}
    assert pair_ambient(5.0, []) is None


def test_glob_update_without_an_ambient_is_one_line(line, tmp_path, capsys):
    d, _ = line
    assert main(["batch", "update", "--glob", str(d / "p*.mcap"), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no ambient recording" in err[0] and "--glob" in err[0]


def test_csv_and_yaml_manifests(line, tmp_path):
    d, bags = line
    csv_m = d / "m.csv"
    csv_m.write_text("# passes of the week\nbag,name,ambient,args,time\n"
                     "p1.mcap,first,amb0.mcap,--max-modes 3 --seed 2,2026-09-22T10:00:00\n"
                     f"{bags['p3']},,amb2.mcap,,\n")
    a = jobs_from_manifest(csv_m, "update")
    yaml_m = d / "m.yaml"
    yaml_m.write_text("recordings:\n"
                      "  - {bag: p1.mcap, name: first, ambient: amb0.mcap, args: [--max-modes, '3', --seed, '2'],"
                      " time: '2026-09-22T10:00:00+00:00'}\n"
                      f"  - {{bag: {bags['p3']}, ambient: amb2.mcap}}\n")
    b = jobs_from_manifest(yaml_m, "update")
    strip = [(j.name, j.bag, j.ambient, j.args, j.time_unix_s) for j in a]
    assert strip == [(j.name, j.bag, j.ambient, j.args, j.time_unix_s) for j in b]
    assert strip[0] == ("first", str(bags["p1"].resolve()), str(bags["amb0"].resolve()),
                        ("--max-modes", "3", "--seed", "2"), datetime(2026, 9, 22, 10, tzinfo=timezone.utc).timestamp())
    assert strip[1][0] == "p3" and strip[1][4] is None


@pytest.mark.parametrize("text, verb, where, says", [
    ("bag,speed\np1.mcap,3\n", "info", "line 1", "unknown column 'speed'"),
    ("bag\nnope.mcap\n", "info", "line 2", "no such recording"),
    ("bag\np1.mcap\n", "update", "line 2", "needs the ambient"),
    ("bag,args\np1.mcap,--json x.json\n", "modes", "line 2", "set by batch"),
    ("bag,args\np1.mcap,--max-order many\n", "modes", "line 2", "invalid int value"),
    ("bag,name\np1.mcap,a\np3.mcap,a\n", "info", "line 2", "used by more than one"),
    ("bag,time\np1.mcap,yesterday\n", "info", "line 2", "ISO 8601"),
])
def test_manifest_mistakes_are_one_line_naming_the_row(line, text, verb, where, says):
    d, _ = line
    m = d / "bad.csv"
    m.write_text(text)
    with pytest.raises(UserError) as e:
        jobs_from_manifest(m, verb)
    msg = str(e.value)
    assert "\n" not in msg and f"bad.csv: {where}" in msg and says in msg


def test_failed_job_leaves_no_directory_and_says_why(line, tmp_path):
    d, bags = line
    out = tmp_path / "out"
    res = run_job(Job("amb0", "irregularity", str(bags["amb0"])), str(out))
    assert res.status == "failed" and "/testline/vehicle/accel missing" in res.error
    assert "\n" not in res.error and "irregularity" in res.log_tail
    assert not (out / "amb0").exists() and not any((out / ".work").iterdir())
    ok = run_job(Job("p1", "info", str(bags["p1"])), str(out))
    assert ok.status == "done" and (out / "p1" / "info.json").is_file()
    assert json.loads((out / "p1" / "job.json").read_text())["metrics"]["message_count"] == ok.metrics["message_count"]
    assert ok.time_unix_s == pytest.approx(T0_S + DAY_S, abs=1e-6)


def test_done_job_is_returned_and_a_changed_one_replaces_its_directory(line, tmp_path):
    d, bags = line
    out = tmp_path / "out"
    job = Job("p1", "info", str(bags["p1"]))
    first = run_job(job, str(out))
    mtime = (out / "p1" / "job.json").stat().st_mtime_ns
    again = run_job(job, str(out))                   # a retry of a finished job: nothing rerun
    assert again.status == "done" and (out / "p1" / "job.json").stat().st_mtime_ns == mtime
    assert again.worker == first.worker
    changed = run_job(Job("p1", "info", str(bags["p1"]), args=("--no-check",)), str(out))
    doc = json.loads((out / "p1" / "job.json").read_text())
    assert changed.status == "done" and doc["argv"][-1] == "--no-check"
    assert json.loads((out / "p1" / "info.json").read_text())["checked"] is False
    assert sorted(p.name for p in out.iterdir()) == [".work", "p1"] and not any((out / ".work").iterdir())


def test_modes_job_equals_the_direct_run(tmp_path):
    from modal_data import guideway_model, simulate_ambient
    model = guideway_model(None)
    fs = 200.0
    y = simulate_ambient(model, fs, 8.0, noise_frac=0.05, seed=1)[:, :6]
    topics = {GUIDEWAY_ACCEL: (model.channels[:6], ("m/s^2",) * 6, fs, y)}
    bag = write_contract_bag(tmp_path / "amb.mcap", make_metadata(topics, kind="ambient"), topics)
    res = run_job(Job("amb", "modes", str(bag)), str(tmp_path / "out"))
    assert res.status == "done", res.error
    direct = tmp_path / "direct.json"
    assert main(["modes", str(bag), "--json", str(direct)]) == 0
    doc = json.loads(direct.read_text())
    assert json.loads((tmp_path / "out" / "amb" / "modes.json").read_text()) == doc
    assert res.metrics["n_modes"] == len(doc["modes"]) >= 1
    assert res.trend["mode frequency [Hz]"]["series"]["modes"] == [m["frequency_hz"] for m in doc["modes"]]
