"""Optional contract extension `acquisition.<topic>.delay_s` (docs/contract-extensions.md)."""
import numpy as np
import pytest

from maglev_ros.contract import metadata_from_dict
from maglev_ros.errors import ContractError
from maglev_ros.twin.sensors import AntiAlias, InstrumentChain, NoiseSpec, anti_alias_delay_s

BASE = {"schema": "maglev-testline/1", "line": {"spans": [{"id": "S1", "start_m": 0.0, "length_m": 12.0}]},
        "sensors": {}, "run": {"kind": "ambient"}}


def test_delay_read_from_metadata_defaults_to_zero():
    md = metadata_from_dict(dict(BASE, acquisition={"/testline/vehicle/accel": {"delay_s": 0.002}}), "bag")
    assert md.acquisition_delay_s("/testline/vehicle/accel") == 0.002
    assert md.acquisition_delay_s("/testline/vehicle/gap") == 0.0
    assert metadata_from_dict(BASE, "bag").acquisition_delay_s("/testline/vehicle/accel") == 0.0


def test_bad_delay_names_the_key():
    md = metadata_from_dict(dict(BASE, acquisition={"/testline/vehicle/gap": {"delay_s": -1}}), "bag")
    with pytest.raises(ContractError, match=r"acquisition\./testline/vehicle/gap\.delay_s"):
        md.acquisition_delay_s("/testline/vehicle/gap")


@pytest.mark.parametrize("spec", [AntiAlias(), AntiAlias("bessel", 8, 0.2), AntiAlias("butterworth", 4, 0.3)])
def test_stated_delay_equals_the_measured_lag_of_the_chain(spec):
    """Independent reference: the lag of a slow sine through the (noise-free) chain."""
    fs_out, over = 1000.0, 4
    fs_int = fs_out * over
    t = np.arange(int(20 * fs_int)) / fs_int
    f = 2.0
    x = np.sin(2 * np.pi * f * t)[:, None]
    ch = InstrumentChain(["a"], fs_out, over, spec, NoiseSpec())
    y = ch.process(x)[:, 0]
    ty = t[over - 1::over][: y.size]
    keep = ty > 5.0
    # least-squares phase of y against the input sine at the output instants
    a, b = np.linalg.lstsq(np.column_stack([np.sin(2 * np.pi * f * ty[keep]), np.cos(2 * np.pi * f * ty[keep])]),
                           y[keep], rcond=None)[0]
    lag_s = -np.arctan2(b, a) / (2 * np.pi * f)
    assert anti_alias_delay_s(spec, fs_out, fs_int) == pytest.approx(lag_s, rel=0.02, abs=2e-6)
