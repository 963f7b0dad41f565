"""The diagnosis as named stages, each a module with a typed result:

calibrate -> :class:`.calibrate.Calibration`, localize -> :class:`.localize.Localization`,
propose -> :class:`.propose.Proposal`, fit -> :class:`.fit.Fits`, judge -> :class:`.judge.Judgement`,
discover -> :class:`.discover.Discovery`, report -> :class:`.report.Diagnosis` (it re-calibrates the
twin after with the found physics in it first: :class:`.recalibrate.Recalibration`).

The stage modules hold the order and the bookkeeping; the physics and the statistics they call live
in the modules of :mod:`maglev_ros.discrepancy` (model, catalogue, fitting, acceptance, localize,
discovery, resonator, ...). :class:`maglev_ros.discrepancy.diagnose.Diagnoser` runs them in order.
"""
