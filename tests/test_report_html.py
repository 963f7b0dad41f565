"""The HTML diagnosis report as an engineer sees it, rendered by headless Chromium.

A fast diagnosis of a small simulated case with a concealed sensor scale fault; its recordings are
stamped in epoch seconds and read from absolute paths, as bags are. Checked: the screenshot is not
blank, the DOM holds the tables (recordings, mismatches, found physics and its parameters, updated
parameters) with units in their headers and cells, mismatches most severe first, times from each
recording's start, one sentence per statistic, and no machine path anywhere in the page.
"""
import dataclasses
import json
import os
import re
import shutil
import subprocess
import sys
from html.parser import HTMLParser

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))
from discrepancy_cases import make_case  # noqa: E402

from maglev_ros.discrepancy.diagnose import DiagnoseConfig, diagnose  # noqa: E402
from maglev_ros.discrepancy.report_html import render  # noqa: E402

CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if os.path.exists("/usr/bin/chromium") else None)
needs_chromium = pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium not installed (Debian: chromium)")
EPOCH_S = 1.7e9          # bag stamps are epoch seconds
STATISTICS = ("NRMSE", "held-out", "log-likelihood ratio", "delta BIC", "severity", "std", "nominal")


def _as_bag(rec, directory):
    """The recording as read from a bag: epoch stamps, its source an absolute path."""
    ch = {n: dataclasses.replace(c, time_s=c.time_s + EPOCH_S) for n, c in rec.channels.items()}
    pt = None if rec.position_time_s is None else rec.position_time_s + EPOCH_S
    return dataclasses.replace(rec, channels=ch, position_time_s=pt,
                               source=str(directory / rec.source.replace("/", "_")))


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    bags = tmp_path_factory.mktemp("bags")
    case = make_case("rep", "sensor_error", {"channel": "G2A", "kind": "scale", "value": 1.4}, seed=11,
                     speeds=(24.0, 30.0), variant={"n_el": 20, "noise_colour": "white", "ambient_s": 8.0},
                     n_spans=2)
    passes = [_as_bag(p, bags) for p in case.passes]
    ambient = _as_bag(case.ambient, bags)
    # only the cheap hypotheses fitted in full, few calibration steps, 2 ms twin step (test time)
    d = diagnose(passes, ambient, DiagnoseConfig(n_top=0, base_max_nfev=2, base_refit_nfev=1, dt_max_s=2e-3,
                                                 fit_every_effect=False))
    out = tmp_path_factory.mktemp("report")
    (out / "report.html").write_text(render(d))
    (out / "report.json").write_text(json.dumps(d.to_dict()))
    return out, d, [*passes, ambient]


def _chromium(tmp_path, *args):
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
           "--disable-component-update", "--disable-sync", "--no-first-run", f"--user-data-dir={tmp_path / 'prof'}",
           *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


class _Tables(HTMLParser):
    """Tables by id (header cells, body rows of cell texts), glossary terms, section ids."""

    def __init__(self):
        super().__init__()
        self.tables, self.terms, self.sections = {}, {}, set()
        self._tid = self._cell = self._row = self._dt = self._dd = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "section" and a.get("id"):
            self.sections.add(a["id"])
        elif tag == "table":
            self._tid = a.get("id")
            if self._tid:
                self.tables[self._tid] = {"head": [], "rows": []}
        elif tag == "tr" and self._tid:
            self._row = []
        elif tag in ("td", "th") and self._tid:
            self._cell = []
        elif tag == "dt":
            self._dt = []
        elif tag == "dd":
            self._dd = []

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self._row.append((tag, "".join(self._cell).strip()))
            self._cell = None
        elif tag == "tr" and self._row is not None:
            t = self.tables[self._tid]
            if all(k == "th" for k, _ in self._row):
                t["head"] = [x for _, x in self._row]
            else:
                t["rows"].append([x for _, x in self._row])
            self._row = None
        elif tag == "table":
            self._tid = None
        elif tag == "dt" and self._dt is not None:
            self._term, self._dt = "".join(self._dt).strip(), None
        elif tag == "dd" and self._dd is not None:
            self.terms[self._term] = "".join(self._dd).strip()
            self._dd = None

    def handle_data(self, data):
        for buf in (self._cell, self._dt, self._dd):
            if buf is not None:
                buf.append(data)


