"""Guideway modal identification (no rclpy).

- :mod:`.ssi_cov`: :class:`SSICov` (covariance-driven SSI, automatic stabilization-diagram
  interpretation, block-based uncertainty), :class:`ModalResult`, :class:`Mode`;
- :mod:`.free_decay`: free-decay window after a vehicle pass and identification from it;
- :mod:`.bands`: SSI-cov settings chosen from the recording and identification in several
  frequency bands, merged (``maglev-ros modes``' defaults);
- :mod:`.transmissibility`: :class:`TransmissibilityID` (PSD transmissibility / half-spectra
  rational-fraction fit with Forsythe polynomials, the paper's route);
- :mod:`.tracking`: :class:`StreamingSSI` (sliding windows, recursive covariances) and
  :class:`ModeTracker` (stable ids, new/lost events, running uncertainty);
- :mod:`.stabilization`: stability criteria, pole clustering, MAC/MPC/MPD;
- :mod:`.plot`: stabilization diagram over the singular-value spectrum.
"""
from maglev_ros.modal.ssi_cov import SCHEMA, ModalResult, Mode, SSICov

__all__ = ["SCHEMA", "ModalResult", "Mode", "SSICov"]
