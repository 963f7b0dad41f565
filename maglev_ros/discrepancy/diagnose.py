"""The diagnosis: recordings -> calibrated twin -> located mismatches -> tested physics -> report.

``Diagnoser(config).fit(passes, ambient=None) -> Diagnosis``; ``Diagnosis.to_dict()`` is the public
``maglev-diagnosis/1`` JSON. ``fit`` runs the stages of :mod:`.pipeline`, each a module with a typed
result: calibrate (what the recordings measure directly, then E, kb, kp, kv; the fastest pass
trains, the others are held out), localize (where twin and recordings differ), propose (which
catalogue physics to fit in full), fit (each hypothesis fitted on the training pass and measured on
the held-out ones), judge (the hypotheses against each other), discover (what the catalogue does not
hold, judged by the same gates) and report. With a single pass the held-out set is that same pass
and the report says so in ``rejected`` (weaker evidence).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from maglev_ros.errors import UserError
from maglev_ros.parallel import SERIAL, Executor, one_blas_thread
from maglev_ros.progress import NULL, Progress

from .acceptance import AcceptanceConfig
from .pipeline.calibrate import calibrate
from .pipeline.discover import discover_stage
from .pipeline.fit import fit_hypotheses
from .pipeline.judge import judge_hypotheses
from .pipeline.localize import localize
from .pipeline.propose import propose
from .pipeline.report import SCHEMA, Diagnosis, build_report
from .recording import Recording, require_pass

__all__ = ["SCHEMA", "DiagnoseConfig", "Diagnoser", "Diagnosis", "diagnose"]


@dataclass(frozen=True)
class DiagnoseConfig:
    n_top: int = 4                    # physics hypotheses fully fitted after screening
    n_elements: int | None = None     # FE mesh of the diagnosing twin (None: design defaults)
    acceptance: AcceptanceConfig = AcceptanceConfig()
    base_max_nfev: int = 6
    dropout_min_s: float = 0.1
    dt_max_s: float | None = None     # integration step of the diagnosing twin (None: design numerics)
    irregularity: bool = True         # drive the twin with the irregularity reconstructed from each pass
    # the diagnosing twin's rail keeps the long waves that drive the car body (0-6 Hz): the time high-pass
    # follows the pass (None: the lowest corner whose filter settling takes at most half the longest
    # clean stretch, the irregularity verb's rule; 0.52 Hz on an 8.5 s pass, 0.22-0.41 Hz on 11-20 s
    # ones), the longest wave = pass speed / (band_factor x corner) with band factor 1 (the verb's 2 cut
    # the 15-60 m waves of fast passes: a cubic air spring was no longer found), the band-pass edge
    # trimmed by trim_wavelengths of it at each end and the integrator's edges 0.6 / corner (edge_s None).
    # A fixed 0.6 Hz corner cut a slow foreign pass's 5-10 m waves by 60-80 % (1.5-8 m correlation with
    # the true rail 0.93-0.99; 0.995 with the pass's own corner). The short end follows the data too
    # (irregularity.twin_input: a grid of one sample step, the Wiener gain of the noise measured on the pass)
    irregularity_highpass_hz: float | None = None
    irregularity_band_factor: float = 1.0
    irregularity_trim_wavelengths: float = 0.5
    irregularity_edge_s: float | None = None
    # passes over one line share their short waves (every pass's magnets average the same rail: half
    # the noise with two passes; a foreign clean case's twin floor at its true parameters 0.110 -> 0.102);
    # kept apart when the passes differ by more than their noise (another rail, a position shift)
    irregularity_shared: bool = True
    base_refit_nfev: int = 4          # calibration steps after the irregularity is rebuilt
    # besides the n_top best-screened: the best of every further effect and every girder/bearing
    # hypothesis of the spans the strongest guideway mismatches name (False: the n_top only)
    fit_every_effect: bool = True
    # damaged zones (a quarter of a measured span) besides the uniform loss of each span: None fits them
    # where the ambient recording's mode ratio of the span is off the twin's (:func:`.pipeline.propose.zones_to_try`)
    girder_zones: bool | None = None


class Diagnoser:
    def __init__(self, config: DiagnoseConfig = DiagnoseConfig()):
        self.config = config

    # ------------------------------------------------------------------------------------
    def fit(self, passes: Sequence[Recording], ambient: Recording | None = None,
            progress: Progress = NULL, executor: Executor = SERIAL) -> Diagnosis:
        """``executor``: where the independent hypotheses are screened and fitted
        (:mod:`maglev_ros.parallel`; the report is the same wherever they run). BLAS runs at one
        thread here too: two threads fight over the twin's 34x34 eigenproblems (sample bags, shared
        2-core machine: 104 s CPU with two, 69 s with one, the same report.json)."""
        with one_blas_thread():
            return self._fit(passes, ambient, progress, executor)

    def _fit(self, passes, ambient, progress, executor) -> Diagnosis:
        if not passes:
            raise UserError("--pass: at least one pass recording is needed")
        for p in passes:
            require_pass(p)
        cfg = self.config
        cal = calibrate(passes, ambient, cfg, progress)              # what the data measure, then E, kb, kp, kv
        loc = localize(cal, ambient, cfg, progress)                  # where twin and recordings differ
        prop = propose(cal, loc, cfg, progress, executor)            # which physics to fit in full
        fr = fit_hypotheses(cal, loc, prop, cfg, progress, executor) # each fitted and measured on held-out data
        jd = judge_hypotheses(cal, loc, fr, cfg, progress)           # the best against each other
        dc = discover_stage(cal, loc, prop, jd, cfg, progress)       # what the catalogue does not hold
        return build_report(cal, loc, prop, fr, jd, dc, ambient, cfg, progress)


def diagnose(passes: Sequence[Recording], ambient: Recording | None = None,
             config: DiagnoseConfig = DiagnoseConfig(), progress: Progress = NULL,
             executor: Executor = SERIAL) -> Diagnosis:
    return Diagnoser(config).fit(passes, ambient, progress, executor)
