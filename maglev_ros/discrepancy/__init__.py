"""Discrepancy between twin and recordings: localize, name the missing physics, fit it, accept it.

Public entry points: :func:`maglev_ros.discrepancy.diagnose.diagnose` (recordings -> Diagnosis),
:mod:`.localize` (residual maps against the noise floor), :mod:`.catalogue` (physics extensions),
:mod:`.discovery` (open-ended: residual resonances), :mod:`.acceptance` (held-out + BIC gates).
"""
