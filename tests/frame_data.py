"""The measured weimar-frame ambient vibration (``../shared/realdata/weimar-frame``, see its
README) as a contract ambient recording, and shared-data locations for tests.

Columns 0-2 are laser velocities, 3-4 accelerations (README); the contract wants accelerations
in m/s^2, so the velocities are differentiated (central differences: zero phase, amplitude
error sin(w dt)/(w dt) < 1.2 % below 10 Hz at 256 Hz; poles are unaffected). Column 5 is
excluded, as the README says.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
FRAME_DIR = SHARED / "realdata" / "weimar-frame"
PARTNER_SIM = SHARED / "validation" / "partner-sim"
FRAME_FS_HZ = 256.0
FRAME_CHANNELS = ("vib_l", "vib_r", "vib_t", "ref_x", "ref_y")
# the README's reference table (koma-python SSI-cov, an independent peer), means over setups 1-3
FRAME_REFERENCE_HZ = np.array([1.2288, 1.4356, 2.1000, 4.0170, 4.7706, 6.6822, 7.6156, 9.6652])
# the README's modes above 11 Hz (decimate-by-3 run): real, allowed beside the 8
FRAME_EXTRA_HZ = np.array([12.1668, 12.5982, 13.7448, 13.8631])


def frame_accelerations(setup: int = 1) -> np.ndarray:
    """(61440, 5) accelerations [m/s^2] of one setup: velocities differentiated."""
    x = np.load(FRAME_DIR / f"measurement_{setup}" / f"measurement_{setup}.npy")[:, :5]
    a = np.array(x, dtype=float)
    a[:, :3] = np.gradient(x[:, :3], 1.0 / FRAME_FS_HZ, axis=0)
    return a


def write_frame_bag(path, setup: int = 1) -> Path:
    """Contract ambient recording of one setup (guideway accel topic, 5 channels, 256 Hz)."""
    from bagfactory import GUIDEWAY_ACCEL, make_metadata, write_contract_bag
    names = tuple(f"S{setup}_{c}" for c in FRAME_CHANNELS)
    topics = {GUIDEWAY_ACCEL: (names, ("m/s^2",) * len(names), FRAME_FS_HZ,
                               frame_accelerations(setup))}
    md = make_metadata(topics, kind="ambient", n_spans=1, span_length_m=1.0,
                       extra={"description": f"weimar-frame setup {setup} (measured steel frame, "
                                             f"pyOMA test data); laser velocities differentiated"})
    return write_contract_bag(path, md, topics)