@pytest.fixture(scope="module")
def dom(report, tmp_path_factory):
    if CHROMIUM is None:
        pytest.skip("headless Chromium not installed (Debian: chromium)")
    out, _, _ = report
    res = _chromium(tmp_path_factory.mktemp("chromium"), "--dump-dom", (out / "report.html").as_uri())
    assert res.returncode == 0, res.stderr[-2000:]
    p = _Tables()
    p.feed(res.stdout)
    return p, res.stdout


def _column(table, name):
    i = table["head"].index(name)
    return [r[i] for r in table["rows"]]


@needs_chromium
def test_screenshot_is_not_blank(report, tmp_path):
    out, _, _ = report
    png = tmp_path / "report.png"
    res = _chromium(tmp_path, f"--screenshot={png}", "--window-size=1400,5000", (out / "report.html").as_uri())
    assert png.exists(), res.stderr[-2000:]
    from PIL import Image
    img = np.asarray(Image.open(png).convert("L"), float) / 255.0
    assert img.shape == (5000, 1400)
    # text, tables and plots: a good share of the page is not white, and it is not one flat colour
    assert np.mean(img < 0.9) > 0.05
    assert img.std() > 0.15
    # the plots are drawn, not broken images: dark pixels all down the page, not only at the top
    rows_inked = np.mean(img < 0.5, axis=1) > 0.01
    assert rows_inked[2500:].mean() > 0.1


@needs_chromium
def test_dom_holds_the_tables_with_units(dom):
    p, _ = dom
    assert {"summary", "glossary", "where", "chosen", "parameters", "before-after", "tried"} <= p.sections
    rec = p.tables["recordings"]
    assert {"recording", "duration [s]"} <= set(rec["head"]) and len(rec["rows"]) == 3
    par = p.tables["parameters"]
    assert {"unit", "nominal (design)", "updated", "std"} <= set(par["head"])
    assert len(par["rows"]) == 5           # E, kb, kp, kv, rho
    for unit, nominal, updated, std in zip(_column(par, "unit"), _column(par, "nominal (design)"),
                                           _column(par, "updated"), _column(par, "std")):
        assert unit and unit != "\u2014"
        float(nominal), float(updated)
        assert std == "\u2014" or std.startswith("\u2014 (") or float(std) > 0
    assert p.tables["physics"]["rows"], "the concealed sensor fault is found"
    phys = p.tables["physics-parameters"]
    assert {"parameter", "unit", "nominal (twin without it)", "found", "std"} <= set(phys["head"])
    assert phys["rows"] and all(u for u in _column(phys, "unit"))
    # a scale fault: the twin's sensor reads 1 (nominal); the found scale is a number beside it
    scale = [r for r in phys["rows"] if r[phys["head"].index("parameter")] == "scale"]
    assert scale and float(scale[0][phys["head"].index("nominal (twin without it)")]) == 1.0


@needs_chromium
def test_mismatches_most_severe_first_with_recording_and_time_from_start(dom, report):
    p, _ = dom
    _, _, recs = report
    mm = p.tables["mismatches"]
    assert {"recording", "time from start [s]", "severity [x noise power]"} <= set(mm["head"])
    sev = [float(x) for x in _column(mm, "severity [x noise power]")]
    assert len(sev) >= 2 and sev == sorted(sev, reverse=True)
    durations = {r.name: r.t1_s - r.t0_s for r in recs}
    named = 0
    for rec, span in zip(_column(mm, "recording"), _column(mm, "time from start [s]")):
        assert "/" not in rec and rec
        if rec in durations:
            named += 1
            t0, t1 = (float(x) for x in span.split("-"))
            assert 0.0 <= t0 <= t1 <= durations[rec] + 0.5
    assert named >= 1


@needs_chromium
def test_every_statistic_has_a_plain_sentence(dom):
    p, _ = dom
    for term in STATISTICS:
        assert term in p.terms and len(p.terms[term].split()) >= 8 and p.terms[term].endswith("."), term


