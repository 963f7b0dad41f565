"""Simulated recordings with KNOWN (hidden) true parameters for the updating tests.

The truth differs from the nominal design (what the metadata's design block / defaults say) in the
guideway E, rho, kb (within +-15 %) and the controller gains (within +-30 %); the updater sees only the
nominal design and the measurements (with sensor noise), never the truth.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from maglev_ros.twin.coupling import simulate_pass
from maglev_ros.twin.design import line_spans, twin_config, with_guideway, with_levitation
from maglev_ros.twin.irregularity_psd import german_high_speed, random_profile

SPAN_M = 12.384
LINE = {"spans": [{"id": "S1", "start_m": 0.0, "length_m": SPAN_M},
                  {"id": "S2", "start_m": SPAN_M, "length_m": SPAN_M}]}
MID_S1 = 0.5 * SPAN_M


@dataclass(frozen=True)
class Truth:
    factors: dict            # parameter name -> true / nominal

    def config(self, nominal):
        g = {k: getattr(nominal.guideway, k) * v for k, v in self.factors.items() if hasattr(nominal.guideway, k)}
        l = {k: getattr(nominal.levitation, k) * v for k, v in self.factors.items() if hasattr(nominal.levitation, k)}
        return with_levitation(with_guideway(nominal, **g), **l)


def random_truth(seed: int) -> Truth:
    rng = np.random.default_rng(1000 + seed)
    f = {}
    for k in ("youngs_modulus_pa", "density_kg_m3", "bearing_stiffness_n_per_m"):
        f[k] = float(1 + rng.choice([-1, 1]) * rng.uniform(0.05, 0.15))
    for k in ("kp_a_per_m", "kv_a_s_per_m", "ka_a_s2_per_m"):
        f[k] = float(1 + rng.choice([-1, 1]) * rng.uniform(0.10, 0.30))
    return Truth(f)


def irregularity(seed: int, start_m: float = -30.0, length_m: float = 90.0):
    return random_profile(german_high_speed("low"), length_m, 0.01, (0.3, 20.0), rng=seed, start_m=start_m)


def simulate_measurement(cfg, speed_mps: float, irr_seed: int, duration_s: float, fs_hz: float = 500.0,
                         noise_seed: int = 0, accel_noise: float = 0.01, gap_noise_m: float = 5e-6,
                         disp_noise_m: float = 2e-6, start_position_m: float | None = None):
    """Dict of measured arrays (noise added) of one pass of the TRUE twin ``cfg``."""
    x, r = irregularity(irr_seed)
    res = simulate_pass(cfg, LINE, speed_mps, (x, r), sensors={"MID": MID_S1}, duration_s=duration_s,
                        fs_out_hz=fs_hz, start_position_m=start_position_m)
    rng = np.random.default_rng(noise_seed)
    n, m = res.magnet_accel_mps2.shape
    g0 = cfg.levitation.nominal_gap_m
    return {
        "time_s": res.time_s, "position_m": res.position_m, "speed_mps": res.speed_mps,
        "accel": res.magnet_accel_mps2 + accel_noise * rng.standard_normal((n, m)),
        "gap": res.magnet_gap_m + gap_noise_m * rng.standard_normal((n, m)),
        "disp_mid": res.guideway_disp_m[:, 0] + disp_noise_m * rng.standard_normal(n),
        "accel_mid": res.guideway_accel_mps2[:, 0],
        "offsets": np.asarray(cfg.vehicle.magnet_offsets_m), "g0": g0,
        "true_irregularity": (x, r), "magnet_force_static_n": None,
    }
