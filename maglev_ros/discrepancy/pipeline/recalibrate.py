"""Re-calibration of the twin after: the calibrated parameters re-fitted with the found physics in it.

The base calibration ran without the physics the twin leaves out, so its global parameters absorbed
part of it (a control delay the gains and the girder's E, rho, kb partly mimic; a soft bearing the
span's E). Once the physics is chosen, E, kb, kp, kv and rho are fitted again on the training pass
with the physics' own parameters held, on the rail that twin reconstructs, and the result is kept
only when the held-out passes (each with the re-calibrated twin's own rail) fit better than with
the twin after as judged. With one pass the held-out check is the training pass itself.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..evaluate import fit_report
from ..fitting import fit_base
from ..model import ModelSpec
from .calibrate import Calibration


@dataclass(frozen=True, eq=False)
class Recalibration:
    spec: ModelSpec                    # the twin after: re-calibrated when that held, else as judged
    rd_all: list                       # every pass as that twin sees it
    heldout_before: float              # held-out NRMSE of the twin after as judged
    heldout_after: float               # ... re-calibrated with the physics (inf: not tried)
    kept: bool
    why: str

    def to_dict(self, spec_before: ModelSpec) -> dict:
        return {"kept": self.kept, "heldout_nrmse_as_judged": self.heldout_before,
                "heldout_nrmse_recalibrated": self.heldout_after, "why": self.why,
                "parameters_as_judged": spec_before.calibrated_values(),
                "parameters_recalibrated": self.spec.calibrated_values() if self.kept else None}


def recalibrate(cal: Calibration, spec: ModelSpec, rd_all: list, config) -> Recalibration:
    """``spec``: the twin after (calibrated + chosen physics), ``rd_all``: the passes as it sees them."""
    test = (lambda rds: rds[:1]) if cal.same_heldout else (lambda rds: rds[1:])
    held0, _ = fit_report(spec, test(rd_all))
    try:
        bf = fit_base(spec, rd_all[:1], config.base_max_nfev)
        rd_new = cal.prepare(bf.spec, log=None).rd_all
        held1, _ = fit_report(bf.spec, test(rd_new))
    except (FloatingPointError, ValueError, ZeroDivisionError, np.linalg.LinAlgError) as exc:
        return Recalibration(spec, rd_all, held0, float("inf"), False, f"re-calibration failed ({exc})")
    if held1 < held0:
        return Recalibration(bf.spec, rd_new, held0, held1, True,
                             f"re-calibrated with the found physics: held-out NRMSE {held0:.3f} -> {held1:.3f}")
    return Recalibration(spec, rd_all, held0, held1, False,
                         f"re-calibrating with the found physics did not fit the held-out passes better "
                         f"({held0:.3f} -> {held1:.3f}): the parameters as judged are kept")
