"""Progress of long work: the plain-line renderer's throttling and heartbeat, the renderer choice
(terminal, pipe, --quiet), and the stages and counts the diagnosis and a command announce."""
import io
import os
import sys

import pytest

sys.path.insert(0, os.path.dirname(__file__))

from maglev_ros.cli import main  # noqa: E402
from maglev_ros.progress import NULL, BarProgress, PlainProgress, RecordingProgress, for_cli  # noqa: E402


class FakeClock:
    def __init__(self):
        self.now_s = 100.0

    def __call__(self):
        return self.now_s


def _plain(clock, **kw):
    out = io.StringIO()
    return PlainProgress("job", out, clock=clock, ticker=False, **{"start_delay_s": 0.0} | kw), out


def test_plain_lines_are_throttled_but_stages_and_notes_always_show():
    clock = FakeClock()
    p, out = _plain(clock, min_interval_s=3.0, heartbeat_s=5.0)
    try:
        p.stage("fit", total=10)
        for _ in range(10):            # ten steps 0.5 s apart: one count line per 3 s
            clock.now_s += 0.5
            p.advance(note="h")
        p.note("a message")
        clock.now_s += 0.1
        p.stage("report")
    finally:
        p.done()
    lines = out.getvalue().splitlines()
    assert lines[0].endswith("job: fit (0/10)")
    counts = [ln for ln in lines if "fit: " in ln]
    # at 3.0 s (6/10) only: the next 3 s have not passed when the stage ends at 5.0 s
    assert len(counts) == 1 and "6/10 (60 %)" in counts[0] and "ETA 2s" in counts[0] and counts[0].endswith("- h")
    assert any(ln.endswith("job: a message") for ln in lines)
    assert lines[-2].endswith("job: report") and lines[-1].endswith("job: done")


def test_plain_heartbeat_during_a_long_single_step():
    clock = FakeClock()
    p, out = _plain(clock, min_interval_s=3.0, heartbeat_s=5.0)
    try:
        p.stage("calibrate", total=4)
        for _ in range(23):            # 23 s without a finished step: a line each 5 s
            clock.now_s += 1.0
            p.tick()
    finally:
        p.done()
    beats = [ln for ln in out.getvalue().splitlines() if "working" in ln]
    assert len(beats) == 4
    assert "calibrate: 0/4 (0 %), 5s in stage - working" in beats[0]
    assert "20s in stage" in beats[-1]


def test_only_the_innermost_renderer_beats():
    clock = FakeClock()
    outer, out_o = _plain(clock, heartbeat_s=5.0)
    inner, out_i = _plain(clock, heartbeat_s=5.0)
    try:
        outer.stage("analysis")
        inner.stage("update")
        clock.now_s += 6.0
        outer.tick()
        inner.tick()
        assert "working" not in out_o.getvalue() and "working" in out_i.getvalue()
        inner.done()
        clock.now_s += 6.0
        outer.tick()
        assert "working" in out_o.getvalue()
    finally:
        inner.done()
        outer.done()


def test_lines_of_a_quick_failure_are_dropped_and_held_lines_keep_their_time():
    clock = FakeClock()
    p, out = _plain(clock, start_delay_s=2.0)
    with pytest.raises(RuntimeError):
        with p:
            p.stage("load recordings", total=1)
            clock.now_s += 0.5
            raise RuntimeError("bad input")
    assert out.getvalue() == ""
    p, out = _plain(clock, start_delay_s=2.0)
    with p:
        p.stage("load recordings", total=1)
        clock.now_s += 2.5
        p.tick()
        assert out.getvalue().splitlines() == ["[    0s] job: load recordings (0/1)"]
    assert out.getvalue().splitlines()[-1] == "[    2s] job: done"


def test_renderer_choice():
    assert for_cli(True, "x") is NULL

    class Tty(io.StringIO):
        def isatty(self):
            return True
    pipe, tty = io.StringIO(), Tty()
    p = for_cli(False, "x", pipe)
    q = for_cli(False, "x", tty, start_delay_s=0.0)
    try:
        assert isinstance(p, PlainProgress)
        assert isinstance(q, BarProgress)
        q.stage("fit", total=3)
        q.advance(2, note="h")
        q.tick()
        assert "2/3" in tty.getvalue() and "fit" in tty.getvalue()
    finally:
        q.done()
        p.done()


def test_simulate_progress_on_stderr_and_quiet_silences_it(tmp_path, capsys):
    argv = ["simulate", "paper-ambient", "--set", "duration_s=4", "--out"]
    assert main(argv + [str(tmp_path / "a")]) == 0
    cap = capsys.readouterr()
    assert "simulate: ambient guideway response" in cap.err and "simulate: done" in cap.err
    assert "wrote" in cap.out and "simulate:" not in cap.out
    assert main(argv + [str(tmp_path / "b"), "--quiet"]) == 0
    cap = capsys.readouterr()
    assert cap.err == "" and "wrote" in cap.out


@pytest.fixture(scope="module")
def small_case():
    from discrepancy_cases import make_case
    # an ambient vibration the diagnosis accepts: no open-ended discovery after it (test time ~20 s)
    return make_case("progress", "ambient_excitation", {"rms_mps2": 0.02}, seed=21, speeds=(24.0, 30.0), n_spans=2,
                     variant={"n_el": 20, "noise_colour": "white", "ambient_s": 8.0, "body_sensors": False})


def test_diagnose_announces_its_stages_and_counts_every_hypothesis(small_case):
    from maglev_ros.discrepancy.diagnose import DiagnoseConfig, diagnose
    rec = RecordingProgress()
    cfg = DiagnoseConfig(n_top=1, base_max_nfev=2, base_refit_nfev=1, dt_max_s=2e-3, fit_every_effect=False)
    diagnose(small_case.passes, small_case.ambient, cfg, progress=rec)
    names = [n for n, _ in rec.stages]
    assert names[:3] == ["calibrate the twin", "locate mismatches", "screen catalogue hypotheses"]
    assert names[3].startswith("fit ") and names[3].endswith(" physics hypotheses (simulated)")
    assert names[4].startswith("fit ") and names[4].endswith(" sensor and ambient hypotheses")
    assert names[5:7] == ["held-out judgement (peers, combinations)", "discovery"]
    # the report stage, after re-calibrating the twin with what was found when something was
    assert names[7:] in (["report"], ["re-calibrate the twin with the found physics", "report"])
    totals = dict(rec.stages)
    # every stage with a count finished it: one advance per screened / fitted hypothesis
    for name in names[:5]:
        assert totals[name] and rec.advances[name] == totals[name], (name, totals[name], rec.advances[name])
    assert totals[names[2]] > totals[names[3]] >= 1          # n_top=1: the best-screened one is fitted
    assert rec.advances["locate mismatches"] == 3            # two passes and the ambient recording
