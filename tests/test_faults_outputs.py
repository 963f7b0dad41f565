"""Outputs under faults (issue 27): every verb checks its output targets before the work and writes
each file atomically; a write failing midway leaves the earlier outputs byte-identical and no
temporary or partial file behind; JSON is strict (a non-finite number is null).

How failures are made without root tricks: where the verb is quick it runs in a subprocess under
RLIMIT_FSIZE with SIGXFSZ ignored, so the kernel itself refuses the write (EFBIG) midway; where the
failing file is smaller than one written before it (simulate's truth.json after the bag) or the
computation is stubbed (diagnose, minutes of work), os.fsync is made to fail with ENOSPC for that
one file in-process. An unwritable directory is emulated by os.open refusing to create files in it
(EACCES), since root ignores permission bits.
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bagfactory import (GUIDEWAY_ACCEL, METADATA_TOPIC, SENSORBLOCK_TYPE, VEHICLE_ACCEL,
                        VEHICLE_GAP, VEHICLE_POSITION, Faults, example_topics, foreign_typestore,
                        make_metadata, write_contract_bag, write_foreign_bag)
from irregularity_data import make_recording
from maglev_ros.cli import main

ROOT = Path(__file__).resolve().parents[1]
EFBIG = os.strerror(errno.EFBIG)        # "File too large"
ENOSPC = os.strerror(errno.ENOSPC)      # "No space left on device"


# ------------------------------------------------------------------------------ helpers
def snapshot(directory: Path) -> dict:
    """Every file and directory under ``directory`` (hidden ones too) with its content hash."""
    out = {}
    for p in sorted(directory.rglob("*")):
        rel = str(p.relative_to(directory))
        out[rel] = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
    return out


def one_error_line(err: str, verb: str) -> str:
    """The single line the CLI prints for a user-facing failure (no traceback)."""
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"maglev-ros {verb}: error: "), err
    return lines[0]


def run_cli(argv, capsys):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def run_limited(argv, limit_bytes: int) -> subprocess.CompletedProcess:
    """The CLI in a subprocess that may not write any file beyond ``limit_bytes`` (EFBIG)."""
    code = ("import resource, runpy, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
            f"resource.setrlimit(resource.RLIMIT_FSIZE, ({limit_bytes}, {limit_bytes})); "
            "sys.argv = ['maglev-ros', *sys.argv[1:]]; "
            "runpy.run_module('maglev_ros.cli', run_name='__main__')")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return subprocess.run([sys.executable, "-c", code, *map(str, argv)], capture_output=True,
                          text=True, env=env, cwd=ROOT, timeout=300)


def fail_fsync_of(monkeypatch, target_name: str, err: int = errno.ENOSPC) -> None:
    """os.fsync fails with ``err`` for the temporary file written for ``target_name``."""
    real = os.fsync

    def fsync(fd):
        name = os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))
        if name.startswith(f".{target_name}."):
            raise OSError(err, os.strerror(err))
        return real(fd)
    monkeypatch.setattr(os, "fsync", fsync)


def deny_create_in(monkeypatch, directory: Path) -> None:
    """No file can be created in ``directory``, as in a read-only one (root ignores chmod)."""
    real = os.open
    prefix = str(directory) + os.sep

    def open_(path, flags, *a, **k):
        if flags & os.O_CREAT and os.fspath(path).startswith(prefix):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fspath(path))
        return real(path, flags, *a, **k)
    monkeypatch.setattr(os, "open", open_)


# ----------------------------------------------------------------------------- recordings
def _pass_bag(rec, path: Path) -> Path:
    topics = {VEHICLE_ACCEL: (rec.accel.channels, rec.accel.units, rec.accel.sample_rate_hz, rec.accel.data),
              VEHICLE_GAP: (rec.gap.channels, rec.gap.units, rec.gap.sample_rate_hz, rec.gap.data),
              VEHICLE_POSITION: (rec.position.channels, rec.position.units, rec.position.sample_rate_hz,
                                 rec.position.data)}
    md = make_metadata(topics, magnet_offsets_m=rec.magnet_offsets_m, nominal_speed_mps=rec.info["speed_mps"])
    return write_contract_bag(path, md, topics)


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    from maglev_ros.twin.simulate import simulate
    d = tmp_path_factory.mktemp("bags")
    simulate("paper-ambient", d / "amb", sets=["duration_s=10"], seed=3)
    rec = make_recording(40, 31, "constant", length_m=150.0, fs_hz=500.0)
    good = _pass_bag(rec, d / "pass")
    # magnet 2 silent (zero acceleration, constant gap): its correlation with the others is undefined
    rec.accel.data[:, 1] = 0.0
    rec.gap.data[:, 1] = rec.nominal_gap_m
    flat = _pass_bag(rec, d / "flat")
    return SimpleNamespace(amb=d / "amb", pass_=good, flat=flat)


# ------------------------------------------------------------- targets checked before the work
# name: (verb, argv(target, bags, tmp), option, kind of target, file suffix)
CASES = {
    "modes --json": ("modes", lambda t, b, d: ["modes", b.amb, "--json", t], "--json", "file", ".json"),
    "modes --plot": ("modes", lambda t, b, d: ["modes", b.amb, "--plot", t], "--plot", "file", ".png"),
    "irregularity --out": ("irregularity", lambda t, b, d: ["irregularity", b.pass_, "--out", t],
                           "--out", "file", ".csv"),
    "irregularity --json": ("irregularity", lambda t, b, d: ["irregularity", b.pass_, "--out", d / "ok.csv",
                                                             "--json", t], "--json", "file", ".json"),
    "irregularity --plot": ("irregularity", lambda t, b, d: ["irregularity", b.pass_, "--out", d / "ok.csv",
                                                             "--plot", t], "--plot", "file", ".png"),
    "update --out": ("update", lambda t, b, d: ["update", "--ambient", b.amb, "--out", t, "--quiet"],
                     "--out", "file", ".json"),
    "update --details": ("update", lambda t, b, d: ["update", "--ambient", b.amb, "--out", d / "ok.json",
                                                    "--details", t, "--quiet"], "--details", "file", ".json"),
    "update --plot": ("update", lambda t, b, d: ["update", "--ambient", b.amb, "--out", d / "ok.json",
                                                 "--plot", t, "--quiet"], "--plot", "dir", ""),
    "diagnose --out": ("diagnose", lambda t, b, d: ["diagnose", "--pass", b.pass_, "--out", t, "--quiet"],
                       "--out", "dir", ""),
    "simulate --out": ("simulate", lambda t, b, d: ["simulate", "paper-ambient", "--out", t, "--set",
                                                    "duration_s=2", "--quiet"], "--out", "bag", ""),
}
FAULTS = ("missing_dir", "dir_is_a_file", "unwritable", "target_is_a_dir")


@pytest.fixture
def forbid_compute(monkeypatch):
    """Any verb that starts its work before its output check fails the test."""
    import maglev_ros.commands.irregularity
    import maglev_ros.commands.modes
    import maglev_ros.discrepancy.recording
    import maglev_ros.twin.simulate
    import maglev_ros.updating.pipeline

    def computed(*a, **k):
        raise AssertionError("the verb started its work before checking its outputs")
    for mod, name in ((maglev_ros.commands.modes, "identify_modes"),
                      (maglev_ros.commands.irregularity, "read_inputs"),
                      (maglev_ros.updating.pipeline, "update_from_bags"),
                      (maglev_ros.discrepancy.recording, "load_recording"),
                      (maglev_ros.twin.simulate, "run_scenario")):
        monkeypatch.setattr(mod, name, computed)


@pytest.mark.parametrize("fault", FAULTS)
@pytest.mark.parametrize("case", list(CASES))
def test_output_target_checked_before_the_work(case, fault, bags, tmp_path, monkeypatch, forbid_compute,
                                               capsys):
    verb, argv, option, kind, suffix = CASES[case]
    if fault == "missing_dir" and kind == "dir":
        pytest.skip("a missing output directory is created (with its parents)")
    if fault == "target_is_a_dir" and kind != "file":
        pytest.skip("the target is a directory by design (or a bag directory, replaced with --overwrite)")
    work = tmp_path / "work"
    work.mkdir()
    (work / "afile").write_text("a regular file\n")
    (work / "ro").mkdir()
    name = "x" + suffix
    target, reason = {
        "missing_dir": (work / "no_such_dir" / name, "does not exist"),
        "dir_is_a_file": (work / "afile" / name, "afile"),
        "unwritable": (work / "ro" / name, os.strerror(errno.EACCES)),
        "target_is_a_dir": (work / "ro", "is a directory"),
    }[fault]
    if fault == "unwritable":
        deny_create_in(monkeypatch, work / "ro")
    before = snapshot(work)
    rc, out, err = run_cli(argv(target, bags, work), capsys)
    assert rc == 1
    line = one_error_line(err, verb)
    assert f"{option} {target}" in line and reason in line, line
    assert snapshot(work) == before          # nothing created, nothing left behind


# ------------------------------------------------------------------ a write failing midway
def test_modes_write_failing_midway_keeps_the_earlier_pair(bags, tmp_path, capsys):
    d = tmp_path / "out"
    d.mkdir()
    js, png = d / "modes.json", d / "stab.png"
    rc, _, _ = run_cli(["modes", bags.amb, "--json", js, "--plot", png, "--fmax-hz", "60"], capsys)
    assert rc == 0
    limit = 60_000
    assert js.stat().st_size < limit // 4 and png.stat().st_size > limit   # JSON staged, plot fails
    before = snapshot(d)
    r = run_limited(["modes", bags.amb, "--json", js, "--plot", png], limit)
    assert r.returncode == 1
    line = r.stderr.strip().splitlines()[-1]
    assert "Traceback" not in r.stderr and line.startswith("maglev-ros modes: error: ")
    assert f"--plot {png}" in line and EFBIG in line, line
    assert snapshot(d) == before             # the earlier JSON and plot byte-identical, no temp file
    # the same run without the limit replaces both (the failed run changed nothing a rerun needs)
    rc, _, _ = run_cli(["modes", bags.amb, "--json", js, "--plot", png], capsys)
    after = snapshot(d)
    assert rc == 0 and set(after) == set(before) and all(after[k] != before[k] for k in before)


def test_irregularity_write_failing_midway_keeps_csv_json_and_plot(bags, tmp_path, capsys):
    d = tmp_path / "out"
    d.mkdir()
    paths = [d / "irr.csv", d / "irr.json", d / "irr.png"]
    argv = ["irregularity", bags.pass_, "--out", paths[0], "--json", paths[1], "--plot", paths[2]]
    rc, _, _ = run_cli(argv + ["--spacing-m", "0.5"], capsys)
    assert rc == 0
    limit = 20_000
    csv_b, json_b = paths[0].stat().st_size, paths[1].stat().st_size
    assert csv_b < limit < json_b              # the CSV is staged, the JSON fails midway
    before = snapshot(d)
    r = run_limited(argv, limit)
    assert r.returncode == 1
    line = r.stderr.strip().splitlines()[-1]
    assert "Traceback" not in r.stderr and f"--json {paths[1]}" in line and EFBIG in line, r.stderr
    assert snapshot(d) == before


def test_irregularity_refusing_a_silent_magnet_keeps_the_earlier_outputs(bags, tmp_path, capsys):
    """Reproduced: a silent magnet made a correlation NaN; the JSON writer refused it midway after
    the CSV had been overwritten, leaving a truncated JSON and a traceback. The sensor-health check
    now refuses the recording (the magnet's only accelerometer is flat) in one line, before any
    output is touched."""
    csv_p, js = tmp_path / "irr.csv", tmp_path / "irr.json"
    rc, _, err = run_cli(["irregularity", bags.pass_, "--out", csv_p, "--json", js], capsys)
    assert rc == 0, err
    before = snapshot(tmp_path)
    rc, _, err = run_cli(["irregularity", bags.flat, "--out", csv_p, "--json", js], capsys)
    assert rc == 1 and "Traceback" not in err
    line = err.strip().splitlines()[-1]
    assert "M2A" in line and "flat" in line
    assert snapshot(tmp_path) == before


def test_update_write_failing_midway_keeps_earlier_outputs_and_removes_a_new_plot_dir(bags, tmp_path, capsys):
    d = tmp_path / "out"
    d.mkdir()
    common = ["update", "--ambient", bags.amb, "--out", d / "params.json", "--details", d / "details.json",
              "--swarm", "4", "4", "--max-modes", "1", "--quiet"]
    rc, _, err = run_cli(common + ["--plot", d / "plots", "--seed", "1"], capsys)
    assert rc == 0, err
    assert sorted(p.name for p in (d / "plots").iterdir()) == ["frequencies.png", "pareto.png"]
    limit = 10_000
    assert (d / "params.json").stat().st_size < limit < (d / "plots" / "pareto.png").stat().st_size
    before = snapshot(d)
    # params.json is staged, the first plot in a new directory fails
    r = run_limited(common + ["--plot", d / "plots_new", "--seed", "2"], limit)
    assert r.returncode == 1
    line = r.stderr.strip().splitlines()[-1]
    assert "Traceback" not in r.stderr and f"--plot {d / 'plots_new'}" in line and EFBIG in line, r.stderr
    assert snapshot(d) == before               # no plots_new, no temp file, earlier files untouched


@pytest.fixture
def stub_diagnosis(monkeypatch):
    """diagnose's minutes of work replaced by a fixed result: these tests are about its files."""
    import maglev_ros.discrepancy.diagnose
    import maglev_ros.discrepancy.recording
    import maglev_ros.discrepancy.report_html
    runs = []

    class Diagnosis:
        def __init__(self, n):
            self.n = n

        def to_dict(self):
            return {"schema": "maglev-diagnosis/1", "run": self.n, "fit_before": {"nrmse": 0.5},
                    "fit_after": {"nrmse": float("nan")}, "mismatches": [], "missing_physics": []}

    def diagnose(passes, ambient, progress=None, **_options):
        runs.append(1)
        return Diagnosis(len(runs))
    monkeypatch.setattr(maglev_ros.discrepancy.recording, "load_recording",
                        lambda p: SimpleNamespace(kind="pass", path=p))
    monkeypatch.setattr(maglev_ros.discrepancy.diagnose, "diagnose", diagnose)
    monkeypatch.setattr(maglev_ros.discrepancy.report_html, "render",
                        lambda d: f"<html><body>report {d.n}</body></html>\n")
    return runs


def test_diagnose_report_pair_replaced_together_or_not_at_all(bags, tmp_path, monkeypatch, stub_diagnosis,
                                                              capsys):
    out = tmp_path / "diag" / "run1"          # created with its parent
    argv = ["diagnose", "--pass", bags.pass_, "--out", out, "--quiet"]
    rc, _, err = run_cli(argv, capsys)
    assert rc == 0, err
    rep = json.loads((out / "report.json").read_text(), parse_constant=lambda c: 1 / 0)
    assert rep["run"] == 1 and rep["fit_after"]["nrmse"] is None        # NaN written as null
    assert (out / "report.html").read_text() == "<html><body>report 1</body></html>\n"
    before = snapshot(tmp_path)
    fail_fsync_of(monkeypatch, "report.html")   # report.json is staged first, then the HTML fails
    rc, _, err = run_cli(argv, capsys)
    assert rc == 1
    line = one_error_line(err, "diagnose")
    assert str(out / "report.html") in line and ENOSPC in line, line
    assert snapshot(tmp_path) == before
    # a failing run into a new directory leaves no directory behind
    rc, _, err = run_cli(["diagnose", "--pass", bags.pass_, "--out", tmp_path / "new" / "d", "--quiet"], capsys)
    assert rc == 1 and ENOSPC in one_error_line(err, "diagnose")
    assert snapshot(tmp_path) == before


def test_diagnose_no_html_drops_the_stale_html(bags, tmp_path, stub_diagnosis, capsys):
    out = tmp_path / "d"
    rc, _, _ = run_cli(["diagnose", "--pass", bags.pass_, "--out", out, "--quiet"], capsys)
    assert rc == 0 and (out / "report.html").is_file()
    rc, _, _ = run_cli(["diagnose", "--pass", bags.pass_, "--out", out, "--quiet", "--no-html"], capsys)
    assert rc == 0
    assert sorted(p.name for p in out.iterdir()) == ["report.json"]
    assert json.loads((out / "report.json").read_text())["run"] == 2


def test_simulate_full_disk_keeps_the_earlier_bag_and_sidecar(tmp_path, capsys):
    d = tmp_path / "out"
    d.mkdir()
    bag = d / "amb"
    argv = ["simulate", "paper-ambient", "--out", bag, "--set", "duration_s=2", "--quiet"]
    rc, _, err = run_cli(argv + ["--seed", "1"], capsys)
    assert rc == 0, err
    assert (d / "amb.truth.json").is_file()
    limit = 20_000
    assert max(p.stat().st_size for p in bag.iterdir()) > 2 * limit
    before = snapshot(d)
    r = run_limited(argv + ["--seed", "2", "--overwrite"], limit)
    assert r.returncode == 1
    line = r.stderr.strip().splitlines()[-1]
    assert "Traceback" not in r.stderr and str(bag) in line and EFBIG in line, r.stderr
    assert snapshot(d) == before               # earlier bag and truth intact, no .partial-* directory


def test_simulate_truth_failing_leaves_no_bag_and_a_rerun_works(tmp_path, monkeypatch, capsys):
    """Reproduced: the truth sidecar failed after the bag was complete, leaving a 0-byte
    truth.json beside it, and the rerun refused the existing bag."""
    d = tmp_path / "out"
    d.mkdir()
    argv = ["simulate", "paper-ambient", "--out", d / "amb", "--set", "duration_s=2", "--quiet", "--seed", "1"]
    fail_fsync_of(monkeypatch, "amb.truth.json")
    rc, _, err = run_cli(argv, capsys)
    assert rc == 1
    line = one_error_line(err, "simulate")
    assert str(d / "amb.truth.json") in line and ENOSPC in line, line
    assert list(d.iterdir()) == []             # no bag, no sidecar, no temp file, no .partial-*
    monkeypatch.undo()
    rc, _, err = run_cli(argv, capsys)
    assert rc == 0, err
    truth = json.loads((d / "amb.truth.json").read_text())
    assert truth["bag"] == "amb" and truth["seed"] == 1 and (d / "amb" / "metadata.yaml").is_file()


# ---------------------------------------------------------------------------- strict JSON
def _nan_rate_bag(path: Path) -> Path:
    """A bag whose first guideway block says sample_rate_hz NaN (the rest are fine)."""
    from rosbags.rosbag2 import Writer
    store = foreign_typestore()
    Msg, Header, Time, String = (store.types[t] for t in (SENSORBLOCK_TYPE, "std_msgs/msg/Header",
                                                         "builtin_interfaces/msg/Time", "std_msgs/msg/String"))
    topics = example_topics(duration_s=0.3, seed=2)
    chans, units, rate, data = topics[GUIDEWAY_ACCEL]
    md = make_metadata({GUIDEWAY_ACCEL: topics[GUIDEWAY_ACCEL]})
    with Writer(path, version=8) as w:
        c = w.add_connection(METADATA_TOPIC, "std_msgs/msg/String", typestore=store)
        w.write(c, 1, store.serialize_cdr(String(data=json.dumps(md)), "std_msgs/msg/String"))
        c = w.add_connection(GUIDEWAY_ACCEL, SENSORBLOCK_TYPE, typestore=store)
        n = int(rate * 0.1)
        for k in range(3):
            m = Msg(header=Header(stamp=Time(sec=1, nanosec=k * 100_000_000), frame_id="g"),
                    sample_rate_hz=float("nan") if k == 0 else float(rate), channels=list(chans),
                    units=list(units), data=np.ascontiguousarray(data[k * n:(k + 1) * n], np.float32).ravel())
            w.write(c, 2 + k, store.serialize_cdr(m, SENSORBLOCK_TYPE))
    return path


def _strict_loads(text: str):
    def refuse(c):
        raise ValueError(f"non-standard JSON constant {c}")
    return json.loads(text, parse_constant=refuse)


def test_info_json_is_strict_on_a_nan_rate(tmp_path, capsys):
    bag = _nan_rate_bag(tmp_path / "nanrate")
    rc, out, err = run_cli(["info", "--json", bag], capsys)
    assert rc == 1 and "bad_rate" in one_error_line(err, "info")      # the report, then the error
    rep = _strict_loads(out)
    topic = next(t for t in rep["topics"] if t["topic"] == GUIDEWAY_ACCEL)
    assert topic["sample_rate_hz"] is None


def test_info_json_is_strict_on_nan_samples(tmp_path, capsys):
    topics = example_topics(duration_s=0.5, seed=4)
    bag = write_foreign_bag(tmp_path / "nan", make_metadata(topics), topics,
                            faults=Faults(nan={GUIDEWAY_ACCEL: [(1, 2, 0)]}, inf={VEHICLE_GAP: [(0, 0, 1)]}))
    rc, out, err = run_cli(["info", "--json", bag], capsys)
    assert rc == 1
    rep = _strict_loads(out)
    assert {(i["kind"], i["topic"]) for i in rep["issues"] if i["severity"] == "error"} >= \
        {("nan", GUIDEWAY_ACCEL), ("nan", VEHICLE_GAP)}


# ------------------------------------------------------------------------- the helper itself
def test_write_json_strict_and_file_mode_like_a_plain_write(tmp_path):
    from maglev_ros import outputs
    p = tmp_path / "a.json"
    outputs.write_json(p, {"x": [1.5, float("nan"), float("inf"), -float("inf")], "n": np.int64(3),
                           "f": np.float32(0.5)}, default=float)
    assert _strict_loads(p.read_text()) == {"x": [1.5, None, None, None], "n": 3.0, "f": 0.5}
    plain = tmp_path / "plain"
    plain.write_text("x")
    assert p.stat().st_mode & 0o777 == plain.stat().st_mode & 0o777
    os.chmod(p, 0o640)                         # an existing file keeps its mode
    outputs.write_text(p, "{}")
    assert p.stat().st_mode & 0o777 == 0o640 and p.read_text() == "{}"
    assert sorted(q.name for q in tmp_path.iterdir()) == ["a.json", "plain"]


@pytest.mark.parametrize("verb", ["modes", "irregularity"])
def test_unknown_figure_format_is_one_line_before_the_work(verb, bags, tmp_path, forbid_compute, capsys):
    bag = bags.amb if verb == "modes" else bags.pass_
    extra = ["--out", tmp_path / "x.csv"] if verb == "irregularity" else []
    rc, _, err = run_cli([verb, bag, *extra, "--plot", tmp_path / "diagram.txt"], capsys)
    assert rc == 1
    line = one_error_line(err, verb)
    assert f"--plot {tmp_path / 'diagram.txt'}" in line and "'.txt'" in line and ".png" in line, line
    assert list(tmp_path.iterdir()) == []