def test_no_machine_paths_or_epoch_times_in_the_report(report):
    out, _, recs = report
    text = (out / "report.html").read_text()
    text = re.sub(r'src="data:image/png;base64,[^"]*"', "", text)
    for r in recs:
        assert os.path.isabs(r.source)
        assert r.source not in text and os.path.dirname(r.source) not in text
    assert "/tmp" not in text and not re.search(r"(?<![\w.])/(home|root|work|tmp|Users|var)/", text)
    # epoch stamps (>= 1e9 s) never show as times
    assert not re.search(r"\b1[0-9]{9}(\.[0-9]+)?\b", text)
    rep = json.loads((out / "report.json").read_text())
    assert "/tmp" not in json.dumps(rep)


def test_json_keeps_its_keys_and_adds_optional_ones(report):
    _, d, recs = report
    rep = d.to_dict()
    names = {r.name for r in recs}
    sev = [m["severity"] for m in rep["mismatches"]]
    assert sev == sorted(sev, reverse=True)
    for m in rep["mismatches"]:
        assert {"channels", "time_s", "position_m", "frequency_hz", "severity"} <= set(m)
        if m["recording"] in names:
            rec = next(r for r in recs if r.name == m["recording"])
            assert m["time_from_start_s"][0] == pytest.approx(m["time_s"][0] - rec.t0_s)
    det = rep["parameter_details"]
    assert set(det) == set(rep["updated_parameters"])
    for k, v in det.items():
        assert v["unit"] and v["updated"] == pytest.approx(rep["updated_parameters"][k]) and v["nominal"] > 0
        assert v["std"] is None or v["std"] > 0


def test_a_mismatch_with_its_own_words_is_shown_with_them(report):
    """A mismatch that is not a band of a residual map (the span's mode pattern) carries an explanation
    and whether the twin after explains it: the page says both, and the rest of it still renders."""
    import copy
    _, d, _ = report
    rep = copy.deepcopy(d.report)
    said = "Span S1's first two bending modes ring at 22.00 and 95.00 Hz in the ambient recording."
    rep["mismatches"].append({"channels": ["G1A"], "time_s": [0.0, 8.0], "position_m": [0.0, 12.384],
                              "frequency_hz": [22.0, 95.0], "severity": 12.0, "explanation": said,
                              "recording": "ambient (span S1's mode ratio)", "time_from_start_s": None,
                              "after_found_physics": {"ratio_shift": 0.031, "standard_errors": 9.0,
                                                      "explained": False}})
    page = render(dataclasses.replace(d, report=rep))
    assert said in page.replace("&#x27;", "'")
    assert "does not explain it (ratio still +3.1 %)" in page
    assert "per-channel NRMSE" in page


def test_the_report_states_the_sensor_delay_the_passes_measure(report):
    """The generator's instrument is a causal 4th-order Butterworth at 0.4 x its 1 kHz Nyquist,
    stated nowhere: the report gives its delay (group delay from scipy.signal, 12-60 Hz where the
    rails' short waves lie at 24-30 m/s) and says it was applied."""
    from scipy import signal
    out, _, _ = report
    rep = json.loads((out / "report.json").read_text())
    d = rep["calibration"]["sensor_delay"]
    _, gd = signal.group_delay(signal.butter(4, 0.4), w=np.linspace(12.0, 60.0, 6), fs=1000.0)
    assert d["applied"]
    assert gd.min() * 1e-3 - 3 * d["std_s"] <= d["delay_s"] <= gd.max() * 1e-3 + 3 * d["std_s"]
    assert "Sensor delay:" in (out / "report.html").read_text()


def test_the_report_states_what_limits_the_calibrated_fit(report):
    """The calibrated fit and the share of it the rail's reconstruction uncertainty makes (the
    floor's own numbers are checked against a noise-free twin in test_discrepancy_fit_floor)."""
    out, _, _ = report
    rep = json.loads((out / "report.json").read_text())
    f = rep["calibration"]["fit_floor"]
    assert f["calibrated_nrmse"] == pytest.approx(rep["fit_before"]["nrmse"])
    assert 0 < f["rail_uncertainty_nrmse"] <= f["calibrated_nrmse"]
    assert f["remainder_nrmse"] ** 2 + f["rail_uncertainty_nrmse"] ** 2 == pytest.approx(f["calibrated_nrmse"] ** 2)
    assert set(f["rail_uncertainty_per_group"]) <= set(rep["calibration"]["fit_per_group"])
    page = (out / "report.html").read_text()
    assert "What limits the calibrated fit" in page and f"{f['rail_uncertainty_nrmse']:.3f}" in page
