"""SSI-cov on measured ambient vibration (weimar-frame, ../shared/realdata next to the repo, see
its README).

Reference frequencies are the README's table (koma-python SSI-cov, an independent peer); the
README warns that their setup-to-setup scatter is not a general tolerance, so we compare within
0.5 %. Channels mix laser velocities (cols 0-2) and accelerations (cols 3-4), so shapes are not
mono-phase: the MPC filter is switched off for this data.
"""
from __future__ import annotations

import numpy as np
import pytest

from frame_data import FRAME_DIR as DATA
from frame_data import FRAME_REFERENCE_HZ as REFERENCE_HZ
from maglev_ros.modal.ssi_cov import SSICov
from maglev_ros.modal.stabilization import StabilityCriteria


@pytest.mark.skipif(not DATA.exists(), reason="weimar-frame data not available")
@pytest.mark.parametrize("setup", [1, 2, 3])
def test_weimar_frame_modes_below_11hz(setup):
    x = np.load(DATA / f"measurement_{setup}" / f"measurement_{setup}.npy")[:, :5]
    x = x - x.mean(axis=0)
    x = x / x.std(axis=0)                         # mixed units: scale each channel
    est = SSICov(block_rows=40, orders=range(2, 101, 2), decimate_to_hz=28.0,
                 freq_range_hz=(0.5, 11.0), criteria=StabilityCriteria(min_mpc=0.0))
    res = est.fit(x, 256.0, ["vib_l", "vib_r", "vib_t", "ref_x", "ref_y"])
    assert res.fs_hz == pytest.approx(256.0 / 9)
    f = res.frequencies_hz()
    for f0 in REFERENCE_HZ:
        assert np.min(np.abs(f - f0)) / f0 < 0.005, (f0, f)
    # nothing else below 11 Hz
    assert len(f) == REFERENCE_HZ.size
    z = np.array([m.damping_ratio for m in res.modes])
    assert np.all((z > 0) & (z < 0.02))
