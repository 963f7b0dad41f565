"""The diagnosis as named stages, each with a typed result: calibrate -> localize -> propose ->
(fit, judge: still in :class:`..diagnose.Diagnoser`) -> report. The stage modules hold the order
and the bookkeeping; the physics and statistics they call live in the modules of
:mod:`maglev_ros.discrepancy`."""
